"""Sources: the simulated world (SourceScene), its primitives and mesh assets, and sources of depth frames
(frames in memory, TUM RGB-D folders, ROS 2 bags, the 3DMatch / 7-Scenes, Redwood / Open3D, ScanNet, Replica and
Stray Scanner layouts)."""

from mabdi.sources.assets import bunny_path, read_mesh
from mabdi.sources.frames import FrameList, FrameSource, SourceDepthFrames, StreamedFrames, StreamOrderError
from mabdi.sources.redwood import RedwoodSequence, write_redwood
from mabdi.sources.replica import ReplicaSequence, write_replica
from mabdi.sources.rosbag2 import Rosbag2Sequence, write_rosbag2
from mabdi.sources.scannet import ScanNetSequence, write_scannet
from mabdi.sources.scene import SourceScene
from mabdi.sources.stray import StraySequence, write_stray
from mabdi.sources.sequences import SequenceError, open_sequence, read_sequence_metadata
from mabdi.sources.threedmatch import ThreeDMatchSequence, write_3dmatch
from mabdi.sources.tum import TumSequence, write_tum

__all__ = [
    "FrameList",
    "StreamedFrames",
    "StreamOrderError",
    "FrameSource",
    "RedwoodSequence",
    "ReplicaSequence",
    "Rosbag2Sequence",
    "ScanNetSequence",
    "SequenceError",
    "SourceDepthFrames",
    "SourceScene",
    "StraySequence",
    "ThreeDMatchSequence",
    "TumSequence",
    "bunny_path",
    "open_sequence",
    "read_mesh",
    "read_sequence_metadata",
    "write_3dmatch",
    "write_redwood",
    "write_replica",
    "write_rosbag2",
    "write_scannet",
    "write_stray",
    "write_tum",
]
