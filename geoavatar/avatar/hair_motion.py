"""Hair that follows the head's turn (issue #27; an addition of ours, in the manner of the pose-dependent
corrections of 3D Gaussian Blendshapes and FlashAvatar, beside the paper's part-wise mouth deformation).

Long hair hangs under gravity: when the head turns, tilts or nods it falls differently over the ears, the
shoulders and the back, which Gaussians rigged to the scalp's triangles cannot do; the avatar then blurs it into
a mean position and the silhouette's band carries most of the error (on d3.mp4, 63-73 % of a training frame's
squared error lies in 8 % of its pixels, the band around the head's outline). With `model.hair_follows_head`
each Gaussian off the face (hair, scalp, ears, neck, eyeballs) moves its local mean and its colour linearly with
the frame's head pose (on by default; the web player applies the same offsets on the GPU, web/pack.py):

    code = head_pose_code(params)                 # [6]: head rotation 3 + neck 3 (axis-angle)
    local mean += M code,  colour += C code        # M, C [3, 6] per Gaussian (means_pose, f_pose in avatar/model.py)

The code is clamped to the box of the training frames' codes (`GaussianAvatar.pose_range`): M and C were fitted
inside it, and a held-out frame or a driver that turns the head further would carry the hair off linearly (d3.mp4:
54 of 71 held-out frames lie outside the box, by up to 2.5 degrees; clamped, held-out PSNR +0.13 dB on two seeds,
LPIPS lower; duda and wojtek within 0.13 dB, LPIPS lower).

The face's skin and the mouth take none: driven by the expression (the leading modes, jaw and eyes) they learned
the training frames' faces (+4.6 dB) and lost 1.7 dB on held-out faces (docs/REJECTED.md). The code holds only
tracked parameters, so a held-out frame or a driver moves the hair by its own head pose, never by a frame index.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from geoavatar.head.params import HeadParams

POSE_CODE_DIM = 6  # head rotation 3 + neck 3 (axis-angle)
FACE_PARTS = ("face", "nose", "eye_region", "lips", "forehead")  # the face's skin (head.regions part names)


def head_pose_code(params: HeadParams) -> Tensor:
    """[6] code of one frame (per-frame keys [1, ...]): head rotation, neck pose."""
    return head_pose_codes(params.rotation, params.neck_pose)[0]


def head_pose_codes(rotation: Tensor, neck_pose: Tensor) -> Tensor:
    """[M, 6] codes of M frames from their head rotations and neck poses (axis-angle, [M, 3] each)."""
    return torch.cat([rotation.reshape(-1, 3), neck_pose.reshape(-1, 3).to(rotation)], 1)


def moving_faces(head) -> Tensor:
    """[F] bool: the faces whose Gaussians follow the head's turn: every face but the face's skin parts and the
    mouth structure (hair, scalp, ears, neck, eyeballs)."""
    from geoavatar.head.regions import MOUTH_PART, face_parts

    parts = face_parts(head.data)
    still = [parts.part_names.index(name) for name in FACE_PARTS] + [MOUTH_PART]
    return torch.from_numpy(~np.isin(parts.part_of_face, still))


__all__ = ["FACE_PARTS", "POSE_CODE_DIM", "head_pose_code", "head_pose_codes", "moving_faces"]
