"""Ctrl-C that a library wraps in another exception still ends a command with 130 and one line.

numba turns a KeyboardInterrupt raised while it unpickles (boxing a kernel's result, loading a cached one)
into ``SystemError: ... returned a result with an exception set``, the KeyboardInterrupt its cause.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from mabdi import interrupts

REPO = Path(__file__).resolve().parents[1]


def _wrapped_interrupt() -> SystemError:
    """What numba raises: a SystemError whose cause is the KeyboardInterrupt."""
    try:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as interrupt:
            raise SystemError("CPUDispatcher(<function kernel>) returned a result with an exception set") from interrupt
    except SystemError as error:
        return error


def _run(out: Path, *options: str) -> list[str]:
    return ["run", str(REPO / "scenes" / "table.toml"), "--frames", "2", "--out", str(out), "--no-eval", "--quiet", *options]


def test_an_exception_is_an_interrupt_when_its_chain_holds_one_or_a_sigint_was_noted(monkeypatch):
    """:func:`mabdi.interrupts.caused_by_interrupt`: the cause or the context (at any depth), or the note."""
    monkeypatch.setattr(interrupts, "_interrupted", False)
    assert interrupts.caused_by_interrupt(KeyboardInterrupt())
    assert interrupts.caused_by_interrupt(_wrapped_interrupt())
    try:
        try:
            raise _wrapped_interrupt()
        except SystemError:
            raise RuntimeError("while handling it")  # noqa: B904 - the context, as a library's cleanup leaves it
    except RuntimeError as error:
        assert interrupts.caused_by_interrupt(error)
    assert not interrupts.caused_by_interrupt(ValueError("an error of its own"))
    circular = ValueError("a")
    circular.__context__ = TypeError("b")
    circular.__context__.__context__ = circular
    assert not interrupts.caused_by_interrupt(circular)
    monkeypatch.setattr(interrupts, "_interrupted", True)
    assert interrupts.caused_by_interrupt(ValueError("raised after a SIGINT came"))


def test_a_wrapped_interrupt_in_a_frame_exits_130_with_the_note(tmp_path, monkeypatch, capsys):
    """A SystemError from a KeyboardInterrupt raised in a frame's own code (removal here, refinement's kernel
    on the user's run): ``mabdi run`` exits 130 with ``mabdi: interrupted``, no traceback, no map."""
    from mabdi.cli import main
    from mabdi.stages.object_removal import ObjectRemoval

    def interrupted(*args, **kwargs):
        raise _wrapped_interrupt()

    monkeypatch.setattr(ObjectRemoval, "find", interrupted)
    assert main(_run(tmp_path / "run")) == 130
    stderr = capsys.readouterr().err
    assert "mabdi: interrupted" in stderr and "Traceback" not in stderr and "SystemError" not in stderr
    assert not (tmp_path / "run" / "world_mesh.vtp").exists()


def test_a_wrapped_interrupt_in_a_pipeline_request_exits_130(tmp_path, monkeypatch, capsys):
    """The same raised inside a VTK request (the simulated sensor's): stored by the algorithm, raised as an interrupt."""
    from mabdi.cli import main
    from mabdi.render.depth_image import FilterDepthImage

    def interrupted(self, request, inInfo, outInfo):  # noqa: N803 (VTK API)
        raise _wrapped_interrupt()

    monkeypatch.setattr(FilterDepthImage, "RequestData", interrupted)
    assert main(_run(tmp_path / "run")) == 130
    stderr = capsys.readouterr().err
    assert "mabdi: interrupted" in stderr and "Traceback" not in stderr


def test_any_error_after_a_noted_sigint_exits_130(tmp_path, monkeypatch, capsys):
    """An error of any kind raised in a frame after a SIGINT was noted (its KeyboardInterrupt lost on the way)."""
    from mabdi.cli import main
    from mabdi.stages.object_removal import ObjectRemoval

    def interrupted(*args, **kwargs):
        interrupts.note()
        raise ValueError("a library's error, raised as it unwound from the interrupt")

    monkeypatch.setattr(ObjectRemoval, "find", interrupted)
    assert main(_run(tmp_path / "run")) == 130
    stderr = capsys.readouterr().err
    assert "mabdi: interrupted" in stderr and "Traceback" not in stderr


def test_a_wrapped_interrupt_outside_the_frames_exits_130(tmp_path, monkeypatch, capsys):
    """The same while the run's outputs are written (after the last frame): the command, not only the frame
    loop, takes a wrapped interrupt for Ctrl-C."""
    from mabdi.cli import main
    from mabdi.loop import run_pipeline

    def interrupted(*args, **kwargs):
        raise _wrapped_interrupt()

    monkeypatch.setattr(run_pipeline, "write_run_outputs", interrupted)
    assert main(_run(tmp_path / "run")) == 130
    stderr = capsys.readouterr().err
    assert "mabdi: interrupted" in stderr and "Traceback" not in stderr and "SystemError" not in stderr


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.mark.slow
def test_ctrl_c_while_numba_unpickles_a_kernels_result_exits_130(tmp_path):
    """A real SIGINT that lands in numba's ``_numba_unpickle`` while refinement's cached kernel
    (``observe_block_kernel``) returns: numba raises SystemError; ``mabdi run`` exits 130 with one line."""
    out = tmp_path / "run"
    script = (
        "import os, signal, sys\n"
        "import numba.core.serialize as serialize\n"  # before any kernel runs: numba's C helper keeps the function
        "unpickle = serialize._numba_unpickle\n"
        "sent = []\n"
        "def interrupted_unpickle(*args):\n"
        "    if not sent and sys._getframe(1).f_code.co_filename.endswith('refinement.py'):\n"
        "        sent.append(True)\n"
        "        os.kill(os.getpid(), signal.SIGINT)\n"  # Ctrl-C: the handler raises inside the unpickling
        "        for _ in range(100000):\n"
        "            pass\n"
        "    return unpickle(*args)\n"
        "serialize._numba_unpickle = interrupted_unpickle\n"
        "from mabdi.cli import main\n"
        f"code = main(['run', 'scenes/table.toml', '--frames', '3', '--noise', 'kinect', '--refinement', '--out', {str(out)!r}, '--no-eval', '--quiet'])\n"
        "print('sent' if sent else 'not sent')\n"
        "sys.exit(code)\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script], cwd=REPO, capture_output=True, text=True, timeout=300,
        env=dict(os.environ, PYTHONUNBUFFERED="1"), preexec_fn=_default_sigint,
    )  # fmt: skip
    assert "not sent" not in done.stdout, "refinement's kernel never ran: the test interrupted nothing"
    assert done.returncode == 130, f"exit {done.returncode}\nstderr: {done.stderr[-3000:]}"
    assert "mabdi: interrupted" in done.stderr and "Traceback" not in done.stderr
    assert not (out / "world_mesh.vtp").exists()


