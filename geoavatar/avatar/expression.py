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

from typing import Literal

import numpy as np
import torch
from torch import Tensor

from geoavatar.head.params import HeadParams

POSE_CODE_DIM = 9  # jaw 3 + eyes 6 (axis-angle): what moves with an expression besides the modes
HEAD_CODE_DIM = 6  # head rotation 3 + neck 3 (axis-angle): how the head hangs in the world (hair under gravity)
MAX_EXPRESSION_MODES = 50  # FLAME has 100; its leading 50 carry nearly all of a face's motion
BLENDSHAPE_PARTS = ("face", "nose", "eye_region", "lips", "forehead")  # the face's skin (head.regions part names)
BlendshapeMode = Literal["off", "face", "all", "split", "hair"]


def expression_code_dims(num_expr_modes: int) -> int:
    """K for a head model with `num_expr_modes` expression modes: the leading min(modes, 50), jaw, eyes, head, neck."""
    return min(int(num_expr_modes), MAX_EXPRESSION_MODES) + POSE_CODE_DIM + HEAD_CODE_DIM


def code_masks(mode: BlendshapeMode, dims: int) -> Tensor:
    """[2, K] which entries of the code drive the Gaussians of the face's skin (row 0) and all the others (row 1).

    face:  the face's skin follows the expression (modes, jaw, eyes); the hair, scalp, ears and neck follow nothing;
    all:   every Gaussian follows the expression;
    split: the face's skin follows the expression, the rest the head's rotation and neck (long hair hangs and swings
           with how the head is turned, not with what the face does);
    hair:  only the rest, by the head's rotation and neck; the face's skin follows nothing."""
    expression = torch.zeros(dims)
    expression[: dims - HEAD_CODE_DIM] = 1.0
    head = 1.0 - expression
    rest = {"face": torch.zeros(dims), "all": expression, "split": head, "hair": head}[mode]
    return torch.stack([torch.zeros(dims) if mode == "hair" else expression, rest])


def expression_groups(head) -> Tensor:
    """[F] long: 0 for the faces of the face's skin parts and the mouth structure, 1 for the rest (hair, scalp,
    ears, neck, eyeballs)."""
    from geoavatar.head.regions import MOUTH_PART, face_parts

    parts = face_parts(head.data)
    wanted = [parts.part_names.index(name) for name in BLENDSHAPE_PARTS] + [MOUTH_PART]
    return torch.from_numpy((~np.isin(parts.part_of_face, wanted)).astype(np.int64))


def expression_code(params: HeadParams, dims: int) -> Tensor:
    """[K] code of one frame (per-frame keys [1, ...]): expr's leading K - 15 entries (zero-padded), jaw, eyes,
    head rotation, neck."""
    modes = dims - POSE_CODE_DIM - HEAD_CODE_DIM
    if modes < 0:
        raise ValueError(f"expression_code: dims must be >= {POSE_CODE_DIM + HEAD_CODE_DIM}, got {dims}")
    expr = params.expr.reshape(-1)[:modes]  # [<= K - 15]
    if expr.shape[0] < modes:
        expr = torch.cat([expr, expr.new_zeros(modes - expr.shape[0])])
    rest = [params.jaw_pose, params.eyes_pose, params.rotation, params.neck_pose]
    return torch.cat([expr, *(value.reshape(-1).to(expr) for value in rest)])


__all__ = ["BLENDSHAPE_PARTS", "BlendshapeMode", "HEAD_CODE_DIM", "MAX_EXPRESSION_MODES", "POSE_CODE_DIM",
           "code_masks", "expression_code", "expression_code_dims", "expression_groups"]
