"""Video decoding (PyAV) and the face-centred, temporally smoothed square crop.

    info = probe_video(path)                                   # size, fps, frame count, rotation
    for index, rgb in decode_frames(path, fps=None, max_frames=N): ...   # [H, W, 3] uint8, upright
    boxes = smooth_crop_boxes(centres, sizes, found, frame_size)          # [T, 3] (cx, cy, side)
    crop = crop_square(rgb, box, out_size)                                # [S, S, 3] uint8

Rotation metadata (the display matrix phones write) is honoured: frames come out upright.
Frame subsampling keeps the first frame whose timestamp reaches each tick of the target rate, so
`--fps 12.5` on a 25 fps video keeps every second frame. `index` is the source frame number.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from geoavatar.prep.errors import PrepareError


@dataclass(frozen=True)
class VideoInfo:
    path: str
    width: int  # upright (after rotation)
    height: int
    fps: float
    num_frames: int  # from the container; may be an estimate (0 when unknown)
    rotation: int  # degrees counter-clockwise applied to the decoded frames to make them upright
    codec: str


def _open(path: Path):
    import av

    path = Path(path)
    if not path.is_file():
        raise PrepareError(f"video '{path}': file not found")
    try:
        container = av.open(str(path))
    except Exception as err:  # PyAV raises many kinds (InvalidDataError, ValueError, ...)
        raise PrepareError(f"video '{path}': not a readable video file ({type(err).__name__}: {err})") from err
    if not container.streams.video:
        container.close()
        raise PrepareError(f"video '{path}': the file has no video stream")
    return container


def probe_video(path: str | Path) -> VideoInfo:
    """Size, frame rate, frame count and rotation of the first video stream; PrepareError if unreadable."""
    container = _open(Path(path))
    try:
        stream = container.streams.video[0]
        fps = float(stream.average_rate or stream.guessed_rate or 25.0)
        rotation = 0
        width, height = stream.codec_context.width, stream.codec_context.height
        try:
            first = next(container.decode(stream))
        except (StopIteration, Exception) as err:
            raise PrepareError(f"video '{path}': no frame could be decoded ({type(err).__name__}: {err})") from err
        rotation = _rotation_of(first)
        if rotation % 180:
            width, height = height, width
        return VideoInfo(str(path), int(width), int(height), fps, int(stream.frames or 0), rotation,
                         stream.codec_context.name)
    finally:
        container.close()


def _rotation_of(frame) -> int:
    """Counter-clockwise degrees (multiple of 90) that make the frame upright (display matrix)."""
    angle = float(getattr(frame, "rotation", 0) or 0)
    return int(round(angle / 90.0)) * 90 % 360


def upright(image: np.ndarray, rotation: int) -> np.ndarray:
    """Rotate [H, W, C] by `rotation` degrees counter-clockwise (a multiple of 90)."""
    k = (rotation // 90) % 4
    return np.ascontiguousarray(np.rot90(image, k)) if k else image


def frame_times(path: str | Path) -> np.ndarray:
    """[N] presentation time in seconds of every frame of the first video stream, in the order decode_frames yields
    them (source index order), read from the packets' timestamps without decoding a picture."""
    container = _open(Path(path))
    try:
        stream = container.streams.video[0]
        fps = float(stream.average_rate or stream.guessed_rate or 25.0)
        stamps = [packet.pts for packet in container.demux(stream) if packet.size > 0]
    finally:
        container.close()
    if stamps and all(p is not None for p in stamps):
        return np.sort(np.array(stamps, np.float64)) * float(stream.time_base)
    start = float(stream.start_time * stream.time_base) if stream.start_time is not None else 0.0
    return start + np.arange(len(stamps)) / fps  # no timestamps: the nominal rate


def decode_frames(path: str | Path, fps: float | None = None, max_frames: int | None = None, start: int = 0,
                  stop: int | None = None) -> Iterator[tuple[int, np.ndarray]]:
    """(source frame index, upright RGB [H, W, 3] uint8), optionally subsampled to `fps`, at most max_frames.

    start / stop: only the kept frames number start..stop-1 (counted after the subsampling): the earlier ones
    are decoded, not converted; a worker's share of a video, exactly the frames a whole pass would give it."""
    if fps is not None and fps <= 0:
        raise PrepareError(f"--fps must be positive, got {fps}")
    if max_frames is not None and max_frames <= 0:
        raise PrepareError(f"--max-frames must be positive, got {max_frames}")
    container = _open(Path(path))
    try:
        stream = container.streams.video[0]
        stream.thread_type = "AUTO"
        source_fps = float(stream.average_rate or stream.guessed_rate or 25.0)
        kept, next_tick = 0, 0.0
        try:
            for index, frame in enumerate(container.decode(stream)):
                time = float(frame.time) if frame.time is not None else index / source_fps
                if fps is not None:
                    if time + 0.5 / source_fps < next_tick:
                        continue
                    next_tick = (math.floor(time * fps + 0.5) + 1) / fps
                if kept >= start:
                    yield index, upright(frame.to_ndarray(format="rgb24"), _rotation_of(frame))
                kept += 1
                if (max_frames is not None and kept >= max_frames) or (stop is not None and kept >= stop):
                    return
        except PrepareError:
            raise
        except Exception as err:
            if kept == 0:
                raise PrepareError(f"video '{path}': no frame could be decoded ({type(err).__name__}: {err})") from err
            raise PrepareError(f"video '{path}': decoding failed after {kept} frames ({type(err).__name__}: {err})") from err
        if kept == 0:
            raise PrepareError(f"video '{path}': the video stream holds no frames")
    finally:
        container.close()


