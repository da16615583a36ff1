"""Sources: the simulated world (SourceScene), its primitives and mesh assets, and sources of depth frames
(frames in memory, TUM RGB-D folders, ROS 2 bags)."""

from mabdi.sources.assets import bunny_path, read_mesh
from mabdi.sources.frames import FrameList, FrameSource, SourceDepthFrames
from mabdi.sources.rosbag2 import Rosbag2Sequence, write_rosbag2
from mabdi.sources.scene import SourceScene
from mabdi.sources.sequences import SequenceError, open_sequence, read_sequence_metadata
from mabdi.sources.tum import TumSequence, write_tum

__all__ = [
    "FrameList",
    "FrameSource",
    "Rosbag2Sequence",
    "SequenceError",
    "SourceDepthFrames",
    "SourceScene",
    "TumSequence",
    "bunny_path",
    "open_sequence",
    "read_mesh",
    "read_sequence_metadata",
    "write_rosbag2",
    "write_tum",
]
