"""Docs in their place: short module docstrings, and measured figures only in docs/benchmarks.md.

A module docstring says what the module does, its units and frames, and the
rule in a few lines; the reasoning lives in docs/architecture.md and the
measured figures in docs/benchmarks.md, where they carry their conditions.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import mabdi

PACKAGE = Path(mabdi.__file__).resolve().parent
DOCS = PACKAGE.parent / "docs"
MAX_MODULE_DOCSTRING_LINES = 40

_NUMBER = r"\d+(?:\.\d+)?"
_UNIT = r"(?:ms|s|mm|cm|m|%|px|degrees|MB|GB)"

#: What counts as a measured figure: a value a run produced, written next to
#: the words that say so. Constants, defaults and spec-sheet facts (640 x 480,
#: 0.02 m, 45 degrees, "default 20 ms") match none of these.
MEASURED_FIGURE = {
    # "F@1cm 0.982", "R@1cm 0.86 at 1", "0.987 F@1cm"
    "an F-score, precision or recall with its value": re.compile(
        r"\b[FPR]@\d+(?:\.\d+)?\s?(?:cm|mm)\b[^.;\n]{0,25}?\b0\.\d{2,}" r"|\b0\.\d{3,}\b[^.;\n]{0,12}?\b[FPR]@\d"
    ),
    # "7.5 frames/s", "12 fps" (not a default: "default 10 frames/s")
    "a frame rate": re.compile(r"(?<!default )\b" + _NUMBER + r"\s?(?:frames?/s|fps)\b"),
    # "233 ms/frame", "40 ms a frame", "1.2 s per scan"
    "a time per frame": re.compile(_NUMBER + r"\s?(?:ms|milliseconds|s|seconds)\s?(?:/|a|per|each)\s?(?:frame|scan)\b"),
    # "Run 2 0.987", "on Run 2, 0.9874", "from 0.987 to 0.990 on Run 2"
    "a run's score": re.compile(r"\bRun [1-9]\b[^.;\n]{0,20}?\b0\.\d{3,}|\b0\.\d{3,}\b[^.;\n]{0,20}?\bon Run [1-9]\b"),
    # "measured: 12 ms", "10 degrees at sigma = 5 mm, measured"
    "a number called measured": re.compile(
        r"\bmeasured(?: at| on| as)?:?\s" + _NUMBER + r"\s?" + _UNIT + r"\b"
        r"|\b" + _NUMBER + r"\s?" + _UNIT + r"\b[^.;\n]{0,25}?,\s?measured\s*[.,;)]"
    ),
    # "2-3 times faster than VTK's locator"
    "a measured speed-up": re.compile(r"\b\d+(?:[.-]\d+)?\s?(?:times|x) (?:faster|slower)\b"),
}


def _modules() -> list[Path]:
    return sorted(PACKAGE.rglob("*.py"))


def module_docstring_lines(path: Path) -> int:
    """Lines of a module's docstring as written (0 without one)."""
    docstring = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8")), clean=False)
    return 0 if docstring is None else len(docstring.splitlines())


def measured_figures(text: str) -> list[tuple[int, str, str]]:
    """(line, kind, text) of every measured figure :data:`MEASURED_FIGURE` finds in ``text``."""
    found = []
    for kind, pattern in MEASURED_FIGURE.items():
        for match in pattern.finditer(text):
            found.append((text.count("\n", 0, match.start()) + 1, kind, match.group(0)))
    return sorted(found)


def _texts_outside_benchmarks() -> list[Path]:
    docs = [p for p in sorted(DOCS.glob("*.md")) if p.name != "benchmarks.md"] if DOCS.is_dir() else []
    return _modules() + docs + [PACKAGE.parent / "README.md"]


def test_module_docstrings_are_short():
    """Every module docstring under mabdi/ is at most 40 lines: the narrative is in docs/architecture.md."""
    lengths = {str(p.relative_to(PACKAGE.parent)): module_docstring_lines(p) for p in _modules()}
    long = {name: n for name, n in lengths.items() if n > MAX_MODULE_DOCSTRING_LINES}
    assert not long, f"module docstrings over {MAX_MODULE_DOCSTRING_LINES} lines: {long}"


def test_no_measured_figures_outside_benchmarks():
    """No measured figure in mabdi/'s source (docstrings, comments) or docs/ other than docs/benchmarks.md.

    What counts (:data:`MEASURED_FIGURE`): an F-score, precision or recall
    with its value ("F@1cm 0.982"); a frame rate ("7.5 frames/s", "12 fps");
    a time per frame or scan ("233 ms/frame", "40 ms a frame"); a run's
    score ("Run 2 0.987"); a number with a unit called measured
    ("measured: 12 ms", "10 degrees at 5 mm, measured"); a speed-up
    ("2-3 times faster"). Constants and spec facts do not.
    """
    found = [
        f"{path.relative_to(PACKAGE.parent)}:{line}: {kind}: {text!r}"
        for path in _texts_outside_benchmarks()
        for line, kind, text in measured_figures(path.read_text(encoding="utf-8"))
    ]
    assert not found, "measured figures belong in docs/benchmarks.md:\n" + "\n".join(found)


def test_the_detector_catches_what_it_names():
    """The detector flags the patterns it names and leaves constants and spec facts alone."""
    flagged = [
        "It lifts the tuned TSDF from F@1cm 0.982 to 0.991",
        "that costs recall, R@1cm 0.86 at 1",
        "on Run 2 0.9874",
        "and from 0.987 to 0.990 on Run 2.",
        "7.03 against 6.98 frames/s",
        "CPU 233 ms/frame over frames",
        "about 40 ms a frame",
        "a plane tilted by the noise (10 degrees at sigma = 5 mm, measured).",
        "2-3 times faster than VTK's locator",
    ]
    clean = [
        "a Kinect's 640 x 480 images",
        "epsilon the anticipated point noise (default 0.02 m, the seed's)",
        "their normals within 45 degrees",
        "within tolerance seconds of it (default 20 ms)",
        "written as if it ran at 30 frames per second",
        "a frame every 1 / rate seconds (default 10 frames/s)",
        "(F@1cm against the ground truth, in the benchmarks)",
        "a test compares the two on Run 1.",
        "the measured depth z = D, at most 0.05 m",
    ]
    assert all(measured_figures(text) for text in flagged), [t for t in flagged if not measured_figures(t)]
    assert not any(measured_figures(text) for text in clean), [t for t in clean if measured_figures(t)]
