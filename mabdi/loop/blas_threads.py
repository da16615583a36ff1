"""One BLAS thread while a frame runs: numpy's and scipy's linear algebra on small matrices, not a thread pool.

A frame's linear algebra is small: 6 x 6 normal equations, 3 x 3 eigen-solves by
the thousand, the map anchor's covariance across at most 128 frames. OpenBLAS
(numpy's and scipy's wheels each bring one) runs such a solve on every core by
default, and its threads spin waiting for each other while the loop's other
threads (llvmpipe drawing E, numba's kernels) or another process hold the cores:
such a solve then takes many times as long as on one thread (docs/benchmarks.md,
"One BLAS thread a frame"). :func:`one_blas_thread` holds
every BLAS library the process has loaded (threadpoolctl finds them) to one thread
for the ``with`` block and gives each its own count back after it, so a user's
script around the loop keeps its own setting.
"""

from __future__ import annotations

from contextlib import AbstractContextManager

from threadpoolctl import ThreadpoolController

_controller: ThreadpoolController | None = None


def one_blas_thread() -> AbstractContextManager:
    """A context in which every loaded BLAS library uses one thread (the libraries are found on first use)."""
    global _controller
    if _controller is None:
        _controller = ThreadpoolController()
    return _controller.limit(limits=1, user_api="blas")
