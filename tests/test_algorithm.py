"""MabdiAlgorithm: errors in pipeline requests reach the caller."""

from __future__ import annotations

import numpy as np
import pytest
from vtkmodules.vtkCommonDataModel import vtkPolyData
from vtkmodules.vtkFiltersCore import vtkTriangleFilter

from mabdi.algorithm import MabdiAlgorithm, raise_pipeline_errors
from mabdi.render.depth_image import FilterDepthImage


class FailingSource(MabdiAlgorithm):
    def __init__(self, fail=True):
        super().__init__(nInputPorts=0, nOutputPorts=1, outputType="vtkPolyData")
        self.fail = fail

    def RequestData(self, request, inInfo, outInfo):
        if self.fail:
            raise KeyError("the source could not find 'widget'")
        vtkPolyData.GetData(outInfo).Initialize()
        return 1


def test_error_in_request_data_is_raised_by_update(capfd):
    source = FailingSource()
    with pytest.raises(KeyError, match="widget"):
        source.Update()
    assert "returned failure" not in capfd.readouterr().err  # VTK's dump is held back


def test_filter_retries_after_a_failure():
    source = FailingSource()
    with pytest.raises(KeyError):
        source.Update()
    source.fail = False
    assert source.Update()


def test_error_upstream_is_raised_by_a_mabdi_filter_downstream():
    source = FailingSource()
    sensor = FilterDepthImage()
    sensor.SetInputConnection(source.GetOutputPort())
    sensor.pose = np.eye(4)
    with pytest.raises(KeyError, match="widget"):
        sensor.Update()


def test_error_pulled_through_a_plain_vtk_filter_surfaces_on_check():
    source = FailingSource()
    plain = vtkTriangleFilter()
    plain.SetInputConnection(source.GetOutputPort())
    plain.Update()  # VTK itself reports nothing to Python here
    with pytest.raises(KeyError, match="widget"):
        raise_pipeline_errors(source)
    raise_pipeline_errors(source)  # the error was cleared once raised


def test_setter_helper_modifies_only_on_change():
    source = FailingSource()
    source._set("_value", np.eye(2))
    before = source.GetMTime()
    source._set("_value", np.eye(2))
    assert source.GetMTime() == before
    source._set("_value", np.zeros((2, 2)))
    assert source.GetMTime() > before


class InterruptedSource(MabdiAlgorithm):
    """A source whose RequestData raises ``error`` (a BaseException) or receives a SIGINT mid-way."""

    def __init__(self, error=None, signal_mid_way=False):
        super().__init__(nInputPorts=0, nOutputPorts=1, outputType="vtkPolyData")
        self.exception, self.signal_mid_way, self.finished = error, signal_mid_way, False

    def RequestData(self, request, inInfo, outInfo):
        if self.exception is not None:
            raise self.exception
        if self.signal_mid_way:
            import signal

            signal.raise_signal(signal.SIGINT)
            sum(range(10000))  # Python code runs on after the signal: the interrupt is held
        vtkPolyData.GetData(outInfo).Initialize()
        self.finished = True
        return 1


@pytest.mark.parametrize("error", [KeyboardInterrupt(), SystemExit(3)])
def test_base_exceptions_in_a_request_are_raised_by_update(error):
    source = InterruptedSource(error)
    with pytest.raises(type(error)):
        source.Update()


def test_keyboard_interrupt_pulled_through_a_plain_vtk_filter_surfaces_on_check():
    source = InterruptedSource(KeyboardInterrupt())
    plain = vtkTriangleFilter()
    plain.SetInputConnection(source.GetOutputPort())
    plain.Update()
    with pytest.raises(KeyboardInterrupt):
        raise_pipeline_errors(source)


@pytest.fixture
def python_sigint_handler():
    """Python's own SIGINT handler, as in a terminal (a shell's background job starts with SIGINT ignored)."""
    import signal

    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def test_ctrl_c_during_update_is_held_until_the_update_ends(python_sigint_handler):
    import signal

    source = InterruptedSource(signal_mid_way=True)
    with pytest.raises(KeyboardInterrupt):
        source.Update()
    assert source.finished  # the request ran to its end; the interrupt came after
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    source.signal_mid_way = False
    source.Modified()
    assert source.Update()  # nothing is left pending


def test_ctrl_c_is_held_under_the_command_lines_handler_too(python_sigint_handler, monkeypatch):
    """``mabdi run`` routes SIGINT through :mod:`mabdi.interrupts` for the whole command: an update holds it
    all the same (else it lands in Python code VTK calls, which prints a traceback and drops it), notes it,
    and gives the command line's handler back."""
    import signal

    from mabdi import interrupts

    monkeypatch.setattr(interrupts, "_interrupted", False)
    assert interrupts.watch()
    try:
        source = InterruptedSource(signal_mid_way=True)
        with pytest.raises(KeyboardInterrupt):
            source.Update()
        assert source.finished  # held to the end of the request
        assert interrupts.interrupted()
        assert signal.getsignal(signal.SIGINT) is interrupts._interrupt
    finally:
        interrupts.unwatch()