# --- the crop --------------------------------------------------------------------------------------


def gaussian_smooth(values: np.ndarray, sigma: float) -> np.ndarray:
    """Zero-phase Gaussian smoothing along axis 0 with edge-replicating borders. values [T, ...]."""
    if sigma <= 0 or len(values) < 2:
        return values.astype(np.float64)
    radius = int(math.ceil(3 * sigma))
    kernel = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
    kernel /= kernel.sum()
    padded = np.concatenate([np.repeat(values[:1], radius, 0), values, np.repeat(values[-1:], radius, 0)], 0)
    out = np.zeros_like(values, dtype=np.float64)
    for i, w in enumerate(kernel):
        out += w * padded[i:i + len(values)]
    return out


def fill_missing(values: np.ndarray, found: np.ndarray) -> np.ndarray:
    """Linear interpolation along axis 0 over the rows where found is False (ends hold the nearest). [T, ...]."""
    values = values.astype(np.float64).copy()
    good = np.flatnonzero(found)
    if len(good) == 0:
        raise ValueError("fill_missing: no valid row")
    flat = values.reshape(len(values), -1)
    t = np.arange(len(values))
    for col in range(flat.shape[1]):
        flat[:, col] = np.interp(t, good, flat[good, col])
    return flat.reshape(values.shape)


def smooth_crop_boxes(
    centres: np.ndarray,  # [T, 2] face centre in pixels (any value where not found)
    sizes: np.ndarray,  # [T] face size in pixels (forehead-to-chin)
    found: np.ndarray,  # [T] bool
    frame_size: tuple[int, int],  # (width, height)
    scale: float = 2.4,
    sigma_frames: float = 12.0,
) -> np.ndarray:
    """Square crop boxes [T, 3] (centre x, centre y, side), one side for the whole video.

    The side is `scale` x the 90th percentile of the face size, at most the shorter frame side, so
    the focal length in crop pixels stays the same in every frame. The centre follows the face,
    smoothed with a zero-phase Gaussian (sigma in frames) so the crop does not jitter, and is
    shifted to keep the box inside the frame (no padding).
    """
    width, height = frame_size
    side = float(min(scale * np.percentile(sizes[found], 90), width, height))
    side = max(8.0, side)
    centre = gaussian_smooth(fill_missing(centres, found), sigma_frames)  # [T, 2]
    centre[:, 0] = np.clip(centre[:, 0], side / 2, width - side / 2)
    centre[:, 1] = np.clip(centre[:, 1], side / 2, height - side / 2)
    return np.concatenate([centre, np.full((len(centre), 1), side)], 1)


def crop_square(image: np.ndarray, box: np.ndarray, out_size: int) -> np.ndarray:
    """Crop the square box (cx, cy, side) of image [H, W, 3] and resize it to out_size² (area/cubic)."""
    import cv2

    cx, cy, side = (float(v) for v in box)
    scale = out_size / side
    # Affine map from source pixels to output pixels (centres at +0.5 on both sides).
    matrix = np.array([[scale, 0.0, out_size / 2 - scale * cx], [0.0, scale, out_size / 2 - scale * cy]])
    matrix[:, 2] += 0.5 * scale - 0.5  # OpenCV's pixel centres sit at integers
    interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_CUBIC
    if scale < 1:
        # warpAffine has no real area filter: downsample first, then place exactly.
        x0, y0 = int(math.floor(cx - side / 2)), int(math.floor(cy - side / 2))
        x1, y1 = int(math.ceil(cx + side / 2)), int(math.ceil(cy + side / 2))
        x0c, y0c = max(0, x0), max(0, y0)
        patch = image[y0c:min(y1, image.shape[0]), x0c:min(x1, image.shape[1])]
        pw, ph = max(1, round(patch.shape[1] * scale)), max(1, round(patch.shape[0] * scale))
        small = cv2.resize(patch, (pw, ph), interpolation=interp)
        sx, sy = pw / patch.shape[1], ph / patch.shape[0]
        matrix = np.array([[1.0, 0.0, out_size / 2 - sx * (cx - x0c)], [0.0, 1.0, out_size / 2 - sy * (cy - y0c)]])
        return cv2.warpAffine(small, matrix, (out_size, out_size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return cv2.warpAffine(image, matrix, (out_size, out_size), flags=interp, borderMode=cv2.BORDER_REPLICATE)


def crop_intrinsics(box: np.ndarray, out_size: int) -> tuple[float, float, float]:
    """(scale, offset x, offset y): a source pixel coordinate p maps to scale * (p - offset) in the crop."""
    cx, cy, side = (float(v) for v in box)
    return out_size / side, cx - side / 2, cy - side / 2


__all__ = ["VideoInfo", "probe_video", "decode_frames", "upright", "gaussian_smooth", "fill_missing",
           "smooth_crop_boxes", "crop_square", "crop_intrinsics"]
