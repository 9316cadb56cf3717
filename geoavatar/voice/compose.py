"""A speaking face's full head parameters: the voice model's mouth and the person's idle motion together.

    params = speaking_params(face, idle_frames, identity)    # npz layout, per-frame keys [N, ...]

    expr        the voice model's expression + the idle motion's upper-face change (blinks, brows; lips untouched)
    jaw_pose    the voice model's
    rotation, neck_pose, translation, eyes_pose    the idle motion's (the person's own head motion and gaze)
    shape, static_offset                           the avatar's identity
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from geoavatar.voice.model import SpokenFace


def speaking_params(face: SpokenFace, idle: dict[str, np.ndarray], identity: dict[str, Tensor],
                    device: torch.device | str = "cpu") -> dict[str, Tensor]:
    """Per-frame keys [N, ...] and the identity's keys; `idle` from IdlePlayer.take(N) (its frames in order)."""
    count = len(face.expr)
    if len(idle["rotation"]) != count:
        raise ValueError(f"speaking_params: {count} faces but {len(idle['rotation'])} idle frames")
    expr = np.array(face.expr, np.float32, copy=True)
    upper = idle["upper_expr"]
    expr[:, :upper.shape[1]] += upper
    tensor = lambda a: torch.as_tensor(np.asarray(a, np.float32), device=device)  # noqa: E731
    out = {"expr": tensor(expr), "jaw_pose": tensor(face.jaw)}
    out.update({key: tensor(idle[key]) for key in ("rotation", "neck_pose", "translation", "eyes_pose")})
    out.update({key: value.to(device) for key, value in identity.items()})
    return out


__all__ = ["speaking_params"]
