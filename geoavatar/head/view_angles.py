"""Where a camera looks at the face from, in the head's own axes, and whether training ever saw the face so.

A novel view named "yaw+30" is 30 degrees from the dataset camera, not from the face: when the head itself is
turned by -15 degrees the camera sees the face from 45 degrees. What decides how hard a view is is the angle
relative to the face, and whether any training frame saw the face from near there. Both come from geometry
alone, for any head model and dataset:

    rest = rest_skull(head, params)                             # [S, 3] the head's skin (no neck, no mouth), unposed
    directions = view_directions(rest, posed, viewmat)          # [B, 3] head centre -> camera, head axes
    yaw, pitch = yaw_pitch(directions)                          # degrees; 0, 0: the camera faces the face
    seen = within_trained_views(directions, trained, 5.0)       # [B] bool; trained: the training frames' directions

The head's orientation in a frame is the rotation that best maps its rest skin onto the posed skin (least
squares, Kabsch), so neck, global rotation and any head model's joints count alike. Head axes: +x the head's
left, +y up, +z out of the face; yaw > 0: the camera sees the head's left side (+x), pitch > 0: from above.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from geoavatar.head.params import HeadParams
from geoavatar.head.regions import skull_vertex_ids


def rest_skull(head, params: HeadParams) -> Tensor:
    """[S, 3] the skull vertices of `params`' identity (first frame's shape) with no pose and no expression."""
    rest = params.rows(slice(0, 1)).map(torch.zeros_like)  # no pose, no expression
    rest = rest.replace(shape=params.shape, static_offset=params.static_offset)
    with torch.no_grad():
        vertices = head.forward_params(rest).vertices[0]
    return vertices[skull_vertex_ids(head).to(vertices.device)]


def face_rotation(rest: Tensor, posed: Tensor) -> Tensor:
    """[B, 3, 3] the rotation R with posed - mean ~ R (rest - mean), least squares; rest [S, 3], posed [B, S, 3]."""
    a = (rest - rest.mean(0)).double()  # [S, 3]
    b = (posed - posed.mean(1, keepdim=True)).double()  # [B, S, 3]
    u, _, vt = torch.linalg.svd(b.transpose(1, 2) @ a)  # [B, 3, 3]: H = sum b a^T
    d = torch.ones(posed.shape[0], 3, dtype=torch.float64, device=posed.device)
    d[:, 2] = torch.sign(torch.det(u @ vt))  # a proper rotation, never a reflection
    return u @ torch.diag_embed(d) @ vt


def view_directions(rest: Tensor, posed: Tensor, viewmat: Tensor) -> Tensor:
    """[B, 3] unit vectors from the posed head's centre to the camera, in the head's own axes.
    rest [S, 3], posed [B, S, 3] (the same vertices), viewmat [B, 4, 4] world-to-camera."""
    rotation = face_rotation(rest, posed)  # [B, 3, 3] head -> world
    view = viewmat.double()
    camera = -(view[:, :3, :3].transpose(1, 2) @ view[:, :3, 3:]).squeeze(-1)  # [B, 3] camera centres
    towards = camera - posed.double().mean(1)  # [B, 3] world
    local = (rotation.transpose(1, 2) @ towards[..., None]).squeeze(-1)  # [B, 3] head axes
    return local / local.norm(dim=-1, keepdim=True)


def yaw_pitch(directions: Tensor) -> tuple[Tensor, Tensor]:
    """Degrees [B], [B] of unit view directions [B, 3] in head axes (see the module docstring)."""
    x, y, z = directions.unbind(-1)
    return torch.rad2deg(torch.atan2(x, z)), torch.rad2deg(torch.atan2(y, torch.hypot(x, z)))


def within_trained_views(directions: Tensor, trained: Tensor, tolerance_deg: float) -> Tensor:
    """[B] bool: some trained direction [N, 3] lies within `tolerance_deg` of each direction [B, 3]."""
    if trained.numel() == 0:
        return torch.zeros(directions.shape[0], dtype=torch.bool)
    cosine = (directions.double() @ trained.double().T).max(dim=1).values  # [B]
    return cosine >= math.cos(math.radians(tolerance_deg))


__all__ = ["face_rotation", "rest_skull", "view_directions", "within_trained_views", "yaw_pitch"]
