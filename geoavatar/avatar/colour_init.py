"""Initial Gaussian colours from the training images (`model.init_colour = "images"`).

GaussianAvatars starts every Gaussian grey. A face the training frames show only at grazing angles gets
few, weak colour gradients and one they never show gets none, so its Gaussians stay grey and novel views
show pale patches there (issue #18). Here each face starts with the colour its pixels show in the
training frames (z-buffered, inside the mask), weighted by cos^2 of the angle between its normal and the
view ray so that head-on views dominate; a face no frame shows takes the colour of the nearest face
that one shows.
"""

from __future__ import annotations

from typing import Iterable

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from geoavatar.render.camera import world_to_camera
from geoavatar.render.mesh import face_normals, rasterize_mesh


def face_colours(
    faces: Tensor,  # [F, 3]
    frames: Iterable[tuple[Tensor, Tensor, Tensor, Tensor, Tensor]],  # (vertices [V, 3], image [H, W, 3],
    # mask [H, W, 1], viewmat [4, 4], K [3, 3]) per training frame
) -> tuple[Tensor, Tensor]:
    """(colour [F, 3] in [0, 1], seen [F] bool): the cos^2-weighted mean colour of each face's pixels over
    the frames; faces no pixel shows take the colour of the nearest seen face (centres in the first frame)."""
    faces = faces.long().cpu()  # the projection below runs on CPU whatever device training uses
    num_faces = faces.shape[0]
    total = torch.zeros(num_faces, 3, dtype=torch.float64)
    weight = torch.zeros(num_faces, dtype=torch.float64)
    centres = None
    for vertices, image, mask, viewmat, K in frames:
        height, width = image.shape[:2]
        cam = world_to_camera(vertices.detach().float().cpu(), viewmat.float().cpu())  # [V, 3]
        if centres is None:
            centres = vertices.detach().float().cpu()[faces].mean(1)  # [F, 3]
        face_id = rasterize_mesh(cam, faces, K.float().cpu(), width, height).face_id.reshape(-1)  # [H*W]
        keep = (face_id >= 0) & (mask.reshape(-1).cpu() > 0.5)
        ids = face_id[keep]  # [P]
        ray = F.normalize(cam[faces].mean(1), dim=-1)  # [F, 3] camera -> face
        cos2 = ((face_normals(cam, faces) * ray).sum(-1) ** 2).double()  # [F] either side
        w = cos2[ids]  # [P]
        total.index_add_(0, ids, image.reshape(-1, 3).cpu().double()[keep] * w[:, None])
        weight.index_add_(0, ids, w)
    if centres is None:
        raise ValueError("face_colours: no frames")
    seen = weight > 1e-12  # [F]
    colour = torch.full((num_faces, 3), 0.5, dtype=torch.float64)
    colour[seen] = total[seen] / weight[seen, None]
    if bool(seen.any()) and not bool(seen.all()):
        from scipy.spatial import cKDTree

        seen_ids = torch.nonzero(seen).squeeze(1)
        _, nearest = cKDTree(centres[seen].numpy()).query(centres[~seen].numpy())
        colour[~seen] = colour[seen_ids[torch.from_numpy(np.asarray(nearest))]]
    return colour.float().clamp(0.0, 1.0), seen


__all__ = ["face_colours"]
