"""Read the INSTA / metrical-tracker layout (the SplattingAvatar and FlashAvatar benchmark data).

Layout::

    <root>/
      checkpoint/00000.frame   metrical-tracker output, one torch.save dict per frame
      images/00000.png         the frame (INSTA: RGBA, alpha = head matte; tracker output: input/)
      matted/, fg_masks/, masks/, alpha/   optional masks when the images carry no alpha

Fields read from each `.frame` (metrical-tracker `Tracker.save_checkpoint`):
  flame.exp [1,E], flame.shape [1,S], flame.jaw [1,6], flame.eyes [1,12], flame.eyelids [1,2];
  opencv.R [1,3,3], opencv.t [1,3], opencv.K [1,3,3] (PyTorch3D's `opencv_from_cameras_projection`);
  img_size [2] = (height, width); frame_id (e.g. "00000"). tex, sh, camera, global_step are ignored.

Conversions to our convention:
  - Camera: metrical-tracker keeps FLAME fixed at the origin (no global rotation / translation, no
    neck pose) and moves the camera. We keep it that way: head parameters rotation = translation =
    neck_pose = 0 and a per-frame camera, viewmat = [[R, t], [0, 0, 0, 1]] (OpenCV world-to-camera,
    exactly our convention; the layout allows a camera per frame). This is exact: no re-posing.
  - K: PyTorch3D's OpenCV conversion puts the image centre at (w/2, h/2), the same continuous pixel
    coordinates as ours (pixel centres at +0.5), so K is used unchanged.
  - 6D rotations: PyTorch3D convention, the first two ROWS of the rotation matrix
    (`geoavatar.geometry.rotation_6d_to_matrix`), then axis-angle. jaw (6) -> jaw_pose (3);
    eyes (12) = left eye (6) then right eye (6) -> eyes_pose (6), FLAME's joint order.
  - exp -> expr, shape [1,S] -> shape [S]. eyelids are kept as an extra key: metrical-tracker adds
    two eyelid blend shapes of its own that our head models do not have, so eyelid closure is only
    approximately reproduced (through the expression basis).

`.frame` files are pickles: they are loaded with torch.load(weights_only=True) and only numpy's
array reconstruction allowed (never a plain unpickler); anything else raises DatasetError.
The head model is FLAME (metrical-tracker tracks FLAME 2020).
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image

from geoavatar.data.errors import DatasetError
from geoavatar.data.subject import FrameRecord, Subject, SubjectInfo, normalize_frame_params, stack_params
from geoavatar.geometry import matrix_to_axis_angle, rotation_6d_to_matrix

log = logging.getLogger(__name__)

CHECKPOINT_DIR = "checkpoint"
IMAGE_DIRS = ("images", "input", "imgs")
MASK_DIRS = ("fg_masks", "masks", "mask", "alpha", "matted")
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg")


def is_insta(root: Path) -> bool:
    folder = Path(root) / CHECKPOINT_DIR
    return folder.is_dir() and any(folder.glob("*.frame"))


def _safe_numpy_globals() -> list:
    """The numpy callables an array pickle needs, under numpy 1.x and 2.x module names."""
    multiarray = np.core.multiarray
    allowed: list = [multiarray._reconstruct, multiarray.scalar, np.ndarray, np.dtype]
    allowed += [(multiarray._reconstruct, "numpy._core.multiarray._reconstruct"), (multiarray.scalar, "numpy._core.multiarray.scalar")]
    dtypes = getattr(np, "dtypes", None)
    if dtypes is not None:
        allowed += [getattr(dtypes, name) for name in dir(dtypes) if name.endswith("DType")]
    return allowed


def load_frame_file(path: str | os.PathLike) -> dict[str, Any]:
    """A metrical-tracker `.frame` dict, loaded safely (tensors become numpy arrays)."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: .frame file not found")
    try:
        with torch.serialization.safe_globals(_safe_numpy_globals()):
            payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # the safe unpickler reports forbidden globals and corrupt files alike
        first_line = str(err).strip().splitlines()[-1] if str(err).strip() else type(err).__name__
        raise DatasetError(
            f"{path}: not loadable as a metrical-tracker .frame file with the safe loader "
            f"(only numpy arrays and tensors are allowed): {first_line}"
        ) from err
    if not isinstance(payload, dict):
        raise DatasetError(f"{path}: expected a dict, got {type(payload).__name__}")
    return _to_numpy(payload)


def _to_numpy(value: Any) -> Any:
    if isinstance(value, dict):
        return {key: _to_numpy(item) for key, item in value.items()}
    if isinstance(value, torch.Tensor):
        return value.detach().cpu().numpy()
    return value


