"""PCD scans (PCL's files) in a KITTI folder: ascii, binary and binary_compressed read the same points."""

from __future__ import annotations

import numpy as np
import pytest

from mabdi.sources.kitti import KittiSequence, read_scan, write_kitti
from mabdi.sources.pcd import lzf_decompress, read_pcd
from mabdi.sources.sequence_files import SequenceError

FIELDS = "FIELDS x y z intensity ring\nSIZE 4 4 4 4 2\nTYPE F F F F U\nCOUNT 1 1 1 1 1\n"


def _cloud(count=500, seed=0):
    """(N,) structured points as a Velodyne driver writes them: x y z intensity (float32), ring (uint16)."""
    rng = np.random.default_rng(seed)
    cloud = np.zeros(count, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"), ("ring", "<u2")])
    for name in ("x", "y", "z"):
        cloud[name] = rng.uniform(-20, 20, count)
    cloud["intensity"] = rng.uniform(0, 100, count)
    cloud["ring"] = rng.integers(0, 32, count)
    return cloud


def _header(count, data, viewpoint="0 0 0 1 0 0 0"):
    return (f"# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n{FIELDS}WIDTH {count}\nHEIGHT 1\n"
            f"VIEWPOINT {viewpoint}\nPOINTS {count}\nDATA {data}\n").encode()


def _literals(raw: bytes) -> bytes:
    """LZF data of ``raw`` made of literal runs only (a valid LZF stream: runs of at most 32 bytes)."""
    out = bytearray()
    for start in range(0, len(raw), 32):
        chunk = raw[start : start + 32]
        out += bytes([len(chunk) - 1]) + chunk
    return bytes(out)


def write_pcd(path, cloud, data, viewpoint="0 0 0 1 0 0 0"):
    if data == "ascii":
        body = "".join(f"{x!r} {y!r} {z!r} {i!r} {ring}\n" for x, y, z, i, ring in cloud.tolist()).encode()
    elif data == "binary":
        body = cloud.tobytes()
    else:  # each field's values one after another, then LZF
        raw = b"".join(np.ascontiguousarray(cloud[name]).tobytes() for name in cloud.dtype.names)
        packed = _literals(raw)
        body = np.array([len(packed), len(raw)], dtype="<u4").tobytes() + packed
    path.write_bytes(_header(len(cloud), data, viewpoint) + body)
    return path


@pytest.mark.parametrize("data", ["ascii", "binary", "binary_compressed"])
def test_a_pcd_file_reads_its_points(tmp_path, data):
    cloud = _cloud()
    points = read_pcd(write_pcd(tmp_path / "000000.pcd", cloud, data))
    expected = np.stack([cloud["x"], cloud["y"], cloud["z"]], axis=1)
    np.testing.assert_array_equal(points, expected)
    assert points.dtype == np.float32


def test_lzf_back_references_copy_what_was_written():
    # "abc" as a literal run, then a reference 3 bytes back for 6 bytes (it overlaps what it writes)
    data = np.frombuffer(bytes([2]) + b"abc" + bytes([(4 << 5) | 0, 2]), dtype=np.uint8)
    out = np.zeros(9, dtype=np.uint8)
    assert lzf_decompress(data, out) == 9 and out.tobytes() == b"abcabcabc"
    # a long reference (length 7 + the next byte) and one before the start of the data: damaged
    data = np.frombuffer(bytes([0]) + b"a" + bytes([(7 << 5), 3, 0]), dtype=np.uint8)
    out = np.zeros(13, dtype=np.uint8)
    assert lzf_decompress(data, out) == 13 and out.tobytes() == b"a" * 13
    assert lzf_decompress(np.frombuffer(bytes([(1 << 5), 5]), dtype=np.uint8), np.zeros(8, dtype=np.uint8)) == -1


def test_the_viewpoint_puts_the_points_in_the_sensor_s_frame(tmp_path):
    cloud = _cloud(50)
    # the sensor 1 m up and turned 90 degrees about z (quaternion w, x, y, z)
    half = np.sqrt(0.5)
    points = read_pcd(write_pcd(tmp_path / "a.pcd", cloud, "binary", f"0 0 1 {half} 0 0 {half}"))
    world = np.stack([cloud["x"], cloud["y"], cloud["z"]], axis=1).astype(np.float64)
    expected = np.stack([world[:, 1], -world[:, 0], world[:, 2] - 1.0], axis=1)
    np.testing.assert_allclose(points, expected, atol=1e-5)


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (lambda b: b.replace(b"DATA binary\n", b"DATA zipped\n"), r"DATA 'zipped': a PCD file's data is ascii, binary or binary_compressed"),
        (lambda b: b.replace(b"FIELDS x y z", b"FIELDS x y w"), r"lack z"),
        (lambda b: b.split(b"DATA")[0], r"no DATA line ends its header"),
        (lambda b: b[: len(b) - 100], r"500 points of 18 bytes need 9000 bytes, the file holds 8900"),
        (lambda b: b.replace(b"TYPE F F F F U", b"TYPE F F F F Q"), r"field 'ring': SIZE 2 TYPE Q"),
        (lambda b: b"ply\nformat ascii 1.0\n", r"not a PCD file: the header line 'ply'"),
    ],
)
def test_a_damaged_pcd_file_is_named_with_what_is_wrong(tmp_path, damage, message):
    path = write_pcd(tmp_path / "000000.pcd", _cloud(), "binary")
    path.write_bytes(damage(path.read_bytes()))
    with pytest.raises(SequenceError, match=message) as caught:
        read_pcd(path)
    assert str(path) in str(caught.value)


