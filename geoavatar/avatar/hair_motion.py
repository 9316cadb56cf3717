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
    return torch.cat([params.rotation.reshape(-1), params.neck_pose.reshape(-1).to(params.rotation)])


def moving_faces(head) -> Tensor:
    """[F] bool: the faces whose Gaussians follow the head's turn: every face but the face's skin parts and the
    mouth structure (hair, scalp, ears, neck, eyeballs)."""
    from geoavatar.head.regions import MOUTH_PART, face_parts

    parts = face_parts(head.data)
    still = [parts.part_names.index(name) for name in FACE_PARTS] + [MOUTH_PART]
    return torch.from_numpy(~np.isin(parts.part_of_face, still))


__all__ = ["FACE_PARTS", "POSE_CODE_DIM", "head_pose_code", "moving_faces"]
