"""The ICP's per-sample work on a GPU (NVIDIA Warp): :mod:`mabdi.stages.registration_kernels` for a device.

Frame-to-map registration spends most of its time summing the normal equations of projective point-to-plane
ICP over D's samples, several times a frame (:func:`~mabdi.stages.registration_kernels.point_to_plane_system`).
With ``[registration] device = "cuda"`` (or ``"cuda:N"``) those sums and the residuals run as Warp kernels on
the GPU; ``"warp-cpu"`` runs the same kernels compiled for the CPU, which is how the tests check them on a
machine without a GPU. The rest of registration (sampling D, the pyramid, the solve, the checks) stays on the
CPU: a step moves a few hundred kilobytes (the samples once a level, their gates once a step) and brings back
the sums and one residual a sample. A LiDAR scan's fit (:mod:`mabdi.stages.scan_registration`) runs its steps
and its cost there the same way (:class:`DeviceScan`; the returns and E's points and normals go once a scan).

The numbers are the CPU kernels' (float64 throughout, E read as float32): each GPU thread sums a strip of
samples (:data:`~mabdi.stages.registration_device_kernels.STRIP`) in order and adds its sums to the totals
atomically, so on a GPU the totals' last bits depend on the order the strips finish in; on the CPU the strips run
in order. E's normals are computed at each pair rather than cached: a GPU thread recomputing four neighbours
costs less than sharing a cache across threads.

Needs the ``warp-lang`` package (``pip install "mabdi[gpu]"``); :func:`warp_device` says so when it is missing
or when there is no CUDA device.
"""

from __future__ import annotations

import numpy as np

from mabdi.errors import ConfigError

# Warp and the kernels are imported by the first DeviceImage (registration's device "cpu" needs neither).
wp = kernels = None


def _warp():
    """Import Warp and the kernels (once)."""
    global wp, kernels
    if kernels is None:
        import warp
        from mabdi.stages import registration_device_kernels

        wp, kernels = warp, registration_device_kernels

#: The ``device`` values of :class:`~mabdi.stages.registration.RegistrationParameters`: the numba kernels, the
#: Warp kernels on the CPU, or on a CUDA GPU (``"cuda:N"`` names one of several).
DEVICES = ("cpu", "warp-cpu", "cuda")


def check_device(name: str) -> None:
    """A ConfigError unless ``name`` is one of :data:`DEVICES` or ``"cuda:N"``."""
    if isinstance(name, str) and (name in DEVICES or (name.startswith("cuda:") and name[5:].isdigit())):
        return
    raise ConfigError(f"registration: device must be one of {', '.join(map(repr, DEVICES))} or 'cuda:N', got {name!r}")


def warp_device(name: str):
    """The Warp device for a ``device`` setting other than ``"cpu"``: a ConfigError naming what is missing where
    Warp is not installed or no such CUDA device exists."""
    check_device(name)
    try:
        _warp()
    except ImportError as error:
        raise ConfigError(f'registration: device {name!r} needs NVIDIA Warp: pip install "mabdi[gpu]" ({error})') from None
    wp.init()
    if name == "warp-cpu":
        return wp.get_device("cpu")
    if not wp.is_cuda_available():
        raise ConfigError(f"registration: device {name!r}: Warp finds no CUDA device on this machine (device = 'cpu' runs without one)")
    if name != "cuda" and int(name[5:]) >= wp.get_cuda_device_count():
        raise ConfigError(f"registration: device {name!r}: this machine has {wp.get_cuda_device_count()} CUDA device(s)")
    return wp.get_device(name)


def _pose(transform: np.ndarray):
    """A 4x4 transform's rotation and translation as Warp values (float64)."""
    rotation = np.asarray(transform[:3, :3], dtype=np.float64)
    return wp.mat33d(*rotation.ravel()), wp.vec3d(*np.asarray(transform[:3, 3], dtype=np.float64))


