"""The simulator: a scene, a depth sensor (camera or LiDAR) with its noise, and the paths it is carried along.

:class:`SimulatedRig` renders D from a scene along a path (:func:`helical_path`, waypoints, a recorded
trajectory: :mod:`mabdi.simulate.path`); the MABDI loop and the runs that drive it are in :mod:`mabdi.loop`.
"""

from mabdi.simulate.path import helical_path, path_from_config
from mabdi.simulate.rig import SimulatedRig

__all__ = ["SimulatedRig", "helical_path", "path_from_config"]
