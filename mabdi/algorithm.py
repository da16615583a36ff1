"""The one base class every mabdi filter and source derives from.

VTK swallows Python exceptions raised inside ``RequestData``: the executive
prints a message and ``Update()`` returns False, and a plain VTK filter
downstream may even go on with an empty input. :class:`MabdiAlgorithm`
closes that hole:

* every pipeline request (``RequestDataObject``, ``RequestInformation``,
  ``RequestUpdateExtent``, ``RequestData``) runs inside a try/except that
  stores the exception and returns failure. That includes ``BaseException``:
  a ``KeyboardInterrupt`` (Ctrl-C) or ``SystemExit`` raised inside a request
  would otherwise be printed by VTK and forgotten, and the run would go on;
* ``Update()`` called on a mabdi algorithm re-raises the stored exception
  (the original type and traceback; one that Ctrl-C caused, numba's SystemError
  around it say, as ``KeyboardInterrupt``: :func:`mabdi.interrupts.caused_by_interrupt`),
  and hides VTK's own "returned failure" dump since the Python exception says
  what went wrong;
* **Ctrl-C** during ``Update()`` (in the main thread, with Python's default
  SIGINT handler or the command line's, :mod:`mabdi.interrupts`) is held until the update returns and then raised as
  ``KeyboardInterrupt`` by ``Update()``, so it never lands in Python code that
  VTK calls outside a request of ours (where VTK would print and drop it). A
  second Ctrl-C while the first is held raises at once;
* **the boundary**: when the update is pulled through a plain VTK filter
  downstream (``vtk_filter.Update()``), nothing of ours is on the call stack
  to raise. Call :func:`raise_pipeline_errors` (or
  :meth:`MabdiAlgorithm.raise_if_failed`) on the mabdi algorithms of that
  pipeline after the update; the simulation runner does so every frame.

Setters call ``Modified()`` only when the value changes (:meth:`_set`).
"""

from __future__ import annotations

import contextlib
import sys
from typing import Any

import numpy as np
from vtkmodules.util.vtkAlgorithm import VTKPythonAlgorithmBase
from vtkmodules.vtkCommonCore import vtkLogger, vtkOutputWindow, vtkStringOutputWindow

from mabdi.interrupts import caused_by_interrupt, interrupts_held


class MabdiAlgorithm(VTKPythonAlgorithmBase):
    """VTKPythonAlgorithmBase that turns failures in pipeline requests into Python exceptions."""

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        self._pending_error: BaseException | None = None

    # VTK calls this for every pipeline pass; VTKPythonAlgorithmBase dispatches to Request*.
    def ProcessRequest(self, request, inInfo, outInfo):  # noqa: N802 (VTK API)
        try:
            return super().ProcessRequest(request, inInfo, outInfo)
        except BaseException as exc:  # stored and re-raised by Update()/raise_if_failed(), Ctrl-C included
            if self._pending_error is None:
                self._pending_error = exc
            # Make the next update try again rather than reuse a failed output.
            self.Modified()
            return 0

    def Update(self, *args) -> bool:  # noqa: N802 (VTK API)
        """Update the pipeline up to this algorithm; raise the first error a request hit."""
        for algorithm in (*upstream_algorithms(self), self):
            if isinstance(algorithm, MabdiAlgorithm):
                algorithm._pending_error = None
        # Hold VTK's own messages back while updating: when a request of ours failed, the
        # Python exception says what went wrong; otherwise they are passed on afterwards.
        with vtk_messages_held():
            with interrupts_held():
                result = super().Update(*args)
            raise_pipeline_errors(*upstream_algorithms(self), self)
        return result

    def GetOutput(self, port: int = 0):  # noqa: N802 (VTK API)
        """The output data object of ``port`` (as VTK's own filters offer it)."""
        return self.GetOutputDataObject(port)

    @property
    def error(self) -> BaseException | None:
        """The exception stored by the last failed request, if any."""
        return self._pending_error

    def raise_if_failed(self) -> None:
        """Raise (and clear) the exception stored by a failed request, if any."""
        error, self._pending_error = self._pending_error, None
        if isinstance(error, Exception) and caused_by_interrupt(error):  # Ctrl-C wrapped by a library (numba)
            raise KeyboardInterrupt from error
        if error is not None:
            raise error

    def _set(self, name: str, value: Any) -> None:
        """Set attribute ``name`` and call Modified() only if the value changed."""
        old = getattr(self, name, None)
        if isinstance(value, np.ndarray) or isinstance(old, np.ndarray):
            same = (
                isinstance(value, np.ndarray)
                and isinstance(old, np.ndarray)
                and old.shape == value.shape
                and np.array_equal(old, value)
            )
        else:
            same = old == value and type(old) is type(value)
        if not same:
            setattr(self, name, value)
            self.Modified()


@contextlib.contextmanager
def vtk_messages_held():
    """Collect VTK's messages (its output window and vtkLogger's stderr) inside the block.

    Yields a function that returns the text collected so far. When the block
    ends normally the text is passed on: to the output window installed
    before, when that is a collecting one (``vtkStringOutputWindow``, as the
    command line installs), else to stderr. When the block raises, the text
    goes only to a collecting window: the exception says what went wrong
    (include what VTK said in its message where it helps).
    """
    previous = vtkOutputWindow.GetInstance()
    captured = vtkStringOutputWindow()
    vtkOutputWindow.SetInstance(captured)
    verbosity = vtkLogger.GetCurrentVerbosityCutoff()  # no getter for stderr alone
    vtkLogger.SetStderrVerbosity(vtkLogger.VERBOSITY_OFF)
    collecting = isinstance(previous, vtkStringOutputWindow)
    try:
        yield captured.GetOutput
    except BaseException:
        if collecting and captured.GetOutput():
            previous.DisplayText(captured.GetOutput())  # kept by the collector, which decides what to show
        raise
    finally:
        vtkLogger.SetStderrVerbosity(verbosity)
        vtkOutputWindow.SetInstance(previous)
    text = captured.GetOutput()
    if text:
        if collecting:
            previous.DisplayText(text)
        else:
            sys.stderr.write(text)


def upstream_algorithms(algorithm) -> list:
    """Every algorithm upstream of ``algorithm`` (through plain VTK filters too), sources first."""
    seen: dict[int, object] = {}

    def visit(alg) -> None:
        for port in range(alg.GetNumberOfInputPorts()):
            for index in range(alg.GetNumberOfInputConnections(port)):
                producer = alg.GetInputAlgorithm(port, index)
                if producer is not None and id(producer) not in seen:
                    visit(producer)
                    seen[id(producer)] = producer

    visit(algorithm)
    return list(seen.values())


def raise_pipeline_errors(*algorithms) -> None:
    """Raise the first error stored by any of ``algorithms`` (mabdi algorithms; others are skipped).

    Use after updating a pipeline through a plain VTK filter, whose
    ``Update()`` cannot see failures upstream.
    """
    for algorithm in algorithms:
        if isinstance(algorithm, MabdiAlgorithm):
            algorithm.raise_if_failed()
