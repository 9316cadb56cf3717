"""The in-memory index of one tracked subject, shared by every reader (VHAP layout, INSTA).

A reader turns a folder into a `Subject`: one `FrameRecord` per (timestep, camera) with the image
and mask paths and the camera in our convention (viewmat world-to-camera with OpenCV axes, K in
pixels with pixel centres at +0.5), and the head-model parameters of every timestep stacked into
tensors. The torch Dataset (`geoavatar.data.dataset`) reads only this object, so all layouts flow
through the same code.

Parameters follow the FLAME npz layout of VHAP / GaussianAvatars (one npz per timestep):

    translation [1,3]  rotation [1,3]  neck_pose [1,3]  jaw_pose [1,3]  eyes_pose [1,6]
    expr [1,E]         shape [S]       static_offset [1,V,3] (optional)
    dynamic_offset [1,V,3], eyelids [1,2] (optional extras, passed through)

rotations are axis-angle; eyes_pose is left eye then right eye (FLAME joints 3 and 4). `Subject.params`
holds the per-timestep keys stacked as [T, ...] (row i = `Subject.timesteps[i]`) and the subject keys
`shape` [S] and `static_offset` [1,V,3] once.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import torch
from torch import Tensor

from geoavatar.data.errors import DatasetError
from geoavatar.data.splits import ExplicitSplit, Split, SplitConfig, split_timesteps
from geoavatar.head.params import SUBJECT_KEYS, npz_frame  # SUBJECT_KEYS: shape, static_offset (every timestep)

# Per-timestep keys with a fixed size: name -> number of values (stored as [1, n]).
POSE_SIZES: dict[str, int] = {"translation": 3, "rotation": 3, "neck_pose": 3, "jaw_pose": 3, "eyes_pose": 6}
REQUIRED_FRAME_KEYS: tuple[str, ...] = (*POSE_SIZES, "expr", "shape")
OPTIONAL_FRAME_KEYS: tuple[str, ...] = ("static_offset", "dynamic_offset", "eyelids")


@dataclass
class FrameRecord:
    """One image of the subject: where it is, the camera that took it, its timestep."""

    timestep: int  # frame index T in the video
    camera: int  # camera index (0 for a monocular video)
    image_path: Path
    mask_path: Path | None  # None: the mask is the image's alpha channel, or absent (all ones)
    viewmat: np.ndarray  # [4, 4] float64 world-to-camera, OpenCV axes
    K: np.ndarray  # [3, 3] float64 pixels, for an image of width x height
    width: int
    height: int
    row: int  # row of this timestep in Subject.params
    where: str  # where the record came from, for error messages ("transforms_train.json, frame 3")
    view: str | None = None  # name of the camera placement in an extra split ("yaw+30"; "front")


@dataclass
class SubjectInfo:
    """Our own metadata of a dataset (geoavatar.json); defaults describe a plain VHAP export."""

    head_model: str = "flame"
    image_size: tuple[int, int] | None = None  # (width, height)
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)  # VHAP composites images on white
    mouth: str | None = None
    source: str | None = None
    format_version: int = 1


@dataclass
class Subject:
    """A tracked subject, ready for the Dataset. See the module docstring for the parameter layout."""

    root: Path
    layout: str  # "vhap" or "insta"
    info: SubjectInfo
    frames: list[FrameRecord]  # sorted by (timestep, camera)
    timesteps: tuple[int, ...]  # sorted, unique; row i of the per-timestep params
    params: dict[str, Tensor]  # per-timestep keys [T, ...]; shape [S]; static_offset [1, V, 3]
    canonical: dict[str, Tensor] = field(default_factory=dict)  # canonical_flame_param.npz, if any
    explicit_split: ExplicitSplit | None = None
    # Extra splits (layout.EXTRA_SPLIT_FILES, e.g. "novel"): frames in none of the splits above.
    extra_frames: dict[str, list[FrameRecord]] = field(default_factory=dict)

    @property
    def head_model(self) -> str:
        return self.info.head_model

    @property
    def num_timesteps(self) -> int:
        return len(self.timesteps)

    def frame_params(self, row: int) -> dict[str, Tensor]:
        """Parameters of one timestep in the npz layout: per-frame keys [1, ...], shape [S]."""
        return npz_frame(self.params, row)

    def split(self, config: SplitConfig | None = None) -> Split:
        return split_timesteps(self.timesteps, config, self.explicit_split, source=str(self.root))

    def frames_of(self, timesteps: Sequence[int]) -> list[FrameRecord]:
        wanted = set(timesteps)
        return [frame for frame in self.frames if frame.timestep in wanted]


def normalize_frame_params(arrays: Mapping[str, np.ndarray], where: str) -> dict[str, np.ndarray]:
    """Check one timestep's parameters against the npz layout; return float32 arrays in its shapes.

    Accepts [n] or [1, n] for the pose keys and expr, [S] or [1, S] for shape, [V, 3] or [1, V, 3]
    for offsets. Raises DatasetError naming `where` and the key when something is missing or wrong.
    """
    missing = [key for key in REQUIRED_FRAME_KEYS if key not in arrays]
    if missing:
        raise DatasetError(f"{where}: missing parameter(s) {', '.join(missing)} (have: {', '.join(sorted(arrays))})")
    out: dict[str, np.ndarray] = {}
    for key, size in POSE_SIZES.items():
        out[key] = _row(arrays[key], key, where, expect=size)
    out["expr"] = _row(arrays["expr"], "expr", where)
    shape = np.asarray(arrays["shape"])
    if shape.ndim == 2 and shape.shape[0] == 1:
        shape = shape[0]
    if shape.ndim != 1 or shape.size == 0:
        raise DatasetError(f"{where}: 'shape' must have shape (S,) or (1, S), got {tuple(np.shape(arrays['shape']))}")
    out["shape"] = _finite(shape, "shape", where)
    for key in ("static_offset", "dynamic_offset"):
        if key in arrays:
            offset = np.asarray(arrays[key])
            if offset.ndim == 2:
                offset = offset[None]
            if offset.ndim != 3 or offset.shape[0] != 1 or offset.shape[2] != 3:
                raise DatasetError(f"{where}: '{key}' must have shape (1, V, 3), got {tuple(np.shape(arrays[key]))}")
            out[key] = _finite(offset, key, where)
    if "eyelids" in arrays:
        out["eyelids"] = _row(arrays["eyelids"], "eyelids", where, expect=2)
    return out


def _row(value: np.ndarray, key: str, where: str, expect: int | None = None) -> np.ndarray:
    array = np.asarray(value)
    if array.ndim == 1:
        array = array[None]
    ok = array.ndim == 2 and array.shape[0] == 1 and array.shape[1] > 0
    if ok and expect is not None:
        ok = array.shape[1] == expect
    if not ok:
        wanted = f"(1, {expect})" if expect is not None else "(1, n)"
        raise DatasetError(f"{where}: '{key}' must have shape {wanted}, got {tuple(np.shape(value))}")
    return _finite(array, key, where)


def _finite(array: np.ndarray, key: str, where: str) -> np.ndarray:
    if not np.issubdtype(array.dtype, np.number):
        raise DatasetError(f"{where}: '{key}' is not numeric (dtype {array.dtype})")
    array = array.astype(np.float32)
    if not np.isfinite(array).all():
        raise DatasetError(f"{where}: '{key}' contains NaN or infinite values")
    return array


def stack_params(
    per_timestep: Sequence[Mapping[str, np.ndarray]],
    wheres: Sequence[str],
    subject_keys_from: Mapping[str, np.ndarray] | None = None,
) -> dict[str, Tensor]:
    """Stack normalised per-timestep parameters into [T, ...] tensors.

    The subject keys (shape, static_offset) come from `subject_keys_from` (the canonical npz) when
    given, else from the first timestep. Every timestep must carry the same keys with the same
    shapes; a mismatch raises DatasetError naming the file.
    """
    if not per_timestep:
        raise DatasetError("no frames to stack parameters from")
    first, first_where = per_timestep[0], wheres[0]
    frame_keys = [key for key in first if key not in SUBJECT_KEYS]
    for params, where in zip(per_timestep, wheres):
        keys = {key for key in params if key not in SUBJECT_KEYS}
        if keys != set(frame_keys):
            raise DatasetError(
                f"{where}: parameter keys {sorted(keys)} differ from those of {first_where} {sorted(frame_keys)}"
            )
        for key in frame_keys:
            if params[key].shape != first[key].shape:
                raise DatasetError(
                    f"{where}: '{key}' has shape {params[key].shape} but {first_where} has {first[key].shape}"
                )
    stacked = {key: torch.from_numpy(np.concatenate([p[key] for p in per_timestep], axis=0)) for key in frame_keys}
    for key in SUBJECT_KEYS:
        source = subject_keys_from if subject_keys_from is not None and key in subject_keys_from else first
        if key in source:
            stacked[key] = torch.from_numpy(np.asarray(source[key], dtype=np.float32).copy())
    return stacked


__all__ = [
    "FrameRecord", "OPTIONAL_FRAME_KEYS", "POSE_SIZES", "REQUIRED_FRAME_KEYS", "Subject",
    "SubjectInfo", "normalize_frame_params", "stack_params",
]