def _upper_to_full(values: np.ndarray) -> np.ndarray:
    """The symmetric 6x6 matrix of its 21 upper entries, row by row."""
    full = np.zeros((6, 6))
    full[np.triu_indices(6)] = values
    return full + np.triu(full, 1).T


def _normal_equations(sums: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(A (6, 6), b (6,)) of a step's totals (:data:`~mabdi.stages.registration_device_kernels.TOTAL_A` on)."""
    return _upper_to_full(sums[kernels.TOTAL_A : kernels.TOTAL_A + 21]), sums[kernels.TOTAL_B : kernels.TOTAL_B + 6].copy()


class DeviceImage:
    """E on a Warp device and the ICP's sums over D's samples there: what
    :class:`~mabdi.stages.registration._MapImage` computes with the numba kernels, with the same arguments and
    results. ``step`` and ``max_jump``: E's normals (:func:`~mabdi.stages.registration_kernels.point_and_normal`)."""

    def __init__(self, expected: np.ndarray, fx: float, fy: float, cx: float, cy: float, step: int, max_jump: float, device) -> None:
        """``device``: a Warp device (:func:`warp_device`)."""
        _warp()
        self.device = device
        self.depth = wp.array(np.ascontiguousarray(expected, dtype=np.float32), dtype=wp.float32, device=device)
        self.camera = (wp.float64(fx), wp.float64(fy), wp.float64(cx), wp.float64(cy), int(step), wp.float64(max_jump))
        self._samples: tuple | None = None  # (points, tiles, scale) as given, and their copies on the device

    def _on_device(self, points: np.ndarray, tiles: np.ndarray | None, scale: np.ndarray | None):
        """The samples' device copies, made once for the arrays of a pyramid level (the steps reuse them)."""
        kept = self._samples
        if kept is not None and kept[0] is points and (tiles is None or kept[1] is tiles) and (scale is None or kept[2] is scale):
            return kept[3:]
        points_d = wp.array(np.ascontiguousarray(points, dtype=np.float64), dtype=wp.float64, device=self.device)
        tiles_d = None if tiles is None else wp.array(np.ascontiguousarray(tiles, dtype=np.int64), dtype=wp.int64, device=self.device)
        scale_d = None if scale is None else wp.array(np.ascontiguousarray(scale, dtype=np.float64), dtype=wp.float64, device=self.device)
        if tiles is not None and scale is not None:
            self._samples = (points, tiles, scale, points_d, tiles_d, scale_d)
        return points_d, tiles_d, scale_d

    def system(self, points, tiles, n_tiles, scale, gate, transform, huber, summaries):
        """(A, b, chi2, pairs, candidates, residuals, support, tile_gradients) of one ICP step at ``transform``, as
        :func:`~mabdi.stages.registration_kernels.point_to_plane_system` returns them."""
        n = len(points)
        points_d, tiles_d, scale_d = self._on_device(points, tiles, scale)
        gate_d = wp.array(np.ascontiguousarray(gate, dtype=np.float64), dtype=wp.float64, device=self.device)
        totals = wp.zeros(kernels.TOTALS, dtype=wp.float64, device=self.device)
        gradients = wp.zeros((max(n_tiles, 1), 6), dtype=wp.float64, device=self.device)
        residuals = wp.empty(max(n, 1), dtype=wp.float64, device=self.device)
        rotation, translation = _pose(transform)
        if n:
            wp.launch(
                kernels.system_kernel, dim=-(-n // kernels.STRIP),
                inputs=[points_d, tiles_d, scale_d, gate_d, rotation, translation, self.depth, *self.camera,
                        wp.float64(huber), int(bool(summaries)), totals, gradients, residuals],
                device=self.device,
            )  # fmt: skip
        sums = totals.numpy()
        kept = residuals.numpy()[:n]
        support = np.zeros((2, 6, 6))
        tile_gradients = np.zeros((n_tiles, 6))
        if summaries:
            support[0] = _upper_to_full(sums[kernels.TOTAL_SUPPORT : kernels.TOTAL_SUPPORT + 21])
            support[1] = _upper_to_full(sums[kernels.TOTAL_SUPPORT + 21 : kernels.TOTAL_SUPPORT + 42])
            tile_gradients = gradients.numpy()[:n_tiles]
        a, b = _normal_equations(sums)
        pairs, candidates = int(round(sums[kernels.TOTAL_PAIRS])), int(round(sums[kernels.TOTAL_CANDIDATES]))
        return a, b, float(sums[kernels.TOTAL_CHI2]), pairs, candidates, kept[kept >= 0.0], support, tile_gradients

    def residuals(self, points, transform) -> np.ndarray:
        """The absolute point-to-plane residuals (m) of every candidate at ``transform``, in the samples' order
        (:func:`~mabdi.stages.registration_kernels.point_to_plane_residuals`)."""
        n = len(points)
        if not n:
            return np.empty(0)
        points_d, _, _ = self._on_device(points, None, None)
        residuals = wp.empty(n, dtype=wp.float64, device=self.device)
        rotation, translation = _pose(transform)
        wp.launch(kernels.residuals_kernel, dim=n, inputs=[points_d, rotation, translation, self.depth, *self.camera, residuals], device=self.device)
        kept = residuals.numpy()
        return kept[kept >= 0.0]


class DeviceScan:
    """A LiDAR scan's returns and E's planes on a Warp device: the sums of
    :func:`~mabdi.stages.scan_registration_kernels.scan_to_plane_system` and
    :func:`~mabdi.stages.scan_registration_kernels.truncated_cost` there, with the same arguments and results.
    ``points`` (N, 3) and E's ``e_points`` and ``e_normals`` (H, W, 3) in the sensor frame of the start pose (m);
    ``row_edges`` and ``columns``: the range image's rows and columns; ``angle_reach`` (radians)."""

    def __init__(self, points, e_points, e_normals, row_edges, columns: int, angle_reach: float, device) -> None:
        _warp()
        self.device = device
        self.count = len(points)

        def upload(values):
            return wp.array(np.ascontiguousarray(values, dtype=np.float64), dtype=wp.float64, device=device)

        self.arrays = (upload(points),)
        self.image = (upload(e_points), upload(e_normals), upload(row_edges), int(columns), wp.float64(angle_reach))

    def system(self, transform: np.ndarray, gate: float, huber: float):
        """(A (6x6), b (6,), |residuals| of the pairs in the returns' order) of one step at ``transform``."""
        totals = wp.zeros(kernels.SCAN_TOTALS, dtype=wp.float64, device=self.device)
        residuals = wp.empty(max(self.count, 1), dtype=wp.float64, device=self.device)
        if self.count:
            rotation, translation = _pose(transform)
            wp.launch(
                kernels.scan_system_kernel, dim=-(-self.count // kernels.STRIP),
                inputs=[*self.arrays, rotation, translation, *self.image, wp.float64(gate), wp.float64(huber), totals, residuals],
                device=self.device,
            )  # fmt: skip
        sums = totals.numpy()
        kept = residuals.numpy()[: self.count]
        a, b = _normal_equations(sums)
        return a, b, kept[kept >= 0.0]

    def cost(self, transform: np.ndarray, gate: float) -> tuple[float, int]:
        """(the mean of min(r, gate)^2 in m^2, NaN where no return sees the map; the returns that see it)."""
        totals = wp.zeros(2, dtype=wp.float64, device=self.device)
        if self.count:
            rotation, translation = _pose(transform)
            wp.launch(
                kernels.scan_cost_kernel, dim=-(-self.count // kernels.STRIP),
                inputs=[*self.arrays, rotation, translation, *self.image, wp.float64(gate), totals], device=self.device,
            )  # fmt: skip
        total, seen = totals.numpy()
        seen = int(round(seen))
        return (float(total) / seen if seen else float("nan")), seen
