"""FrameRecords: the run's frame records by column read back exactly what went in, in little memory."""

from dataclasses import asdict, fields

import numpy as np
import pytest

from mabdi.io.checkpoint import decode, encode
from mabdi.loop.frame_records import BLOCK, FrameRecords
from mabdi.loop.loop import FrameRecord


def record(i: int) -> FrameRecord:
    statuses = ("registered", "no_map", "too_few_inliers")
    return FrameRecord(
        frame=i, novel_fraction=i / 7.0, cells_added=3 * i - 5, cells_total=10**9 + i, t_depth_ms=0.1 * i,
        t_expected_ms=1e-9 * i, t_classify_ms=float(i), t_surface_ms=2.5, t_append_ms=0.0, t_total_ms=12.345678901234,
        novel_pixels=i % 640, registration=statuses[i % 3], residual_mm=float("nan") if i % 5 == 0 else 0.25 * i,
        area_removed=1e-4 * i,
    )


def same(a: FrameRecord, b: FrameRecord) -> bool:
    """Every field equal (NaN equal to NaN), and of the same type."""
    for name, value in asdict(a).items():
        other = getattr(b, name)
        if type(value) is not type(other):
            return False
        if not (value == other or (isinstance(value, float) and np.isnan(value) and np.isnan(other))):
            return False
    return True


def test_records_read_back_exactly_by_index_slice_iteration_and_column():
    count = 2 * BLOCK + 17  # three blocks, the last partly used
    originals = [record(i) for i in range(count)]
    records = FrameRecords()
    for r in originals:
        records.append(r)
    assert len(records) == count
    for i in (0, 1, BLOCK - 1, BLOCK, count - 1):
        assert same(records[i], originals[i])
    assert same(records[-1], originals[-1])
    assert all(same(a, b) for a, b in zip(records, originals, strict=True))
    assert [r.frame for r in records[BLOCK - 2 : BLOCK + 2]] == [BLOCK - 2, BLOCK - 1, BLOCK, BLOCK + 1]
    assert [r.cells_total for r in records] == [r.cells_total for r in originals]
    np.testing.assert_array_equal(records.column("novel_fraction"), [r.novel_fraction for r in originals])
    assert list(records.column("registration")) == [r.registration for r in originals]
    with pytest.raises(IndexError, match=f"out of range \\(the run has {count}\\)"):
        records[count]
    with pytest.raises(KeyError, match="no field 'speed'"):
        records.column("speed")


def test_records_take_about_a_tenth_of_a_kilobyte_a_frame():
    records = FrameRecords(record(i) for i in range(10 * BLOCK))
    per_frame = records.nbytes / len(records)
    numeric = sum(1 for f in fields(FrameRecord) if f.type != "str")
    assert per_frame == 8 * numeric + 1  # 8 bytes per number, one per status


def test_checkpoint_state_round_trip_and_older_list_of_dicts():
    originals = [record(i) for i in range(BLOCK + 3)]
    records = FrameRecords(originals)
    header, arrays = encode({"records": records.state()})
    back = FrameRecords.from_state(decode(header, arrays)["records"])
    assert len(back) == len(originals)
    assert all(same(a, b) for a, b in zip(back, originals, strict=True))
    older = FrameRecords.from_state([asdict(r) for r in originals[:5]])
    assert all(same(a, b) for a, b in zip(older, originals[:5], strict=True))
    with pytest.raises(TypeError, match="speed"):
        FrameRecords.from_state([{**asdict(originals[0]), "speed": 1.0}])
