"""TOML text from nested dicts: the one writer behind a run's ``config.toml`` and a sequence's ``mabdi.toml``.

Python reads TOML (``tomllib``) but does not write it; mabdi writes two
kinds of file, both read back with ``tomllib``: the resolved run config
(:func:`mabdi.config.dump_toml`, which turns the config's dataclasses into a
dict first) and the metadata beside a recorded sequence
(:func:`mabdi.sources.sequence_files.metadata_toml`).

A table is a dict, written in its own order: its plain keys first, then its
sub-tables (dict values, as ``[a.b]``), then its arrays of tables (non-empty
lists of dicts, as ``[[a.b]]``). Values: bool, int, float (``nan``, ``inf``
and ``-inf`` as TOML spells them), str, lists and tuples, and numpy scalars
and arrays (as their Python values). Keys that are not bare (letters, digits,
``-``, ``_``) are quoted. Anything else is a ``TypeError`` naming the key.
"""

from __future__ import annotations

import math

_ESCAPES = {'"': '\\"', "\\": "\\\\", "\b": "\\b", "\t": "\\t", "\n": "\\n", "\f": "\\f", "\r": "\\r"}


def _string(text: str) -> str:
    """A TOML basic string: quotes, backslashes and control characters escaped."""
    out = []
    for c in text:
        if c in _ESCAPES:
            out.append(_ESCAPES[c])
        elif ord(c) < 0x20 or ord(c) == 0x7F:
            out.append(f"\\u{ord(c):04X}")
        else:
            out.append(c)
    return '"' + "".join(out) + '"'


def toml_key(key) -> str:
    """A key as TOML writes it: bare when it can be, quoted otherwise."""
    key = str(key)
    if key and all(c.isalnum() or c in "-_" for c in key):
        return key
    return _string(key)


def toml_value(value, where: str = "value") -> str:
    """One value as TOML text (see the module docs); ``where`` names the key in the error for a value TOML cannot hold."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isfinite(value):
            return repr(value)
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")
    if isinstance(value, str):
        return _string(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_value(v, where) for v in value) + "]"
    if hasattr(value, "item") and getattr(value, "shape", None) == ():  # numpy scalars
        return toml_value(value.item(), where)
    if hasattr(value, "tolist"):  # numpy arrays
        return toml_value(value.tolist(), where)
    raise TypeError(f"cannot write {where} = {value!r} ({type(value).__name__}) to TOML")


def _is_table_array(value) -> bool:
    return isinstance(value, list) and bool(value) and all(isinstance(item, dict) for item in value)


def toml_lines(table: dict, prefix: str = "") -> list[str]:
    """The lines of ``table`` (a dict) as TOML, its sub-tables named under ``prefix`` (``"a."`` for table ``a``)."""
    lines = []
    for key, value in table.items():
        if not isinstance(value, dict) and not _is_table_array(value):
            lines.append(f"{toml_key(key)} = {toml_value(value, prefix + str(key))}")
    for key, value in table.items():
        if isinstance(value, dict):
            name = prefix + toml_key(key)
            lines.extend(["", f"[{name}]", *toml_lines(value, name + ".")])
    for key, value in table.items():
        if _is_table_array(value):
            name = prefix + toml_key(key)
            for item in value:
                lines.extend(["", f"[[{name}]]", *toml_lines(item, name + ".")])
    return lines