def convert_frame(payload: dict[str, Any], where: str) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray, tuple[int, int]]:
    """One `.frame` dict -> (parameters in the npz layout, viewmat [4,4], K [3,3], (width, height))."""
    flame, opencv = payload.get("flame"), payload.get("opencv")
    if not isinstance(flame, dict) or not isinstance(opencv, dict):
        raise DatasetError(f"{where}: missing the 'flame' or 'opencv' dict")

    def array(group: dict, group_name: str, key: str, shape: tuple[int, ...] | None = None) -> np.ndarray:
        if key not in group:
            raise DatasetError(f"{where}: missing '{group_name}.{key}'")
        value = np.asarray(group[key])
        if not np.issubdtype(value.dtype, np.number):
            raise DatasetError(f"{where}: '{group_name}.{key}' is not numeric")
        if shape is not None and value.shape != shape:
            raise DatasetError(f"{where}: '{group_name}.{key}' must have shape {shape}, got {value.shape}")
        return value.astype(np.float64)

    jaw = array(flame, "flame", "jaw", (1, 6))
    eyes = array(flame, "flame", "eyes", (1, 12))
    exp = array(flame, "flame", "exp")
    shape = array(flame, "flame", "shape")
    R = array(opencv, "opencv", "R", (1, 3, 3))[0]
    t = array(opencv, "opencv", "t", (1, 3))[0]
    K = array(opencv, "opencv", "K", (1, 3, 3))[0]
    size = np.asarray(payload.get("img_size", ()))
    if size.shape != (2,):
        raise DatasetError(f"{where}: 'img_size' must be (height, width), got {payload.get('img_size')!r}")
    height, width = int(size[0]), int(size[1])

    six_d = torch.from_numpy(np.concatenate([jaw, eyes[:, :6], eyes[:, 6:]], axis=0))  # [3, 6]
    axis_angle = matrix_to_axis_angle(rotation_6d_to_matrix(six_d)).numpy()  # [3, 3]: jaw, left eye, right eye
    params = {
        "translation": np.zeros((1, 3)), "rotation": np.zeros((1, 3)), "neck_pose": np.zeros((1, 3)),
        "jaw_pose": axis_angle[0:1], "eyes_pose": axis_angle[1:3].reshape(1, 6), "expr": exp, "shape": shape,
    }
    if "eyelids" in flame:
        params["eyelids"] = array(flame, "flame", "eyelids", (1, 2))
    params = normalize_frame_params(params, where)
    viewmat = np.eye(4)
    viewmat[:3, :3], viewmat[:3, 3] = R, t
    if not (np.isfinite(viewmat).all() and np.isfinite(K).all()):
        raise DatasetError(f"{where}: the camera contains NaN or infinite values")
    return params, viewmat, K, (width, height)


