"""Exceptions raised by mabdi.

Every error a user can cause (a bad config, a bad pose, a missing file) is
raised as one of these, with a message that names the file, key, shape or
value at fault. They subclass the matching built-in exception so callers can
also catch ``ValueError`` / ``FileNotFoundError`` as usual.
"""

from __future__ import annotations


class MabdiError(Exception):
    """Base class of every error mabdi raises on purpose."""


class ConfigError(MabdiError, ValueError):
    """A run config (TOML) or a config value is invalid."""


class PoseError(MabdiError, ValueError):
    """A pose is not a rigid 4x4 ``world_from_camera`` matrix."""


class PoseFileWarning(UserWarning):
    """A recording's pose file held rotations written to a few digits, which mabdi made rigid (how many, by how much)."""


class AssetNotFoundError(MabdiError, FileNotFoundError):
    """A mesh file or built-in asset (the bunny) could not be found."""


class DamagedFileError(MabdiError, ValueError):
    """An input file that is cut short, empty, or not what its suffix says (a truncated PLY, a map with NaN vertices)."""


class WriteError(MabdiError, OSError):
    """A file could not be written completely (a full disk, a failing writer); nothing was left under its name."""


def check_switch(name: str, value) -> None:
    """Raise :class:`ConfigError` unless ``value`` is a switch that may be left to the input: true, false or
    "auto" (what "auto" means is the parameter's own)."""
    if not isinstance(value, (bool, str)) or value not in (True, False, "auto"):
        raise ConfigError(f'{name} must be true, false or "auto", got {value!r}')


class RenderBackendError(MabdiError, RuntimeError):
    """A render backend cannot be used on this machine (its system library is missing)."""
