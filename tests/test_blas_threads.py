"""A frame's linear algebra runs on one BLAS thread, and the caller's setting comes back after it
(:mod:`mabdi.loop.blas_threads`)."""

from __future__ import annotations

import numpy as np
from threadpoolctl import threadpool_info, threadpool_limits

import mabdi
from mabdi.camera import Intrinsics
from mabdi.config import RunConfig
from mabdi.depth import DepthFrame
from mabdi.loop.blas_threads import one_blas_thread
from mabdi.sources.frames import FrameList


def _blas_threads() -> list[int]:
    return [pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"]


def test_one_thread_inside_and_the_callers_count_after():
    assert _blas_threads(), "numpy loads a BLAS library"
    with threadpool_limits(limits=2, user_api="blas"):
        with one_blas_thread():
            assert set(_blas_threads()) == {1}
        assert set(_blas_threads()) == {2}


def test_a_loop_step_runs_on_one_blas_thread(monkeypatch):
    small = Intrinsics(fx=50, fy=50, cx=20, cy=15, width=40, height=30)
    frames = FrameList([DepthFrame(np.full(small.shape, 2.0, np.float32), small, np.eye(4), 0)])
    loop = mabdi.MabdiLoop.from_config(RunConfig(), frames)
    seen = []
    step = loop._step

    def counting(index):
        seen.append(_blas_threads())
        return step(index)

    monkeypatch.setattr(loop, "_step", counting)
    with threadpool_limits(limits=2, user_api="blas"):
        loop.step(0)
        assert set(_blas_threads()) == {2}
    assert set(seen[0]) == {1}
    assert loop.mesh().GetNumberOfCells() > 0
