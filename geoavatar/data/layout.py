"""Read and write the VHAP / GaussianAvatars dataset layout (plus our small geoavatar.json).

Layout (what VHAP's `export_as_nerf_dataset.py` writes and GaussianAvatars reads)::

    <root>/
      transforms.json                 all frames (VHAP writes it; optional for reading)
      transforms_train.json           the split files (GaussianAvatars needs them)
      transforms_val.json
      transforms_test.json
      images/00000_00.png             <timestep:05d>_<camera:02d>.png, RGB (VHAP: composited on white)
      fg_masks/00000_00.png           foreground masks, 8-bit gray (optional)
      flame_param/00000.npz           one npz per timestep, keys below
      canonical_flame_param.npz       zero pose / expression, jaw open 0.3 rad; marks the layout
      geoavatar.json                  ours: {"format_version": 1, "head_model": "flame"|"openhead",
                                      "image_size": [w, h], "background": [r, g, b], "mouth", "source"}

Fields read from each frame of a transforms file: `timestep_index` (required), `camera_index`
(default 0), `file_path` (".png" is appended when it has no extension, as GaussianAvatars does),
`fg_mask_path` (optional; an RGBA image's alpha serves when absent), `flame_param_path` (required),
`transform_matrix` (camera-to-world, OpenGL axes: +y up, +z backward; converted with
`geoavatar.render.camera.opengl_c2w_to_viewmat`), intrinsics `fl_x`, `fl_y`, `cx`, `cy`, `w`, `h`
(per frame, else the file's top level, as VHAP writes both), or `camera_angle_x` with the principal
point at the image centre when no focal length is given. VHAP and GaussianAvatars put the image
centre at (w/2, h/2) — the same continuous pixel coordinates as ours (pixel centres at +0.5) — so K
is used unchanged. `timestep_indices` at the top level, when present, must match the frames.

Per-timestep npz keys (VHAP writes one file per timestep, with `shape` and `static_offset` copied
into each): translation (1,3), rotation (1,3), neck_pose (1,3), jaw_pose (1,3), eyes_pose (1,6),
shape (300,), expr (1,100), static_offset (1,V,3), optional dynamic_offset (1,V,3). The reader takes
shape / static_offset from canonical_flame_param.npz when it exists (else from the first timestep).
npz files are read with allow_pickle=False.

A dataset without geoavatar.json is a plain VHAP export and is read as FLAME (logged). Splits: the
split files are kept as `Subject.explicit_split`; `geoavatar.data.splits` decides whether they rule.

Writing (`LayoutWriter`, used by the synthetic-subject generator and converters) goes frame by
frame, so a long video never sits in memory, into a hidden temporary folder beside the target;
`finish()` writes the canonical npz, the transforms files and geoavatar.json last, then renames the
folder into place. A half-written dataset therefore never exists under the target name.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
from dataclasses import asdict
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

import numpy as np
import torch
from PIL import Image
from torch import Tensor

from geoavatar.data.errors import DatasetError
from geoavatar.data.splits import ExplicitSplit, SplitConfig, split_timesteps
from geoavatar.data.subject import (
    POSE_SIZES,
    FrameRecord,
    Subject,
    SubjectInfo,
    normalize_frame_params,
    stack_params,
)
from geoavatar.errors import DiskFullError
from geoavatar.head.base import FLAME_EXPR_DIM, FLAME_SHAPE_DIM
from geoavatar.imaging import to_uint8
from geoavatar.io.atomic import atomic_write_npz, disk_full_as_error, replace_folder, temporary_folder_for
from geoavatar.render.camera import field_of_view, focal_length, opengl_c2w_to_viewmat, viewmat_to_opengl_c2w

log = logging.getLogger(__name__)

INFO_FILE = "geoavatar.json"
CANONICAL_FILE = "canonical_flame_param.npz"
FORMAT_VERSION = 1
HEAD_MODEL_NAMES = ("flame", "openhead")
SPLIT_FILES = {"train": "transforms_train.json", "val": "transforms_val.json", "test": "transforms_test.json"}
# Extra splits: views listed in their own transforms file and in no other (not in transforms.json), so
# that readers that know nothing of them (GaussianAvatars) never train or test on them. "novel": test
# timesteps seen from other cameras (`geoavatar synth --novel-views`), for `geoavatar eval --split novel`.
EXTRA_SPLIT_FILES = {"novel": "transforms_novel.json"}
ALL_FILE = "transforms.json"
CANONICAL_JAW_OPEN = 0.3  # rad, as VHAP's canonical_flame_param.npz (open mouth)


# --- geoavatar.json --------------------------------------------------------------------------------


def read_info(root: Path) -> SubjectInfo | None:
    """geoavatar.json of `root`, or None when the dataset has none (a plain VHAP export)."""
    path = Path(root) / INFO_FILE
    if not path.is_file():
        return None
    try:
        raw = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise DatasetError(f"{path}: not readable JSON ({err})") from err
    if not isinstance(raw, dict):
        raise DatasetError(f"{path}: expected a JSON object")
    version = raw.get("format_version", 1)
    if not isinstance(version, int) or version > FORMAT_VERSION:
        raise DatasetError(f"{path}: format_version {version!r} is newer than this reader ({FORMAT_VERSION})")
    head = raw.get("head_model")
    if head not in HEAD_MODEL_NAMES:
        raise DatasetError(f"{path}: head_model must be one of {', '.join(HEAD_MODEL_NAMES)}, got {head!r}")
    size = raw.get("image_size")
    if size is not None and not (isinstance(size, list) and len(size) == 2 and all(isinstance(v, int) and v > 0 for v in size)):
        raise DatasetError(f"{path}: image_size must be [width, height] in pixels, got {size!r}")
    background = raw.get("background", [1.0, 1.0, 1.0])
    if not (isinstance(background, list) and len(background) == 3):
        raise DatasetError(f"{path}: background must be [r, g, b] in [0, 1], got {background!r}")
    return SubjectInfo(
        head_model=head,
        image_size=tuple(size) if size is not None else None,
        background=tuple(float(v) for v in background),
        mouth=raw.get("mouth"),
        source=raw.get("source"),
        format_version=version,
    )


def info_to_json(info: SubjectInfo) -> dict[str, Any]:
    raw = asdict(info)
    raw["image_size"] = list(info.image_size) if info.image_size is not None else None
    raw["background"] = list(info.background)
    return {key: value for key, value in raw.items() if value is not None}


# --- reading -------------------------------------------------------------------------------------


def is_layout(root: Path) -> bool:
    """True when `root` looks like a VHAP / GaussianAvatars dataset."""
    root = Path(root)
    return (root / CANONICAL_FILE).is_file() or any((root / name).is_file() for name in (ALL_FILE, *SPLIT_FILES.values()))


def read_layout(root: str | os.PathLike) -> Subject:
    """Index a VHAP / GaussianAvatars dataset; check that every referenced file exists.

    Raises DatasetError naming the file for missing images / npz files, wrong parameter shapes,
    inconsistent frame counts or unreadable JSON.
    """
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{root}: dataset folder not found")
    info = read_info(root)
    if info is None:
        log.info("%s: no %s; reading it as a VHAP export with FLAME parameters", root, INFO_FILE)
        info = SubjectInfo(head_model="flame")

    transforms = {name: _read_json(root / fname) for name, fname in SPLIT_FILES.items() if (root / fname).is_file()}
    if (root / ALL_FILE).is_file():
        transforms["all"] = _read_json(root / ALL_FILE)
    if not transforms:
        raise DatasetError(f"{root}: no transforms.json or transforms_{{train,val,test}}.json found")

    records: dict[tuple[int, int], tuple[dict, dict, str]] = {}  # (timestep, camera) -> frame, top, where
    split_timesteps_listed: dict[str, set[int]] = {}
    for name in ("all", "train", "val", "test"):
        if name not in transforms:
            continue
        top, fname = transforms[name], (ALL_FILE if name == "all" else SPLIT_FILES[name])
        frames = top.get("frames")
        if not isinstance(frames, list):
            raise DatasetError(f"{root / fname}: has no 'frames' list")
        listed = set()
        for i, frame in enumerate(frames):
            where = f"{root / fname}, frame {i}"
            if not isinstance(frame, dict) or "timestep_index" not in frame:
                raise DatasetError(f"{where}: missing 'timestep_index'")
            key = (int(frame["timestep_index"]), int(frame.get("camera_index", 0)))
            listed.add(key[0])
            records.setdefault(key, (frame, top, where))
        declared = top.get("timestep_indices")
        if declared is not None and set(int(t) for t in declared) != listed:
            raise DatasetError(
                f"{root / fname}: 'timestep_indices' lists {len(set(declared))} timesteps but its frames "
                f"cover {len(listed)}; the frame counts do not match"
            )
        if name != "all":
            split_timesteps_listed[name] = listed

    timesteps = tuple(sorted({key[0] for key in records}))
    row_of = {t: i for i, t in enumerate(timesteps)}
    npz_of: dict[int, tuple[Path, str]] = {}
    frames_out: list[FrameRecord] = []
    for (timestep, camera), (frame, top, where) in sorted(records.items()):
        frames_out.append(_frame_record(root, frame, top, where, timestep, camera, row_of[timestep]))
        if "flame_param_path" not in frame:
            raise DatasetError(f"{where}: missing 'flame_param_path' (export VHAP with flame_mode='param')")
        npz_of.setdefault(timestep, (root / frame["flame_param_path"], where))

    paths = [npz_of[t][0] for t in timesteps]
    if len(set(paths)) != len(paths):
        raise DatasetError(
            f"{root}: {len(timesteps)} timesteps share {len(set(paths))} flame_param files; "
            "each timestep needs its own npz (the frame counts do not match)"
        )
    per_timestep = [_load_params(npz_of[t][0], npz_of[t][1]) for t in timesteps]
    canonical: dict[str, np.ndarray] | None = None
    if (root / CANONICAL_FILE).is_file():
        canonical = _load_params(root / CANONICAL_FILE, str(root / CANONICAL_FILE))
    params = stack_params(per_timestep, [str(p) for p in paths], canonical)

    extra = {name: _extra_frames(root, fname, row_of) for name, fname in EXTRA_SPLIT_FILES.items()
             if (root / fname).is_file()}
    if info.image_size is None:
        info.image_size = (frames_out[0].width, frames_out[0].height)
    explicit = None
    if split_timesteps_listed:
        explicit = ExplicitSplit(
            train=tuple(sorted(split_timesteps_listed.get("train", set()))),
            val=tuple(sorted(split_timesteps_listed.get("val", set()))),
            test=tuple(sorted(split_timesteps_listed.get("test", set()))),
        )
    return Subject(
        root=root,
        layout="vhap",
        info=info,
        frames=frames_out,
        timesteps=timesteps,
        params=params,
        canonical={k: torch.from_numpy(v) for k, v in (canonical or {}).items()},
        explicit_split=explicit,
        extra_frames=extra,
    )


def _extra_frames(root: Path, fname: str, row_of: dict[int, int]) -> list[FrameRecord]:
    """The frames of an extra split file: views of timesteps the main files hold (their parameters)."""
    top = _read_json(root / fname)
    frames = top.get("frames")
    if not isinstance(frames, list):
        raise DatasetError(f"{root / fname}: has no 'frames' list")
    out, seen = [], set()
    for i, frame in enumerate(frames):
        where = f"{root / fname}, frame {i}"
        if not isinstance(frame, dict) or "timestep_index" not in frame:
            raise DatasetError(f"{where}: missing 'timestep_index'")
        timestep, camera = int(frame["timestep_index"]), int(frame.get("camera_index", 0))
        if timestep not in row_of:
            raise DatasetError(f"{where}: timestep {timestep} is in none of the main transforms files, so it has "
                               "no head parameters")
        if (timestep, camera) in seen:
            raise DatasetError(f"{where}: (timestep {timestep}, camera {camera}) is listed twice")
        seen.add((timestep, camera))
        record = _frame_record(root, frame, top, where, timestep, camera, row_of[timestep])
        view = frame.get("view")
        record.view = str(view["name"]) if isinstance(view, dict) and "name" in view else None
        out.append(record)
    return sorted(out, key=lambda f: (f.timestep, f.camera))


def _read_json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise DatasetError(f"{path}: not readable JSON ({err})") from err
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: expected a JSON object")
    return data


def _existing(root: Path, relative: str, what: str, where: str) -> Path:
    path = root / relative
    if path.is_file():
        return path
    if not path.suffix and path.with_suffix(".png").is_file():
        return path.with_suffix(".png")
    raise DatasetError(f"{where}: {what} not found: {path}")


def _frame_record(root: Path, frame: dict, top: dict, where: str, timestep: int, camera: int, row: int) -> FrameRecord:
    def field(name: str):
        return frame.get(name, top.get(name))

    if "file_path" not in frame:
        raise DatasetError(f"{where}: missing 'file_path'")
    image_path = _existing(root, frame["file_path"], "image", where)
    mask_path = _existing(root, frame["fg_mask_path"], "mask", where) if frame.get("fg_mask_path") else None
    if "transform_matrix" not in frame:
        raise DatasetError(f"{where}: missing 'transform_matrix'")
    c2w = np.asarray(frame["transform_matrix"], dtype=np.float64)
    if c2w.shape not in ((4, 4), (3, 4)) or not np.isfinite(c2w).all():
        raise DatasetError(f"{where}: 'transform_matrix' must be a finite 4x4 (or 3x4) matrix, got shape {c2w.shape}")
    viewmat = opengl_c2w_to_viewmat(torch.from_numpy(c2w)).numpy()

    width, height = field("w"), field("h")
    if width is None or height is None:
        with Image.open(image_path) as image:  # reads the header only
            width, height = image.size
    width, height = int(width), int(height)
    fl_x, fl_y = field("fl_x"), field("fl_y")
    if fl_x is None:
        angle = field("camera_angle_x")
        if angle is None:
            raise DatasetError(f"{where}: no intrinsics (need fl_x/fl_y/cx/cy or camera_angle_x)")
        fl_x = focal_length(float(angle), width)
    fl_y = fl_x if fl_y is None else fl_y
    cx = field("cx") if field("cx") is not None else width / 2.0
    cy = field("cy") if field("cy") is not None else height / 2.0
    K = np.array([[float(fl_x), 0.0, float(cx)], [0.0, float(fl_y), float(cy)], [0.0, 0.0, 1.0]])
    return FrameRecord(
        timestep=timestep, camera=camera, image_path=image_path, mask_path=mask_path, viewmat=viewmat, K=K,
        width=width, height=height, row=row, where=where,
    )


def _load_params(path: Path, where: str) -> dict[str, np.ndarray]:
    if not path.is_file():
        raise DatasetError(f"{where}: parameter file not found: {path}")
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {key: npz[key] for key in npz.files}
    except (OSError, ValueError, EOFError) as err:
        raise DatasetError(f"{path}: not a readable npz of arrays ({err})") from err
    return normalize_frame_params(arrays, str(path))


# --- writing -------------------------------------------------------------------------------------


def frame_param_files(root: str | os.PathLike) -> dict[int, Path]:
    """Each timestep's flame_param file, from the dataset's transforms files (transforms.json and the splits)."""
    root, files = Path(root), {}
    for name in (ALL_FILE, *SPLIT_FILES.values()):
        if (root / name).is_file():
            for frame in _read_json(root / name).get("frames", []):
                files.setdefault(int(frame["timestep_index"]), root / frame["flame_param_path"])
    return files


def rewrite_npz_rows(path: str | os.PathLike, rows: Mapping[str, np.ndarray], optional: Sequence[str] = ()) -> None:
    """Replace keys of one parameter npz: `rows[key]` is a row [W]. Every other key is kept, and so is each key's
    width in the file (the leading entries written, zeros after them: FLAME's 100 expressions stay 100 when 23 are
    given); a key the file lacks is written [1, W], unless it is one of `optional`. The file is replaced atomically."""
    with np.load(path, allow_pickle=False) as npz:
        arrays = {k: npz[k] for k in npz.files}
    for key, row in rows.items():
        if key in optional and key not in arrays:
            continue
        row = np.asarray(row, np.float32).reshape(-1)
        like = arrays.get(key, np.empty((1, row.shape[0]), np.float32))
        out = np.zeros(like.shape, like.dtype)
        n = min(like.shape[-1], row.shape[0])
        out[..., :n] = row[:n]
        arrays[key] = out
    atomic_write_npz(path, **arrays)


def rewrite_frame_params(root: str | os.PathLike, values: Mapping[int, Mapping[str, np.ndarray]],
                         optional: Sequence[str] = ()) -> None:
    """Replace keys of a dataset's flame_param files in place: `values[timestep][key]` is a row [W] (a per-frame key,
    or shape), written by `rewrite_npz_rows`."""
    files = frame_param_files(root)
    for timestep, rows in values.items():
        if timestep not in files:
            raise DatasetError(f"{root}: no flame_param file for timestep {timestep} in its transforms files")
        rewrite_npz_rows(files[timestep], rows, optional)


class LayoutWriter:
    """Write a dataset in the VHAP / GaussianAvatars layout, one frame at a time.

        with LayoutWriter(root, head_model="openhead", image_size=(512, 512), shape=betas) as writer:
            for t in range(num_frames):
                writer.add_frame(t, image, params, viewmat, K, mask=alpha)
        # leaving the block calls finish(); an exception instead removes the partial folder

    Frames go to a hidden temporary folder beside `root`; `finish()` writes the canonical npz, the
    transforms files (split by `split`, see geoavatar.data.splits; a synthetic subject with a novel
    test segment passes SplitConfig(test_frames=N)) and geoavatar.json, then renames
    the folder to `root`. An existing `root` is refused unless `overwrite=True`. Extra files a
    producer wants inside the dataset (ground truth, previews) go under `writer.tmp` before finish().

    Parameters are written padded to the FLAME npz sizes (shape 300, expr 100) so files look like
    VHAP's; models with fewer modes use the leading entries when reading.
    """

    def __init__(
        self,
        root: str | os.PathLike,
        *,
        head_model: str,
        image_size: tuple[int, int],  # (width, height)
        shape: np.ndarray | Tensor,  # [S] identity coefficients, S <= 300
        static_offset: np.ndarray | Tensor | None = None,  # [V, 3] or [1, V, 3]
        background: tuple[float, float, float] = (1.0, 1.0, 1.0),
        mouth: str | None = None,
        source: str | None = None,
        split: SplitConfig | None = None,
        overwrite: bool = False,
        png_compress_level: int = 6,
    ):
        self.root = Path(root)
        if head_model not in HEAD_MODEL_NAMES:
            raise ValueError(f"head_model must be one of {', '.join(HEAD_MODEL_NAMES)}, got {head_model!r}")
        if self.root.exists() and not overwrite:
            raise FileExistsError(f"{self.root} exists; pass overwrite=True to replace it")
        width, height = (int(v) for v in image_size)
        if width <= 0 or height <= 0:
            raise ValueError(f"image_size must be positive, got {image_size}")
        self.info = SubjectInfo(
            head_model=head_model, image_size=(width, height), background=tuple(float(v) for v in background),
            mouth=mouth, source=source, format_version=FORMAT_VERSION,
        )
        self.shape = _pad(_numpy(shape).reshape(-1), FLAME_SHAPE_DIM, "shape")  # [300]
        self.static_offset = None
        if static_offset is not None:
            offset = _numpy(static_offset)
            offset = offset[None] if offset.ndim == 2 else offset
            if offset.ndim != 3 or offset.shape[0] != 1 or offset.shape[2] != 3:
                raise ValueError(f"static_offset must be [V, 3] or [1, V, 3], got {offset.shape}")
            self.static_offset = offset.astype(np.float32)
        self.split = split
        self.overwrite = overwrite
        self.png_compress_level = png_compress_level
        self.root.parent.mkdir(parents=True, exist_ok=True)
        self.tmp = temporary_folder_for(self.root)  # with a normal folder's mode (the umask's)
        for sub in ("images", "fg_masks", "flame_param"):
            (self.tmp / sub).mkdir()
        self.frames: list[dict] = []
        self.extra: dict[str, list[dict]] = {}  # extra split -> its frames (EXTRA_SPLIT_FILES)
        self._written_params: set[int] = set()
        self._keys: set[tuple[int, int]] = set()
        self.done = False

    # context manager: finish on success, clean up on error
    def __enter__(self) -> "LayoutWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None and not self.done:
            self.finish()
        elif exc_type is not None:
            self.abort()

    def add_frame(
        self,
        timestep: int,
        image: np.ndarray | Tensor | os.PathLike,  # [H, W, 3] uint8, or float in [0, 1]; or an RGB PNG file
        params: Mapping[str, np.ndarray | Tensor],  # expr, rotation, neck_pose, jaw_pose, eyes_pose, translation
        viewmat: np.ndarray | Tensor,  # [4, 4] world-to-camera, OpenCV axes
        K: np.ndarray | Tensor,  # [3, 3] pixels
        mask: np.ndarray | Tensor | os.PathLike | None = None,  # [H, W] or [H, W, 1], uint8 or float in [0, 1]; or a
        #                                                         greyscale PNG file
        camera: int = 0,
        split: str | None = None,
        view: Mapping[str, Any] | None = None,
    ) -> None:
        """Write one frame's image, mask and (once per timestep) parameter npz to disk.

        `split` names an extra split (EXTRA_SPLIT_FILES): the frame is listed in that split's transforms
        file only. `view` ({"name": ..., ...}) is stored with the frame (how the camera was placed).
        An image or mask given as a PNG file of the dataset's size is linked (or copied) into the dataset as it is:
        a producer that has its frames as PNGs already (prepare) saves decoding and encoding them again."""
        if split is not None and split not in EXTRA_SPLIT_FILES:
            raise ValueError(f"unknown extra split {split!r}; known: {', '.join(EXTRA_SPLIT_FILES)}")
        if self.done:
            raise RuntimeError("LayoutWriter.add_frame after finish()/abort()")
        timestep, camera = int(timestep), int(camera)
        if timestep < 0 or camera < 0:
            raise ValueError(f"timestep and camera must be >= 0, got {timestep}, {camera}")
        if (timestep, camera) in self._keys:
            raise ValueError(f"frame (timestep {timestep}, camera {camera}) was already written")
        width, height = self.info.image_size
        pixels = _png_file(image, "RGB", (width, height), "image") if _is_path(image) else _to_uint8(image, "image")
        if not _is_path(pixels) and (pixels.ndim != 3 or pixels.shape[2] != 3):
            raise ValueError(f"image must be [H, W, 3], got {pixels.shape}")
        if not _is_path(pixels) and pixels.shape[:2] != (height, width):
            raise ValueError(f"image is {pixels.shape[1]}x{pixels.shape[0]} but the dataset is {width}x{height}")
        viewmat_np = _numpy(viewmat).astype(np.float64)
        K_np = _numpy(K).astype(np.float64)
        if viewmat_np.shape != (4, 4) or K_np.shape != (3, 3):
            raise ValueError(f"viewmat must be [4, 4] and K [3, 3], got {viewmat_np.shape} and {K_np.shape}")

        stem = f"{timestep:05d}_{camera:02d}"
        frame: dict[str, Any] = {"timestep_index": timestep, "camera_index": camera, "file_path": f"images/{stem}.png"}
        if view is not None:
            frame["view"] = dict(view)
        alpha = None
        if mask is not None and _is_path(mask):
            alpha = _png_file(mask, "L", (width, height), "mask")
            frame["fg_mask_path"] = f"fg_masks/{stem}.png"
        elif mask is not None:
            alpha = _to_uint8(mask, "mask")
            alpha = alpha[..., 0] if alpha.ndim == 3 and alpha.shape[2] == 1 else alpha
            if alpha.shape != (height, width):
                raise ValueError(f"mask must be [H, W] or [H, W, 1] matching the image, got {alpha.shape}")
            frame["fg_mask_path"] = f"fg_masks/{stem}.png"
        frame["flame_param_path"] = f"flame_param/{timestep:05d}.npz"
        arrays = self._npz_arrays(params, f"frame {timestep}") if timestep not in self._written_params else None
        with self._disk_full():
            for picture, name in ((pixels, "file_path"), (alpha, "fg_mask_path")):
                if _is_path(picture):
                    _link_or_copy(Path(picture), self.tmp / frame[name])
                elif picture is not None:
                    Image.fromarray(picture).save(self.tmp / frame[name], compress_level=self.png_compress_level)
            if arrays is not None:
                np.savez(self.tmp / frame["flame_param_path"], **arrays)
                self._written_params.add(timestep)

        c2w = viewmat_to_opengl_c2w(torch.from_numpy(viewmat_np)).numpy()
        fl_x, fl_y, cx, cy = K_np[0, 0], K_np[1, 1], K_np[0, 2], K_np[1, 2]
        frame.update({
            "transform_matrix": c2w.tolist(), "fl_x": fl_x, "fl_y": fl_y, "cx": cx, "cy": cy, "w": width, "h": height,
            "camera_angle_x": field_of_view(fl_x, width), "camera_angle_y": field_of_view(fl_y, height),
        })
        (self.frames if split is None else self.extra.setdefault(split, [])).append(frame)
        self._keys.add((timestep, camera))

    def list_frame(self, split: str, timestep: int, camera: int = 0, view: Mapping[str, Any] | None = None) -> None:
        """List a frame already added to the main files in an extra split too (the same image and camera),
        e.g. the dataset's own view of a test timestep as the reference of the novel views."""
        if split not in EXTRA_SPLIT_FILES:
            raise ValueError(f"unknown extra split {split!r}; known: {', '.join(EXTRA_SPLIT_FILES)}")
        match = [f for f in self.frames if (f["timestep_index"], f["camera_index"]) == (int(timestep), int(camera))]
        if not match:
            raise ValueError(f"list_frame: frame (timestep {timestep}, camera {camera}) was not added")
        frame = dict(match[0])
        if view is not None:
            frame["view"] = dict(view)
        self.extra.setdefault(split, []).append(frame)

    def _npz_arrays(self, params: Mapping[str, np.ndarray | Tensor], where: str) -> dict[str, np.ndarray]:
        known = {*POSE_SIZES, "expr", "dynamic_offset", "eyelids"}
        unknown = sorted(set(params) - known - {"shape", "static_offset"})
        if unknown:
            raise ValueError(f"{where}: unknown parameter(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}")
        arrays: dict[str, np.ndarray] = {}
        for key, size in POSE_SIZES.items():
            if key not in params:
                raise ValueError(f"{where}: missing parameter '{key}'")
            value = _numpy(params[key]).astype(np.float32).reshape(1, -1)
            if value.shape != (1, size):
                raise ValueError(f"{where}: '{key}' must have {size} values, got {value.size}")
            arrays[key] = value
        if "expr" not in params:
            raise ValueError(f"{where}: missing parameter 'expr'")
        arrays["expr"] = _pad(_numpy(params["expr"]).reshape(-1), FLAME_EXPR_DIM, "expr")[None]
        arrays["shape"] = self.shape
        if self.static_offset is not None:
            arrays["static_offset"] = self.static_offset
        if "dynamic_offset" in params:
            arrays["dynamic_offset"] = _numpy(params["dynamic_offset"]).astype(np.float32).reshape(1, -1, 3)
        if "eyelids" in params:
            arrays["eyelids"] = _numpy(params["eyelids"]).astype(np.float32).reshape(1, 2)
        return arrays

    def finish(self, split: SplitConfig | None = None) -> Path:
        """Write the canonical npz, transforms files and geoavatar.json; move the folder into place."""
        if self.done:
            raise RuntimeError("LayoutWriter.finish called twice")
        if not self.frames:
            self.abort()
            raise ValueError(f"{self.root}: no frames were added")
        try:
            with self._disk_full():
                self._write_canonical()
                self.frames.sort(key=lambda f: (f["timestep_index"], f["camera_index"]))
                timesteps = sorted({f["timestep_index"] for f in self.frames})
                chosen = split_timesteps(timesteps, split or self.split or SplitConfig(), source=str(self.root))
                for name, frames in self.extra.items():
                    orphans = sorted({f["timestep_index"] for f in frames} - set(timesteps))
                    if orphans:
                        raise ValueError(f"extra split {name!r}: timestep {orphans[0]} has no frame in the main files")
                self._write_transforms(ALL_FILE, self.frames)
                self._write_transforms(SPLIT_FILES["train"], [f for f in self.frames if f["timestep_index"] in set(chosen.train)])
                self._write_transforms(SPLIT_FILES["val"], [f for f in self.frames if f["timestep_index"] in set(chosen.val)])
                self._write_transforms(SPLIT_FILES["test"], [f for f in self.frames if f["timestep_index"] in set(chosen.test)])
                for name, frames in self.extra.items():
                    self._write_transforms(EXTRA_SPLIT_FILES[name], sorted(
                        frames, key=lambda f: (f["timestep_index"], f["camera_index"])))
                # geoavatar.json last: inside the temporary folder it marks the content complete.
                (self.tmp / INFO_FILE).write_text(json.dumps(info_to_json(self.info), indent=2) + "\n")
                self._move_into_place()
        except BaseException:
            self.abort()
            raise
        self.done = True
        return self.root

    @contextlib.contextmanager
    def _disk_full(self) -> Iterator[None]:
        """A full disk while writing: remove the temporary folder (its space is freed), DiskFullError naming root."""
        try:
            with disk_full_as_error(self.root, f"{self.root} is unchanged" if self.root.exists() else "nothing was written"):
                yield
        except DiskFullError:
            self.abort()
            raise

    def abort(self) -> None:
        """Remove the temporary folder; the target is left as it was."""
        self.done = True
        shutil.rmtree(self.tmp, ignore_errors=True)

    def _write_canonical(self) -> None:
        arrays = {key: np.zeros((1, size), np.float32) for key, size in POSE_SIZES.items()}
        arrays["jaw_pose"][0, 0] = CANONICAL_JAW_OPEN
        arrays["expr"] = np.zeros((1, FLAME_EXPR_DIM), np.float32)
        arrays["shape"] = self.shape
        if self.static_offset is not None:
            arrays["static_offset"] = self.static_offset
        np.savez(self.tmp / CANONICAL_FILE, **arrays)

    def _write_transforms(self, name: str, frames: Sequence[dict]) -> None:
        first = self.frames[0]
        shared = {key: first[key] for key in ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y")}
        data = {
            **shared,
            "frames": list(frames),
            "timestep_indices": sorted({f["timestep_index"] for f in frames}),
            "camera_indices": sorted({f["camera_index"] for f in frames}),
        }
        (self.tmp / name).write_text(json.dumps(data, indent=2) + "\n")

    def _move_into_place(self) -> None:
        if self.root.exists() and not self.overwrite:
            raise FileExistsError(f"{self.root} appeared while writing; not replacing it")
        replace_folder(self.tmp, self.root)


def _is_path(value) -> bool:
    return isinstance(value, (str, os.PathLike))


def _png_file(path, mode: str, size: tuple[int, int], name: str) -> Path:
    """`path`, checked from its header to be a PNG of `mode` and `size` (width, height); ValueError otherwise."""
    path = Path(path)
    with Image.open(path) as image:
        kind, have_mode, have_size = image.format, image.mode, image.size
    if kind != "PNG" or have_mode != mode or have_size != tuple(size):
        raise ValueError(f"{name} file {path}: a {have_size[0]}x{have_size[1]} {kind} of mode {have_mode}, but the "
                         f"dataset takes {size[0]}x{size[1]} PNGs of mode {mode}")
    return path


def _link_or_copy(source: Path, target: Path) -> None:
    """A hard link of `source` at `target` (no bytes copied), or a copy where links are not possible."""
    try:
        os.link(source, target)
    except OSError:
        shutil.copyfile(source, target)


def _numpy(value: np.ndarray | Tensor) -> np.ndarray:
    if isinstance(value, Tensor):
        return value.detach().cpu().numpy()
    return np.asarray(value)


def _pad(values: np.ndarray, size: int, name: str) -> np.ndarray:
    values = values.astype(np.float32)
    if values.size > size:
        raise ValueError(f"'{name}' has {values.size} coefficients; the layout holds at most {size}")
    return np.concatenate([values, np.zeros(size - values.size, np.float32)])


def _to_uint8(value: np.ndarray | Tensor, name: str) -> np.ndarray:
    array = _numpy(value)
    if array.dtype == np.uint8:
        return np.ascontiguousarray(array)
    if np.issubdtype(array.dtype, np.floating):
        return np.ascontiguousarray(to_uint8(array))
    if array.dtype == np.bool_:
        return np.ascontiguousarray(array.astype(np.uint8) * 255)
    raise ValueError(f"{name} must be uint8, bool or float in [0, 1], got dtype {array.dtype}")


__all__ = [
    "EXTRA_SPLIT_FILES", "CANONICAL_FILE", "FORMAT_VERSION", "HEAD_MODEL_NAMES", "INFO_FILE", "LayoutWriter", "info_to_json",
    "is_layout", "read_info", "read_layout",
]
