"""Data edges: calibration files and rig presets, detection recordings in every format."""

from mvpose_jax.data.formats import FORMATS, load_recording, open_recording, save_recording
from mvpose_jax.data.native import read_native, read_native_rig, write_native
from mvpose_jax.data.npz import read_npz, write_npz
from mvpose_jax.data.openpose import read_openpose, save_openpose
from mvpose_jax.data.original import read_original, write_original
from mvpose_jax.data.recording import Recording, convert_layout, select_cameras, slice_frames
from mvpose_jax.data.stream import RecordingStream

__all__ = [
    "FORMATS",
    "Recording",
    "RecordingStream",
    "convert_layout",
    "load_recording",
    "open_recording",
    "read_native",
    "read_native_rig",
    "read_npz",
    "read_openpose",
    "read_original",
    "save_openpose",
    "save_recording",
    "select_cameras",
    "slice_frames",
    "write_native",
    "write_npz",
    "write_original",
]
