"""The expression code of a frame: what the avatar's expression blendshapes take (issue #27; an addition of ours,
in the manner of 3D Gaussian Blendshapes and FlashAvatar, beside the paper's part-wise mouth deformation).

    code = expression_code(params, avatar.expression_dims)        # [K] = expr [K - 9], jaw [3], eyes [6]

The head model's expression modes move the mesh, and the Gaussians bound to it follow; what the modes cannot
express stays fixed on the face: the wrinkles of a frown, the folds of a smile, the shadow of a puffed cheek, a
lip pulled further than the mode goes. With blendshapes each Gaussian's colour and local mean move linearly with the
frame's code (GaussianAvatar.forward), so a neutral frame (code 0) shows the neutral face and an expression shows
its own wrinkles. The code holds only tracked parameters, so a held-out frame or a driver gets its blendshapes from
its parameters, as it gets its mesh; the frame index T never enters (the paper's gamma(T) does, for the mouth).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from geoavatar.head.params import HeadParams

POSE_CODE_DIM = 9  # jaw 3 + eyes 6 (axis-angle)
MAX_EXPRESSION_MODES = 50  # FLAME has 100; its leading 50 carry nearly all of a face's motion


def expression_code_dims(num_expr_modes: int) -> int:
    """K for a head model with `num_expr_modes` expression modes: the leading min(modes, 50), jaw and eyes."""
    return min(int(num_expr_modes), MAX_EXPRESSION_MODES) + POSE_CODE_DIM


BLENDSHAPE_PARTS = ("face", "nose", "eye_region", "lips", "forehead")  # the face's skin (head.regions part names)


def expression_face_mask(head) -> Tensor:
    """[F] float: 1 for the faces whose Gaussians carry blendshapes with model.expression_blendshapes = "face" (the
    face's skin parts and the mouth structure), 0 for the hair, scalp, ears, neck and eyeballs: what moves with an
    expression is the face; the hair that swings in some frames would be learned as a function of the code."""
    from geoavatar.head.regions import MOUTH_PART, face_parts

    parts = face_parts(head.data)
    wanted = [parts.part_names.index(name) for name in BLENDSHAPE_PARTS] + [MOUTH_PART]
    return torch.from_numpy(np.isin(parts.part_of_face, wanted).astype(np.float32))


def expression_code(params: HeadParams, dims: int) -> Tensor:
    """[K] code of one frame (per-frame keys [1, ...]): expr's leading K - 9 entries (zero-padded), jaw, eyes."""
    modes = dims - POSE_CODE_DIM
    if modes < 0:
        raise ValueError(f"expression_code: dims must be >= {POSE_CODE_DIM}, got {dims}")
    expr = params.expr.reshape(-1)[:modes]  # [<= K - 9]
    if expr.shape[0] < modes:
        expr = torch.cat([expr, expr.new_zeros(modes - expr.shape[0])])
    return torch.cat([expr, params.jaw_pose.reshape(-1).to(expr), params.eyes_pose.reshape(-1).to(expr)])


__all__ = ["BLENDSHAPE_PARTS", "MAX_EXPRESSION_MODES", "POSE_CODE_DIM", "expression_code", "expression_code_dims",
           "expression_face_mask"]
