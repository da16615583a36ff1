"""Registration's GPU path (:mod:`mabdi.stages.registration_device`): the Warp kernels compiled for the CPU give
the numba kernels' sums, a camera's frame, a LiDAR's scan and a recorded run register on them as on the CPU path,
they compile for a CUDA GPU, and a device that cannot run says why."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from conftest import merged
from mabdi.camera import Intrinsics, look_at
from mabdi.errors import ConfigError
from mabdi.render.depth_image import DepthRenderer
from mabdi.sensor_noise import SensorNoise
from mabdi.sources.primitives import box
from mabdi.stages import registration_device
from mabdi.stages.registration import FilterRegistration, RegistrationParameters, register_depth, transform_size
from mabdi.stages.registration_kernels import point_to_plane_residuals, point_to_plane_system
from test_registration import _moved, depth_of, perturbed

wp = pytest.importorskip("warp", reason="the GPU path needs warp-lang (the test extra installs it)")

FX, FY, CX, CY = 120.0, 118.0, 80.3, 59.6
STEP, MAX_JUMP = 1, 0.05


def _samples(expected: np.ndarray, count: int, seed: int):
    """Points of a frame seen from E's pose (camera frame, m) with 3 mm of noise, their tiles, noise and gates."""
    rng = np.random.default_rng(seed)
    rows = rng.integers(0, expected.shape[0], count)
    cols = rng.integers(0, expected.shape[1], count)
    z = expected[rows, cols].astype(np.float64) + rng.normal(0.0, 0.003, count)
    keep = np.isfinite(z)
    rows, cols, z = rows[keep], cols[keep], z[keep]
    points = np.stack([(cols + 0.5 - CX) / FX * z, (rows + 0.5 - CY) / FY * z, z], axis=1)
    tiles = (rows // 40 * 4 + cols // 40).astype(np.int64)
    return points, tiles, np.full(len(z), 0.003), rng.uniform(0.005, 0.03, len(z))


def _expected_image() -> np.ndarray:
    """A tilted, rippled surface 2 m away with a hole and a step (silhouettes, pixels without a normal)."""
    rows, cols = np.mgrid[0:120, 0:160]
    depth = 2.0 + 0.3 * (cols - CX) / 160 + 0.1 * np.sin(rows / 9.0)
    depth[70:, 100:] -= 0.4
    depth[40:50, 60:90] = np.nan
    return depth.astype(np.float32)


@pytest.mark.parametrize("huber", [2.0, 0.0])
def test_the_warp_kernels_sum_what_the_numba_kernels_sum(huber):
    """One ICP step at a pose 4 mm and 0.2 degrees off, Huber weights and Tukey's biweight: the same normal
    equations, supports and tile gradients to 1e-12 of their size, the same pairs, candidates and residuals."""
    expected = _expected_image()
    points, tiles, scale, gate = _samples(expected, 4000, seed=1)
    transform = np.eye(4)
    transform[:3, :3] = Rotation.from_rotvec(np.radians([0.1, -0.05, 0.15])).as_matrix()
    transform[:3, 3] = [0.004, -0.002, 0.003]
    normals, known = np.empty((*expected.shape, 3)), np.zeros(expected.shape, dtype=np.int8)
    cpu = point_to_plane_system(
        points, tiles, 12, scale, gate, transform[:3, :3], np.ascontiguousarray(transform[:3, 3]), expected, normals, known,
        FX, FY, CX, CY, STEP, MAX_JUMP, huber, True,
    )  # fmt: skip
    image = registration_device.DeviceImage(expected, FX, FY, CX, CY, STEP, MAX_JUMP, registration_device.warp_device("warp-cpu"))
    device = image.system(points, tiles, 12, scale, gate, transform, huber, True)
    a, b, chi2, pairs, candidates, residuals, support, tile_gradients = device
    assert 2000 < pairs < candidates < len(points)  # some samples miss E, some fall outside their gates
    assert (pairs, candidates) == (cpu[3], cpu[4])
    np.testing.assert_array_equal(residuals, cpu[5])
    for mine, theirs in ((a, cpu[0]), (b, cpu[1]), (chi2, cpu[2]), (support, cpu[6]), (tile_gradients, cpu[7])):
        np.testing.assert_allclose(mine, theirs, rtol=0, atol=1e-12 * np.max(np.abs(theirs)))
    known[:] = 0
    np.testing.assert_array_equal(
        image.residuals(points, transform),
        point_to_plane_residuals(
            points, transform[:3, :3], np.ascontiguousarray(transform[:3, 3]), expected, normals, known, FX, FY, CX, CY, STEP, MAX_JUMP
        ),
    )
    without = image.system(points, tiles, 12, scale, gate, transform, huber, False)
    np.testing.assert_allclose(without[0], a, rtol=0, atol=1e-12 * np.max(np.abs(a)))
    assert not without[6].any() and not without[7].any()  # no summaries asked, none summed


def test_a_frame_registers_on_the_warp_kernels_as_on_the_numba_kernels():
    """A wall with a recess, D from the true pose with a Kinect's noise and E from one 6 mm off: ``device =
    "warp-cpu"`` finds the CPU path's transform (to a micrometre), with the same status, steps and inliers."""
    wall = merged(
        _moved(box((0.1, 9.5, 20.0)), [2.55, -5.25, 0.0]),
        _moved(box((0.1, 9.5, 20.0)), [2.55, 5.25, 0.0]),
        _moved(box((0.1, 1.0, 20.0)), [2.58, 0.0, 0.0]),
    )
    intrinsics = Intrinsics()
    renderer = DepthRenderer()
    noise = SensorNoise("kinect")
    true = look_at([0.0, -0.3, 0.0], [2.5, 0.1, 0.05])
    given = perturbed(true, [0.004, 0.003, 0.003], [0.0, 0.0, 0.0])
    measured = depth_of(renderer, wall, intrinsics, true, noise, frame=2)
    expected = depth_of(renderer, wall, intrinsics, given)
    results = {
        device: register_depth(measured, expected, intrinsics, noise, RegistrationParameters(device=device))
        for device in ("cpu", "warp-cpu")
    }
    cpu, warp_cpu = results["cpu"], results["warp-cpu"]
    assert cpu.registered, cpu.status
    assert (warp_cpu.status, warp_cpu.iterations) == (cpu.status, cpu.iterations)
    assert warp_cpu.inlier_share == pytest.approx(cpu.inlier_share, abs=1e-9)
    distance, angle = transform_size(np.linalg.inv(cpu.transform) @ warp_cpu.transform)
    assert distance < 1e-6 and angle < 1e-4, (distance, angle)
    error = (given @ warp_cpu.transform)[:3, 3] - true[:3, 3]
    assert abs(error[0]) < 0.0015 and abs(error[1]) < 0.002, error  # and right where the wall holds it


def test_the_kernels_compile_for_a_cuda_gpu(tmp_path):
    """Warp's NVRTC turns the kernels into PTX for a Hopper GPU (sm_90) on a machine without one: the CUDA
    code of the camera's and the LiDAR's kernels exists and compiles."""
    from mabdi.stages import registration_device_kernels

    try:
        paths = wp.compile_aot_module(registration_device_kernels, arch=90, module_dir=tmp_path, use_ptx=True)
    except RuntimeError as error:  # a Warp build without NVRTC
        pytest.skip(f"Warp cannot compile CUDA here: {error}")
    ptx = "".join(path.read_text() for path in paths if path.suffix == ".ptx")
    assert ".target sm_90" in ptx
    for kernel in ("system_kernel", "residuals_kernel", "scan_system_kernel", "scan_cost_kernel"):
        assert kernel in ptx, kernel


def test_a_device_that_cannot_run_says_why(monkeypatch):
    """A misspelt device names the choices; CUDA on a machine without it says so; no Warp names the package."""
    with pytest.raises(ConfigError, match="device must be one of 'cpu', 'warp-cpu', 'cuda' or 'cuda:N', got 'gpu'"):
        RegistrationParameters(device="gpu")
    RegistrationParameters(device="cuda:1")  # a valid name; whether it exists is known when it is used
    if not wp.is_cuda_available():
        with pytest.raises(ConfigError, match="finds no CUDA device"):
            registration_device.warp_device("cuda")
        with pytest.raises(ConfigError, match="finds no CUDA device"):  # when the filter is made, not at a frame
            FilterRegistration(RegistrationParameters(device="cuda"))
        FilterRegistration(RegistrationParameters(device="cuda", enabled=False))  # no ICP: no device needed

    def no_warp():
        raise ImportError("No module named 'warp'")

    monkeypatch.setattr(registration_device, "_warp", no_warp)
    with pytest.raises(ConfigError, match=r'needs NVIDIA Warp: pip install "mabdi\[gpu\]"'):
        registration_device.warp_device("warp-cpu")


def _placed(device: str, given, truth, noise="none"):
    from mabdi.frame_values import Measured
    from mabdi.stages.expected_image import FilterExpectedImage
    from mabdi.stages.scan_registration import ScanRegistration
    from test_scan_registration import GEOMETRY, room, scan

    mesh = room()
    registration = ScanRegistration(RegistrationParameters(device=device), FilterExpectedImage(identity=True))
    measured = Measured(scan(mesh, truth, noise), GEOMETRY, given, SensorNoise.of("none"), index=1)
    return registration.place(measured, mesh)


def test_a_lidar_scan_registers_on_the_warp_kernels_as_on_the_numba_kernels():
    """A scan of a room given 2 degrees and 7 cm off (a lagging odometry), then one given right with range noise:
    on ``"warp-cpu"`` the same status, correction (to a micrometre) and kept pose as on the numba kernels."""
    from test_scan_registration import pose

    for given, truth, noise in ((pose(1.06, -0.53, 27.0), pose(1.0, -0.5, 25.0), "none"), (pose(-1.0, 0.5, -40.0),) * 2 + ("range",)):
        cpu = _placed("cpu", given, truth, noise)
        warp_cpu = _placed("warp-cpu", given, truth, noise)
        assert warp_cpu[1].status == cpu[1].status == "registered"
        distance, angle = transform_size(np.linalg.inv(cpu[0].pose) @ warp_cpu[0].pose)
        assert distance < 1e-6 and angle < 1e-4, (distance, angle)
        assert warp_cpu[1].residual_m == pytest.approx(cpu[1].residual_m, abs=1e-9)
        assert (warp_cpu[2] is None) == (cpu[2] is None)  # the drawing reused where the pose was kept
    assert transform_size(np.linalg.inv(truth) @ warp_cpu[0].pose)[0] < 1e-9  # the good pose kept as given


def test_a_recording_runs_with_the_device_and_makes_the_cpu_path_s_map(tmp_path):
    """``mabdi run --sequence ... --device warp-cpu`` on a recorded table (a Kinect's noise, 12 frames): the
    poses within a micrometre of the CPU path's and the same number of triangles to 1%; the summary and the
    printed line say where registration ran."""
    import contextlib
    import io
    import json

    from conftest import REPO
    from mabdi.cli import main

    text = (REPO / "scenes" / "table.toml").read_text().replace("frames = 30", "frames = 12")
    (tmp_path / "table.toml").write_text(text.replace('noise = "none"', 'noise = "kinect"'))
    assert main(["record", str(tmp_path / "table.toml"), "--format", "tum", "--out", str(tmp_path / "table")]) == 0
    summaries, printed = {}, {}
    for device in ("cpu", "warp-cpu"):
        out = tmp_path / device
        output = io.StringIO()
        with contextlib.redirect_stdout(output):
            command = ["run", "--sequence", str(tmp_path / "table"), "--out", str(out), "--quiet", "--no-eval", "--time-offset", "0"]
            assert main([*command, "--device", device]) == 0
        summaries[device], printed[device] = json.loads((out / "summary.json").read_text()), output.getvalue()
    cpu, warp_cpu = summaries["cpu"], summaries["warp-cpu"]
    assert cpu["registration"]["registered"] >= 10
    assert (warp_cpu["registration"]["device"], cpu["registration"]["device"]) == ("warp-cpu", "cpu")
    assert warp_cpu["registration"]["statuses"] == cpu["registration"]["statuses"]
    assert abs(warp_cpu["cells"] - cpu["cells"]) <= 0.01 * cpu["cells"]
    poses = [np.load(tmp_path / device / "poses.npy") for device in ("cpu", "warp-cpu")]
    assert np.abs(poses[0] - poses[1]).max() < 1e-6
    assert "registered to the map on warp-cpu" in printed["warp-cpu"]
    assert "registered to the map (" in printed["cpu"]
