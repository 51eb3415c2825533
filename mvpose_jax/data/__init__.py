"""Data edges: calibration files and rig presets, detection recordings in every format."""

from mvpose_jax.data.formats import FORMATS, load_recording, save_recording
from mvpose_jax.data.native import read_native, read_native_rig, write_native
from mvpose_jax.data.npz import read_npz, write_npz
from mvpose_jax.data.openpose import read_openpose, save_openpose
from mvpose_jax.data.original import read_original, write_original
from mvpose_jax.data.recording import Recording, convert_layout, select_cameras

__all__ = [
    "FORMATS",
    "Recording",
    "convert_layout",
    "load_recording",
    "read_native",
    "read_native_rig",
    "read_npz",
    "read_openpose",
    "read_original",
    "save_openpose",
    "save_recording",
    "select_cameras",
    "write_native",
    "write_npz",
    "write_original",
]
