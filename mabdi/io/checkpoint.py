"""Checkpoint files: a tree of plain data in one ``.npz``, loaded without pickle.

A checkpoint holds data only: numpy arrays (numeric, bool or fixed-width
string dtypes; never ``object``) and a JSON header. Loading it runs no code:
the file is read with ``numpy.load(..., allow_pickle=False)`` and the header
with ``json.loads``; anything else in the file is an error.

**Format** (:data:`FORMAT`, version :data:`VERSION`): an uncompressed
``numpy.savez`` archive with

* ``header``: a uint8 array, the UTF-8 JSON text of
  ``{"format": "mabdi-checkpoint", "version": 2, "tree": NODE}``;
* ``a0``, ``a1``, ...: the arrays the tree refers to.

A ``NODE`` is a JSON value: ``null``, a bool, a number or a string stands for
itself; ``{"array": "a7"}`` is an array; ``{"scalar": 0.5, "dtype":
"float32"}`` a numpy scalar (its dtype kept); ``{"list": [NODE, ...]}`` a list
(tuples come back as lists); ``{"dict": [[KEY, NODE], ...]}`` a dict (keys
str or int, order kept). Non-finite floats are written as JSON's
``NaN`` / ``Infinity`` (Python's ``json`` reads them back).

:func:`encode` / :func:`decode` turn any such tree into (header, arrays) and
back; :func:`write_tree` / :func:`read_tree` add the file. Whoever adds state
to :meth:`mabdi.loop.loop.MabdiLoop.state` only needs to keep it to
dicts, lists, numbers, strings, None and numpy arrays.
"""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np

from mabdi.errors import MabdiError
from mabdi.io.atomic import atomic_output

FORMAT = "mabdi-checkpoint"
VERSION = 2


class CheckpointError(MabdiError, ValueError):
    """A checkpoint cannot be written (state that is not plain data) or read (damaged, foreign, other version)."""


def encode(tree, arrays: dict[str, np.ndarray] | None = None, where: str = "state") -> tuple[object, dict[str, np.ndarray]]:
    """(JSON-able header node, {name: array}) of a tree of plain data (see the module docs).

    Raises :class:`CheckpointError` naming the path (``state.loop.world...``) of anything else.
    """
    arrays = {} if arrays is None else arrays
    if tree is None or isinstance(tree, (bool, str)):
        return tree, arrays
    if isinstance(tree, (int, float)) and not isinstance(tree, np.generic):
        return tree, arrays
    if isinstance(tree, np.ndarray):
        if tree.dtype.hasobject or tree.dtype.kind not in "biufcSU":
            raise CheckpointError(f"checkpoint: {where} is an array of dtype {tree.dtype}, not plain data")
        name = f"a{len(arrays)}"
        arrays[name] = tree
        return {"array": name}, arrays
    if isinstance(tree, np.generic):
        if tree.dtype.hasobject:
            raise CheckpointError(f"checkpoint: {where} is a numpy object scalar, not plain data")
        return {"scalar": tree.item(), "dtype": tree.dtype.str}, arrays
    if isinstance(tree, (list, tuple)):
        return {"list": [encode(item, arrays, f"{where}[{i}]")[0] for i, item in enumerate(tree)]}, arrays
    if isinstance(tree, dict):
        items = []
        for key, value in tree.items():
            if isinstance(key, np.integer):
                key = int(key)
            if not isinstance(key, (str, int)) or isinstance(key, bool):
                raise CheckpointError(f"checkpoint: {where} has a key {key!r} that is not a string or an integer")
            items.append([key, encode(value, arrays, f"{where}.{key}")[0]])
        return {"dict": items}, arrays
    raise CheckpointError(f"checkpoint: {where} is a {type(tree).__name__}, not plain data (dicts, lists, numbers, strings, arrays)")


def decode(node, arrays, where: str = "state"):
    """The tree of :func:`encode`'s header node, its arrays taken from ``arrays`` (a mapping name -> array)."""
    if node is None or isinstance(node, (bool, int, float, str)):
        return node
    if isinstance(node, dict) and len(node) == 1 and "array" in node:
        try:
            return arrays[node["array"]]
        except KeyError:
            raise CheckpointError(f"checkpoint: {where} refers to an array {node['array']!r} the file does not hold") from None
    if isinstance(node, dict) and set(node) == {"scalar", "dtype"}:
        dtype = np.dtype(node["dtype"])
        if dtype.hasobject:
            raise CheckpointError(f"checkpoint: {where}: object dtype")
        return dtype.type(node["scalar"])
    if isinstance(node, dict) and set(node) == {"list"} and isinstance(node["list"], list):
        return [decode(item, arrays, f"{where}[{i}]") for i, item in enumerate(node["list"])]
    if isinstance(node, dict) and set(node) == {"dict"} and isinstance(node["dict"], list):
        out = {}
        for item in node["dict"]:
            if not (isinstance(item, list) and len(item) == 2 and isinstance(item[0], (str, int))):
                raise CheckpointError(f"checkpoint: {where}: a dict entry is not [key, value]")
            out[item[0]] = decode(item[1], arrays, f"{where}.{item[0]}")
        return out
    raise CheckpointError(f"checkpoint: {where}: unknown header node {str(node)[:80]!r}")


def write_tree(path, tree) -> None:
    """Write ``tree`` (plain data) as a checkpoint file at ``path``, atomically."""
    node, arrays = encode(tree)
    header = json.dumps({"format": FORMAT, "version": VERSION, "tree": node}, separators=(",", ":"))
    arrays = {name: np.ascontiguousarray(array) for name, array in arrays.items()}
    with atomic_output(path) as temporary, open(temporary, "wb") as stream:
        np.savez(stream, header=np.frombuffer(header.encode("utf-8"), dtype=np.uint8), **arrays)


def read_tree(path):
    """The tree in the checkpoint file ``path``; never unpickles or runs anything.

    Raises :class:`CheckpointError` when the file is damaged, not a checkpoint, or of another version.
    """
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as archive:
            if "header" not in archive.files:
                raise CheckpointError(f"{path} is not a mabdi checkpoint (no header)")
            header = json.loads(archive["header"].tobytes().decode("utf-8"))
            if not isinstance(header, dict) or header.get("format") != FORMAT:
                raise CheckpointError(f"{path} is not a mabdi checkpoint")
            if header.get("version") != VERSION:
                raise CheckpointError(
                    f"{path} is a checkpoint of format version {header.get('version')!r}; this mabdi reads version {VERSION}"
                )
            arrays = {name: archive[name] for name in archive.files if name != "header"}
    except CheckpointError:
        raise
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, UnicodeDecodeError, EOFError) as exc:
        # ValueError includes numpy's refusal of object arrays (allow_pickle=False)
        raise CheckpointError(f"{path} is damaged or not a checkpoint ({type(exc).__name__}: {exc})") from None
    return decode(header["tree"], arrays)