def _sigint_inside_a_c_callback() -> None:
    """A real SIGINT that lands while C code calls back into Python (libc's qsort with a Python comparator,
    as llvmlite's object cache is called back while numba compiles): Python cannot raise the
    KeyboardInterrupt through the C frames and reports it as "Exception ignored"."""
    import ctypes
    import ctypes.util

    libc = ctypes.CDLL(ctypes.util.find_library("c"))
    comparator_type = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.POINTER(ctypes.c_int), ctypes.POINTER(ctypes.c_int))
    sent = []

    def compare(a, b):
        if not sent:
            sent.append(True)
            os.kill(os.getpid(), signal.SIGINT)  # the handler runs here, inside the callback
        return a[0] - b[0]

    values = (ctypes.c_int * 4)(3, 1, 2, 0)
    libc.qsort(values, len(values), ctypes.sizeof(ctypes.c_int), comparator_type(compare))


def test_an_interrupt_python_cannot_raise_is_noted_not_printed(monkeypatch, capsys):
    """While watched, a KeyboardInterrupt reported as unraisable (from a C callback) is noted, with no
    traceback; any other unraisable exception is still reported; unwatched, Python's hook is back."""
    monkeypatch.setattr(interrupts, "_interrupted", False)
    previous_handler = signal.signal(signal.SIGINT, signal.default_int_handler)  # as a command starts outside pytest
    previous_hook, sys.unraisablehook = sys.unraisablehook, sys.__unraisablehook__  # Python's own (pytest's in tests)
    try:
        assert interrupts.watch()
        _sigint_inside_a_c_callback()
        assert interrupts.interrupted()
        assert "Traceback" not in capsys.readouterr().err

        class Failing:
            def __del__(self):
                raise ValueError("a finaliser's own error")

        reported = []
        kept, interrupts._previous_unraisable_hook = interrupts._previous_unraisable_hook, reported.append
        try:
            Failing()
        finally:
            interrupts._previous_unraisable_hook = kept
        assert [type(report.exc_value) for report in reported] == [ValueError]
        interrupts.unwatch()
        assert sys.unraisablehook is sys.__unraisablehook__
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        interrupts.unwatch()
        sys.unraisablehook = previous_hook
        signal.signal(signal.SIGINT, previous_handler)


def test_ctrl_c_inside_a_c_callback_in_a_frame_exits_130_without_a_traceback(tmp_path, monkeypatch, capsys):
    """The same during ``mabdi run`` (the interrupt lands in a C callback inside a frame): exit 130 with one
    line, no "Exception ignored" traceback, no map."""
    from mabdi.cli import main
    from mabdi.stages.object_removal import ObjectRemoval

    find = ObjectRemoval.find

    def interrupted(*args, **kwargs):
        _sigint_inside_a_c_callback()
        return find(*args, **kwargs)

    monkeypatch.setattr(ObjectRemoval, "find", interrupted)
    monkeypatch.setattr(sys, "unraisablehook", sys.__unraisablehook__)  # Python's own (pytest takes it in tests)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)  # as a command starts outside pytest
    try:
        code = main(_run(tmp_path / "run"))
    finally:
        signal.signal(signal.SIGINT, previous)
    assert code == 130
    stderr = capsys.readouterr().err
    assert "mabdi: interrupted" in stderr and "Traceback" not in stderr and "Exception ignored" not in stderr
    assert not (tmp_path / "run" / "world_mesh.vtp").exists()


def test_watching_again_while_watched_takes_the_unraisable_reports_and_leaves_sigint_to_the_first(monkeypatch):
    """A command started while SIGINT is already routed through :mod:`mabdi.interrupts` (a program that runs
    two in one process, a test after another) still has a KeyboardInterrupt Python cannot raise noted, not
    printed: :func:`~mabdi.interrupts.watch` takes the unraisable reports and returns False (the first watcher
    gives SIGINT back)."""
    monkeypatch.setattr(sys, "unraisablehook", sys.__unraisablehook__)
    previous = signal.signal(signal.SIGINT, interrupts._interrupt)
    try:
        assert not interrupts.watch()
        assert sys.unraisablehook is interrupts._unraisable
        assert signal.getsignal(signal.SIGINT) is interrupts._interrupt
    finally:
        interrupts.unwatch()
        signal.signal(signal.SIGINT, previous)
    assert sys.unraisablehook is sys.__unraisablehook__
