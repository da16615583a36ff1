"""The run's frame records, kept by column: a few hundred bytes a frame, not a Python object per frame.

A run keeps one :class:`~mabdi.loop.loop.FrameRecord` per frame for its
``metrics.csv``, its summary and its checkpoints. Held as objects, each frame
costs a slotted object and a boxed number per field; :class:`FrameRecords`
holds the same values in numpy columns, in fixed-size blocks of :data:`BLOCK`
frames (no copy as the run grows, at most one block unused): 8 bytes per
numeric field (int64 / float64, so every value comes back exactly) and one
byte per text field (``registration``: an index into the statuses seen so
far). ``docs/benchmarks.md`` ("Frame records kept by column") has what it saves.

It reads like the list it replaces: ``len``, indexing (a :class:`FrameRecord`
built on the fly; a slice gives a list of them), iteration; ``column(name)``
gives one field for every frame as an array. :meth:`state` /
:meth:`from_state` are what a checkpoint holds (one array per field; a
checkpoint written before, a list of one dict per frame, still reads).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import fields

import numpy as np

from mabdi.loop.loop import FrameRecord

#: Frames per block of storage.
BLOCK = 1024

_KINDS = {"int": np.int64, "float": np.float64, "str": np.uint8}


def _field_kinds() -> dict[str, str]:
    """FrameRecord's fields and their kind ("int", "float" or "str"), in declaration order."""
    kinds = {}
    for f in fields(FrameRecord):
        kind = f.type if isinstance(f.type, str) else f.type.__name__
        if kind not in _KINDS:
            raise TypeError(f"FrameRecord.{f.name} is {kind}: FrameRecords stores int, float and str fields only")
        kinds[f.name] = kind
    return kinds


class FrameRecords(Sequence):
    """The frame records of a run, by column (see the module docs)."""

    def __init__(self, records=()) -> None:
        self._kinds = _field_kinds()
        self._dtype = np.dtype([(name, _KINDS[kind]) for name, kind in self._kinds.items()])
        self._blocks: list[np.ndarray] = []
        self._length = 0
        self._labels: dict[str, list[str]] = {name: [] for name, kind in self._kinds.items() if kind == "str"}
        for record in records:
            self.append(record)

    def append(self, record: FrameRecord) -> None:
        """Add one frame's record at the end."""
        if self._length == len(self._blocks) * BLOCK:
            self._blocks.append(np.zeros(BLOCK, dtype=self._dtype))
        row = self._blocks[-1][self._length % BLOCK : self._length % BLOCK + 1]
        for name, kind in self._kinds.items():
            value = getattr(record, name)
            row[name] = self._code(name, value) if kind == "str" else value
        self._length += 1

    def _code(self, name: str, text: str) -> int:
        labels = self._labels[name]
        if text not in labels:
            if len(labels) == np.iinfo(np.uint8).max + 1:
                raise ValueError(f"FrameRecords: more than 256 distinct values of {name!r}")
            labels.append(text)
        return labels.index(text)

    def __len__(self) -> int:
        return self._length

    def __getitem__(self, index):
        if isinstance(index, slice):
            return [self[i] for i in range(*index.indices(self._length))]
        position = int(index)
        if position < 0:
            position += self._length
        if not 0 <= position < self._length:
            raise IndexError(f"frame record {index} out of range (the run has {self._length})")
        row = self._blocks[position // BLOCK][position % BLOCK]
        values = {}
        for name, kind in self._kinds.items():
            value = row[name].item()
            values[name] = self._labels[name][value] if kind == "str" else value
        return FrameRecord(**values)

    def __iter__(self) -> Iterator[FrameRecord]:
        for position in range(self._length):
            yield self[position]

    @property
    def nbytes(self) -> int:
        """Bytes the columns take (whole blocks, the last one's unused rows included)."""
        return sum(block.nbytes for block in self._blocks)

    def column(self, name: str) -> np.ndarray:
        """One field of every frame, in frame order (text fields as an array of str)."""
        if name not in self._kinds:
            raise KeyError(f"FrameRecord has no field {name!r} (fields: {', '.join(self._kinds)})")
        values = np.concatenate([block[name] for block in self._blocks])[: self._length] if self._blocks else np.zeros(0, self._dtype[name])
        if self._kinds[name] == "str":
            return np.array(self._labels[name], dtype=str)[values] if len(values) else np.zeros(0, dtype=str)
        return values.copy()

    def state(self) -> dict[str, np.ndarray]:
        """What a checkpoint keeps: one array per field (text fields as fixed-width strings)."""
        return {name: self.column(name) for name in self._kinds}

    @classmethod
    def from_state(cls, state) -> FrameRecords:
        """The records of :meth:`state`, or of a list of one field dict per frame (checkpoints written
        before the records were kept by column). A missing or unknown field is a TypeError naming it."""
        if isinstance(state, dict):
            lengths = {len(np.asarray(values)) for values in state.values()}
            if len(lengths) > 1:
                raise TypeError(f"frame record columns of different lengths: {sorted(lengths)}")
            count = lengths.pop() if lengths else 0
            columns = {name: np.asarray(values) for name, values in state.items()}
            rows = ({name: values[i].item() for name, values in columns.items()} for i in range(count))
        else:
            rows = iter(state)
        return cls(FrameRecord(**row) for row in rows)

    def __repr__(self) -> str:
        return f"FrameRecords({self._length} frames)"