def test_a_kitti_folder_of_pcd_scans_reads_as_its_bin_scans(tmp_path):
    """The same scans as .bin and as .pcd files: the same frames; a folder holding both kinds is refused."""
    from tests.test_kitti import _source

    folder = write_kitti(_source(frames=3), tmp_path / "bin")
    pcd = tmp_path / "pcd"
    (pcd / "velodyne").mkdir(parents=True)
    for name in ("poses.txt", "calib.txt", "times.txt", "mabdi.toml"):
        if (folder / name).is_file():
            (pcd / name).write_bytes((folder / name).read_bytes())
    for scan in sorted((folder / "velodyne").glob("*.bin")):
        points = read_scan(scan)
        cloud = np.zeros(len(points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"), ("ring", "<u2")])
        cloud["x"], cloud["y"], cloud["z"] = points.T
        write_pcd(pcd / "velodyne" / f"{scan.stem}.pcd", cloud, "binary_compressed")
    ours, theirs = KittiSequence(pcd), KittiSequence(folder)
    for i in range(3):
        np.testing.assert_array_equal(ours.read(i).depth, theirs.read(i).depth)
    (pcd / "velodyne" / "000003.bin").write_bytes(b"")
    with pytest.raises(SequenceError, match=r"holds both .bin and .pcd scans"):
        KittiSequence(pcd)


def test_scans_are_taken_in_the_order_of_their_numbers(tmp_path):
    """Scan files named by unpadded numbers (9.pcd, 10.pcd, as some datasets name them) are frames 9 then 10,
    not in the order of their names' characters; two files of one number are refused."""
    from mabdi.sources.kitti import scan_files

    (tmp_path / "velodyne").mkdir()
    for number in (10, 9, 100, 0):
        write_pcd(tmp_path / "velodyne" / f"{number}.pcd", _cloud(10, seed=number), "binary")
    assert [p.stem for p in scan_files(tmp_path)] == ["0", "9", "10", "100"]
    write_pcd(tmp_path / "velodyne" / "009.pcd", _cloud(10), "binary")
    with pytest.raises(SequenceError, match=r"two scans are number 9 \(009.pcd, 9.pcd\)"):
        scan_files(tmp_path)
