"""The helical sensor path of seed 001 §4.1.

The sensor circles the scene ``turns`` times (twice by default) on an
ellipse with radii ``radius_x``, ``radius_y`` (m) about ``center`` (x, y),
rising linearly from height ``z0`` to ``z1``, and looks at a point that moves
linearly from ``look_from`` to ``look_to``: each pass sees the scene from a
slightly different place, and the second pass returns to parts already
mapped. Frame i of N sits at t = i / (N - 1) along the whole path, so N
frames always span the same helix; more frames are finer steps.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from mabdi.camera import look_at
from mabdi.config import PathConfig
from mabdi.errors import ConfigError


def helical_path(frames: int, **parameters) -> np.ndarray:
    """(frames, 4, 4) ``world_from_camera`` poses along the helix (metres; ``start_angle`` in degrees).

    ``parameters`` are the keys of :class:`mabdi.config.PathConfig` (``center``,
    ``radius_x``, ``radius_y``, ``z0``, ``z1``, ``look_from``, ``look_to``,
    ``turns``, ``start_angle``), which also holds their defaults. The angle
    runs counter-clockwise seen from above, starting at ``start_angle``
    (-90 degrees = on the -y side of the centre).
    """
    unknown = sorted(set(parameters) - {f.name for f in dataclasses.fields(PathConfig)})
    if unknown:
        raise TypeError(f"helical_path: unknown parameter {unknown[0]!r}")
    return path_from_config(frames, PathConfig(**parameters))


def circle_index(frames: int, turns: float) -> np.ndarray:
    """(frames,) which circle of the helix each frame is in (frame i at t = i / (N - 1); the last
    frame counts to the last circle)."""
    circles = max(1, int(round(turns)))
    t = np.arange(frames) / max(frames - 1, 1)
    return np.minimum((t * turns).astype(int), circles - 1)


def path_targets(frames: int, config: PathConfig) -> np.ndarray:
    """(frames, 3) look-at points of :func:`path_from_config` (where each pose looks)."""
    t = np.linspace(0.0, 1.0, frames) if frames > 1 else np.zeros(1)
    a, b = np.asarray(config.look_from), np.asarray(config.look_to)
    return a + t[:, None] * (b - a)


def path_from_config(frames: int, config: PathConfig) -> np.ndarray:
    """(frames, 4, 4) poses along the helix of a ``[path]`` config section (see :func:`helical_path`)."""
    if isinstance(frames, bool) or not isinstance(frames, (int, np.integer)) or frames < 1:
        raise ConfigError(f"helical_path: frames must be a positive integer, got {frames!r}")
    t = np.linspace(0.0, 1.0, frames) if frames > 1 else np.zeros(1)
    angle = math.radians(config.start_angle) + 2.0 * math.pi * config.turns * t
    eye = np.stack(
        [
            config.center[0] + config.radius_x * np.cos(angle),
            config.center[1] + config.radius_y * np.sin(angle),
            config.z0 + (config.z1 - config.z0) * t,
        ],
        axis=1,
    )
    return np.stack([look_at(e, g) for e, g in zip(eye, path_targets(frames, config), strict=True)])
