"""Ctrl-C that a library swallowed: a note of every SIGINT, which the command line checks.

Python turns SIGINT into a KeyboardInterrupt wherever the main thread is.
Raised inside a third-party import, it can come out as that import's
ImportError ("Failed to load vtkRenderingOpenGL2: No module named ..."), and
a library that takes the module for optional carries on without it: the
interrupt is lost, and ``mabdi run`` would go on to the end of its frames.

So while ``import mabdi`` runs, and for the whole of a command-line run,
SIGINT goes through :func:`_interrupt`, which raises KeyboardInterrupt as
Python's own handler does and also notes that it came. The command line
checks the note before a run starts and after every frame
(:func:`raise_if_interrupted`), and forgets it when the command ends
(:func:`clear`). A program that imports mabdi has Python's
handler back once the import is done; one that installed its own handler
keeps it throughout (:func:`watch` only takes Python's default).

A library can also wrap the KeyboardInterrupt in an exception of its own:
numba raises ``SystemError: ... returned a result with an exception set``,
the KeyboardInterrupt its cause, when Ctrl-C lands while it unpickles (a
cached kernel's first call, a kernel's result boxed). :func:`caused_by_interrupt`
tells such an exception (a KeyboardInterrupt in its chain, or any raised once
a SIGINT was noted), and :func:`interrupts_unwrapped` raises it as the
KeyboardInterrupt it stands for (the loop's frames and the pipeline's
requests go through it).

Where Python cannot raise at all (the KeyboardInterrupt came inside a C
callback, such as llvmlite's object cache while numba compiles, or in a
``__del__``), it reports the exception as "Exception ignored in ..." with a
traceback. While watched, :func:`_unraisable` takes such a report: a
KeyboardInterrupt is noted (the command stops at its next check) and not
printed; any other exception goes to the hook that was there before.
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading

_interrupted = False
_previous_unraisable_hook = None


def note() -> None:
    """Note a SIGINT (:func:`_interrupt`; and :func:`interrupts_held` for one it holds)."""
    global _interrupted
    _interrupted = True


def _interrupt(signum, frame) -> None:
    """SIGINT: note it, then raise KeyboardInterrupt (what Python's own handler does)."""
    note()
    raise KeyboardInterrupt


def _unraisable(report) -> None:
    """``sys.unraisablehook`` while watched: a KeyboardInterrupt Python could not raise is noted, not printed."""
    if isinstance(report.exc_value, KeyboardInterrupt) or report.exc_type is KeyboardInterrupt:
        note()
        return
    (_previous_unraisable_hook or sys.__unraisablehook__)(report)


def raising_handlers() -> tuple:
    """The SIGINT handlers that raise KeyboardInterrupt as Python's does: its own and :func:`_interrupt`
    (code that holds Ctrl-C for a while takes over from either and gives the same one back)."""
    return (signal.default_int_handler, _interrupt)


def _in_main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


def watch() -> bool:
    """Route SIGINT through :func:`_interrupt` where Python's default handler holds it (main thread only:
    only it may set handlers), and unraisable reports through :func:`_unraisable` (also where SIGINT is
    watched already). Returns whether it routed SIGINT (the caller then gives it back: :func:`unwatch`)."""
    if not _in_main_thread():
        return False
    handler = signal.getsignal(signal.SIGINT)
    if handler is _interrupt:  # watched already (the caller that did gives it back): the reports too
        _take_unraisable_reports()
        return False
    if handler is not signal.default_int_handler:
        return False
    signal.signal(signal.SIGINT, _interrupt)
    _take_unraisable_reports()
    return True


def _take_unraisable_reports() -> None:
    """Route ``sys.unraisablehook`` through :func:`_unraisable` (once; the hook before is kept for the rest)."""
    global _previous_unraisable_hook
    if sys.unraisablehook is not _unraisable:
        _previous_unraisable_hook, sys.unraisablehook = sys.unraisablehook, _unraisable


def unwatch() -> None:
    """Give SIGINT back to Python's default handler, where :func:`watch` took it."""
    global _previous_unraisable_hook
    if _in_main_thread() and signal.getsignal(signal.SIGINT) is _interrupt:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    if sys.unraisablehook is _unraisable:
        sys.unraisablehook = _previous_unraisable_hook or sys.__unraisablehook__
        _previous_unraisable_hook = None


def interrupted() -> bool:
    """Whether a SIGINT came while watched (swallowed or not)."""
    return _interrupted


def clear() -> None:
    """Forget the note (a command that ended, interrupted or not: the next one in the same process starts clean)."""
    global _interrupted
    _interrupted = False


def raise_if_interrupted() -> None:
    """Raise KeyboardInterrupt if a SIGINT came while watched: one that something caught on its way out
    still stops the command."""
    if _interrupted:
        raise KeyboardInterrupt


def caused_by_interrupt(error: BaseException) -> bool:
    """Whether ``error`` is Ctrl-C's doing: a KeyboardInterrupt, an exception with one in its chain
    (``__cause__`` or ``__context__``, at any depth: numba's SystemError), or any exception once a SIGINT
    was noted."""
    pending, seen = [error], set()
    while pending:
        current = pending.pop()
        if current is None or id(current) in seen:
            continue
        if isinstance(current, KeyboardInterrupt):
            return True
        seen.add(id(current))
        pending += [current.__cause__, current.__context__]
    return _interrupted


@contextlib.contextmanager
def interrupts_unwrapped():
    """Raise an exception of the block that Ctrl-C caused (:func:`caused_by_interrupt`) as KeyboardInterrupt
    (from it: the traceback keeps it)."""
    try:
        yield
    except Exception as error:
        if caused_by_interrupt(error):
            raise KeyboardInterrupt from error
        raise


_held = {"depth": 0, "pending": False}


@contextlib.contextmanager
def interrupts_held():
    """Hold Ctrl-C (SIGINT) inside the block and raise ``KeyboardInterrupt`` when it ends.

    Only in the main thread and only while Python's default SIGINT handler, or
    the command line's (:func:`_interrupt`: it raises the same), is installed
    (a program with its own handler keeps it); that one is back when the block
    ends. Nested blocks hold until the outermost one ends. A second SIGINT
    while one is held raises ``KeyboardInterrupt`` at once (for an update that
    never returns). Used around pipeline updates (:mod:`mabdi.algorithm`) and
    an atomic write's temporary file (:mod:`mabdi.io.atomic`).
    """
    if _held["depth"]:
        _held["depth"] += 1
        try:
            yield
        finally:
            _held["depth"] -= 1
        return
    previous = signal.getsignal(signal.SIGINT) if threading.current_thread() is threading.main_thread() else None
    if previous not in raising_handlers():
        yield
        return

    def hold(signum, frame):
        if previous is not signal.default_int_handler:  # the command line's: its note, should the interrupt be lost later
            note()
        if _held["pending"]:
            raise KeyboardInterrupt
        _held["pending"] = True

    _held["depth"], _held["pending"] = 1, False
    signal.signal(signal.SIGINT, hold)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        _held["depth"] = 0
        pending, _held["pending"] = _held["pending"], False
        if pending:
            raise KeyboardInterrupt
