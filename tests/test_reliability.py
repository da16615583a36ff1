"""Failures that must end a command cleanly: Ctrl-C, damaged input files, a full disk, damaged maps."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
INTERRUPTED = (130, -signal.SIGINT)  # main's exit status, or death by SIGINT (an interrupt while importing)


def _mabdi(*args, **kwargs) -> subprocess.Popen:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen(
        [sys.executable, "-m", "mabdi.cli", *map(str, args)],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        **kwargs,
    )


def _wait_for(predicate, process, timeout: float) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return True
        if process.poll() is not None:
            return False
        time.sleep(0.05)
    return False


def _finish(process, timeout: float = 60.0) -> tuple[int, str, str]:
    try:
        out, err = process.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        out, err = process.communicate()
        pytest.fail(f"the run went on for {timeout} s after Ctrl-C\nstdout: {out[-2000:]}\nstderr: {err[-2000:]}")
    return process.returncode, out, err


# -- Ctrl-C ---------------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("seconds_into_run", [0.0, 1.5, 3.0, 5.0])
def test_ctrl_c_during_a_run_exits_130(tmp_path, seconds_into_run):
    """SIGINT at several moments of the frame loop: exit 130, never 0, and no summary.json.

    400 frames take far longer than the moments chosen, so a run that swallowed the
    interrupt would run on (and fail by the timeout) or exit 0.
    """
    out = tmp_path / "run"
    process = _mabdi("run", "scenes/table.toml", "--frames", 400, "--out", out, "--no-eval", "--quiet")
    started = _wait_for(lambda: (out / "config.toml").exists(), process, timeout=120)
    assert started, f"the run did not start: {process.communicate()}"
    time.sleep(seconds_into_run)
    assert process.poll() is None, "the run ended before it was interrupted"
    process.send_signal(signal.SIGINT)
    code, stdout, stderr = _finish(process)
    assert code == 130, f"exit {code}\nstdout: {stdout[-2000:]}\nstderr: {stderr[-2000:]}"
    assert "mabdi: interrupted" in stderr
    assert "Traceback" not in stderr
    assert not (out / "summary.json").exists()
    assert not list(out.glob(".*.tmp*")), "a temporary file was left behind"


@pytest.mark.slow
def test_ctrl_c_while_starting_never_exits_0(tmp_path):
    """SIGINT before the run loop (imports, scene set-up) ends the process as interrupted too."""
    for delay in (0.5, 2.0):
        process = _mabdi("run", "scenes/table.toml", "--frames", 400, "--out", tmp_path / f"run{delay}", "--no-eval", "--quiet")
        time.sleep(delay)
        process.send_signal(signal.SIGINT)
        code, stdout, stderr = _finish(process)
        assert code in INTERRUPTED, f"exit {code}\nstderr: {stderr[-2000:]}"


@pytest.mark.slow
def test_ctrl_c_during_evaluation_exits_130(tmp_path):
    """SIGINT once the frames are done (the map is scored against the scene): 130, no summary with metrics."""
    out = tmp_path / "run"
    process = _mabdi("run", "scenes/table.toml", "--frames", 12, "--out", out, "--quiet")
    lines = []

    def evaluating() -> bool:
        line = process.stdout.readline()
        if line:
            lines.append(line)
        return any(line.startswith("map:") for line in lines)

    assert _wait_for(evaluating, process, timeout=240), f"no 'map:' line: {lines}"
    process.send_signal(signal.SIGINT)
    code, stdout, stderr = _finish(process)  # the evaluation takes seconds: the signal lands in it
    assert code == 130, f"exit {code}\nstderr: {stderr[-2000:]}"
    summary = out / "summary.json"
    assert not summary.exists() or "metrics" not in json.loads(summary.read_text())
