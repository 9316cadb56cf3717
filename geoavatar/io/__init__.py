"""Everything GeoAvatar writes goes through here: atomic files and folders (atomic.py, with the
umask's permissions and a one-line DiskFullError), the one mp4 writer (video.py) and the standard
3DGS PLY (ply.py). Pickles that are not ours (FLAME's, LPIPS's weights) are read only through the
restricted unpickler (safe_pickle.py)."""

from geoavatar.io.atomic import (
    DiskFullError, atomic_file, atomic_folder, atomic_write_bytes, atomic_write_json, atomic_write_npz, atomic_write_png,
    atomic_write_text, disk_full_as_error, file_mode, folder_mode, replace_folder, temporary_folder_for,
)
from geoavatar.io.ply import GaussianPly, PLY_PROPERTIES, read_gaussian_ply, write_gaussian_ply
from geoavatar.io.video import Mp4Writer, pad_to_even, write_mp4

__all__ = [
    "DiskFullError", "GaussianPly", "Mp4Writer", "PLY_PROPERTIES", "atomic_file", "atomic_folder", "atomic_write_bytes",
    "atomic_write_json", "atomic_write_npz", "atomic_write_png", "atomic_write_text", "disk_full_as_error",
    "file_mode", "folder_mode", "pad_to_even", "read_gaussian_ply", "replace_folder", "temporary_folder_for",
    "write_gaussian_ply", "write_mp4",
]
