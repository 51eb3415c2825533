"""Data edges: calibration files and rig presets, detection recordings in every format, Pose2Sim
projects."""

from mvpose_jax.data.formats import FORMATS, load_recording, open_recording, save_recording
from mvpose_jax.data.native import read_native, read_native_rig, write_native
from mvpose_jax.data.npz import read_npz, write_npz
from mvpose_jax.data.openpose import parse_camera_map, read_openpose, save_openpose
from mvpose_jax.data.original import read_original, write_original
from mvpose_jax.data.pose2sim import (
    Pose2SimSession,
    Pose2SimTrial,
    find_trials,
    is_pose2sim_project,
    open_trial,
    trc_name,
)
from mvpose_jax.data.recording import Recording, convert_layout, select_cameras, slice_frames
from mvpose_jax.data.stream import ReadReport, RecordingStream

__all__ = [
    "FORMATS",
    "Pose2SimSession",
    "Pose2SimTrial",
    "ReadReport",
    "Recording",
    "RecordingStream",
    "convert_layout",
    "find_trials",
    "is_pose2sim_project",
    "load_recording",
    "open_recording",
    "open_trial",
    "parse_camera_map",
    "read_native",
    "read_native_rig",
    "read_npz",
    "read_openpose",
    "read_original",
    "save_openpose",
    "save_recording",
    "select_cameras",
    "slice_frames",
    "trc_name",
    "write_native",
    "write_npz",
    "write_original",
]