def read_insta(
    root: str | os.PathLike,
    image_dir: str | None = None,
    mask_dir: str | None = None,
    image_offset: int | None = None,
    strict_frame_count: bool = True,
) -> Subject:
    """Index an INSTA / metrical-tracker folder.

    image_dir / mask_dir: folder names under root (default: the first of IMAGE_DIRS / MASK_DIRS that
    exists; no mask folder and no alpha channel means masks of ones). image_offset: image number =
    frame number + offset (None: 0 when those images exist, else 1, the numbering of videos split by
    ffmpeg, as FlashAvatar's data). strict_frame_count: the image folder must hold exactly one image
    per .frame file.
    """
    root = Path(root)
    checkpoint = root / CHECKPOINT_DIR
    frame_files = sorted(checkpoint.glob("*.frame"), key=_natural_key) if checkpoint.is_dir() else []
    if not frame_files:
        raise DatasetError(f"{root}: no {CHECKPOINT_DIR}/*.frame files (not an INSTA / metrical-tracker folder)")
    images_root = _pick_dir(root, image_dir, IMAGE_DIRS, "image")
    image_count = sum(1 for p in images_root.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS)
    if strict_frame_count and image_count != len(frame_files):
        raise DatasetError(
            f"{root}: {CHECKPOINT_DIR}/ has {len(frame_files)} .frame files but {images_root.name}/ has "
            f"{image_count} images; the frame counts do not match (pass strict_frame_count=False to use "
            "the images that have a .frame)"
        )

    payloads = [(path, load_frame_file(path)) for path in frame_files]
    ids = [_frame_id(payload, path) for path, payload in payloads]
    offset = _resolve_offset(images_root, ids, image_offset)
    image_paths = [_find_image(images_root, _shift(frame_id, offset), str(path)) for (path, _), frame_id in zip(payloads, ids)]
    with Image.open(image_paths[0]) as first:
        has_alpha = first.mode in ("RGBA", "LA", "PA")
    masks_root = None
    if mask_dir is not None or not has_alpha:
        masks_root = _pick_dir(root, mask_dir, MASK_DIRS, "mask", required=mask_dir is not None)
    if masks_root is None and not has_alpha:
        log.warning("%s: the images have no alpha channel and no mask folder was found; masks are all ones", root)

    numeric = all(frame_id.isdigit() for frame_id in ids)
    per_timestep, wheres, frames = [], [], []
    for row, ((path, payload), frame_id, image_path) in enumerate(zip(payloads, ids, image_paths)):
        params, viewmat, K, (width, height) = convert_frame(payload, str(path))
        mask_path = None
        if masks_root is not None:
            mask_path = _find_image(masks_root, image_path.stem, str(path), what="mask")
        timestep = int(frame_id) if numeric else row
        frames.append(FrameRecord(
            timestep=timestep, camera=0, image_path=image_path, mask_path=mask_path, viewmat=viewmat, K=K,
            width=width, height=height, row=row, where=str(path),
        ))
        per_timestep.append(params)
        wheres.append(str(path))
    timesteps = tuple(frame.timestep for frame in frames)
    if len(set(timesteps)) != len(timesteps):
        raise DatasetError(f"{checkpoint}: two .frame files carry the same frame_id")
    order = sorted(range(len(frames)), key=lambda i: timesteps[i])
    frames = [frames[i] for i in order]
    per_timestep = [per_timestep[i] for i in order]
    wheres = [wheres[i] for i in order]
    for row, frame in enumerate(frames):
        frame.row = row
    shapes = np.stack([p["shape"] for p in per_timestep])
    if np.abs(shapes - shapes[0]).max() > 1e-4:
        log.warning("%s: identity (shape) differs between .frame files; using the first frame's", checkpoint)
    params = stack_params(per_timestep, wheres)
    info = SubjectInfo(
        head_model="flame", image_size=(frames[0].width, frames[0].height), background=(0.0, 0.0, 0.0),
        source="insta",
    )
    return Subject(root=root, layout="insta", info=info, frames=frames, timesteps=tuple(f.timestep for f in frames), params=params)


def _natural_key(path: Path) -> tuple:
    return tuple(int(part) if part.isdigit() else part for part in re.split(r"(\d+)", path.stem))


def _frame_id(payload: dict, path: Path) -> str:
    frame_id = payload.get("frame_id", path.stem)
    if isinstance(frame_id, (int, np.integer)):
        return f"{int(frame_id):05d}"
    if not isinstance(frame_id, str) or not frame_id:
        raise DatasetError(f"{path}: 'frame_id' must be a string or an integer, got {frame_id!r}")
    return frame_id


def _shift(frame_id: str, offset: int) -> str:
    if offset == 0:
        return frame_id
    if not frame_id.isdigit():
        raise DatasetError(f"frame_id {frame_id!r} is not a number; image_offset must be 0")
    return f"{int(frame_id) + offset:0{len(frame_id)}d}"


def _resolve_offset(images_root: Path, ids: list[str], image_offset: int | None) -> int:
    if image_offset is not None:
        return image_offset
    stems = {p.stem for p in images_root.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS}
    if all(frame_id in stems for frame_id in ids):
        return 0
    if all(frame_id.isdigit() for frame_id in ids) and all(_shift(frame_id, 1) in stems for frame_id in ids):
        log.info("%s: images are numbered from 1 (frame 00000 -> image 00001)", images_root)
        return 1
    return 0  # _find_image names the first missing image


def _pick_dir(root: Path, chosen: str | None, candidates: tuple[str, ...], what: str, required: bool = True) -> Path | None:
    if chosen is not None:
        folder = root / chosen
        if not folder.is_dir():
            raise DatasetError(f"{root}: {what} folder '{chosen}' not found")
        return folder
    for name in candidates:
        if (root / name).is_dir():
            return root / name
    if required and what == "image":
        raise DatasetError(f"{root}: no image folder (looked for {', '.join(candidates)})")
    return None


def _find_image(folder: Path, stem: str, where: str, what: str = "image") -> Path:
    for ext in IMAGE_EXTENSIONS:
        path = folder / f"{stem}{ext}"
        if path.is_file():
            return path
    raise DatasetError(f"{where}: {what} not found: {folder / stem}.png (or .jpg)")


__all__ = ["convert_frame", "is_insta", "load_frame_file", "read_insta"]
