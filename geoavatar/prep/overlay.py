"""Overlay video: the tracked mesh (shaded, alpha-blended) and the landmarks over the frames.

Green dots are MediaPipe's (filtered) landmarks, red dots the tracked model's projected landmarks;
where they sit on each other the tracking is right. A caption in the top-left corner names the frame and
the fit shown (prepare: "photometric" or "landmark fit"); on a frame where no face was found it says so in
orange (its green dots are then interpolated, not detected). The mesh is rendered at `mesh_size` pixels
and resized to the frame (the CPU z-buffer rasterizer is the cost of this stage).
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterable

import numpy as np
import torch

from geoavatar.imaging import to_uint8
from geoavatar.io.video import write_mp4
from geoavatar.render.camera import scale_intrinsics
from geoavatar.render.mesh import render_mesh

MESH_ALPHA = 0.45
DETECTED = (60, 230, 60)
PROJECTED = (240, 40, 40)
CAPTION = (255, 255, 255)
FLAGGED = (255, 150, 0)  # caption of a frame without a detected face


def overlay_frame(
    image: np.ndarray,  # [S, S, 3] uint8
    vertices: torch.Tensor,  # [V, 3] world
    faces: torch.Tensor,  # [F, 3]
    viewmat: torch.Tensor,  # [4, 4]
    K: torch.Tensor,  # [3, 3] in image pixels
    detected: np.ndarray,  # [L, 2] pixels
    projected: np.ndarray,  # [L, 2] pixels
    mesh_size: int = 256,
    caption: str = "",
    flagged: bool = False,
) -> np.ndarray:
    """One overlay picture [S, S, 3] uint8, with `caption` in the top-left corner (orange when `flagged`)."""
    import cv2

    height, width = image.shape[:2]
    factor = mesh_size / max(width, height)
    mw, mh = max(1, round(width * factor)), max(1, round(height * factor))
    picture = render_mesh(vertices, faces, viewmat, scale_intrinsics(K.to(vertices), factor), mw, mh, ssaa=1,
                          background=(0.0, 0.0, 0.0))
    shaded = picture.image.numpy().astype(np.float32)  # [mh, mw, 3] in [0, 1]
    coverage = picture.mask.numpy().astype(np.float32)
    if (mw, mh) != (width, height):
        shaded = cv2.resize(shaded, (width, height), interpolation=cv2.INTER_LINEAR)
        coverage = cv2.resize(coverage, (width, height), interpolation=cv2.INTER_LINEAR)
    alpha = MESH_ALPHA * coverage[..., None]
    out = to_uint8(image.astype(np.float32) / 255.0 * (1 - alpha) + shaded * alpha)
    radius = max(1, round(width / 256))
    for points, colour in ((detected, DETECTED), (projected, PROJECTED)):
        for x, y in points:
            cv2.circle(out, (int(round(x - 0.5)), int(round(y - 0.5))), radius, colour, -1, lineType=cv2.LINE_AA)
    if caption:
        scale = max(0.3, width / 1024)
        thickness = max(1, round(2 * scale))
        origin = (round(8 * scale) + 2, round(28 * scale) + 4)
        cv2.putText(out, caption, origin, cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), thickness + 2, cv2.LINE_AA)
        cv2.putText(out, caption, origin, cv2.FONT_HERSHEY_SIMPLEX, scale, FLAGGED if flagged else CAPTION, thickness,
                    cv2.LINE_AA)
    return out


def write_video(path: Path, frames: Iterable[np.ndarray], fps: float) -> Path:
    """Encode RGB frames [H, W, 3] uint8 as H.264 mp4 with the one mp4 writer (geoavatar.io.video: atomic,
    odd sizes padded with the edge row / column); a fast preset, as the overlay is a check, not a result."""
    return write_mp4(path, frames, fps, crf=20, preset="veryfast")


def contact_sheet(pictures: list[np.ndarray], labels: list[str] | None = None) -> np.ndarray:
    """Pictures side by side [H, sum W, 3] with an optional label in each corner."""
    import cv2

    sheet = np.concatenate(pictures, axis=1).copy()
    if labels:
        x = 0
        for picture, label in zip(pictures, labels):
            cv2.putText(sheet, label, (x + 8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 2, cv2.LINE_AA)
            x += picture.shape[1]
    return sheet


__all__ = ["overlay_frame", "write_video", "contact_sheet"]
