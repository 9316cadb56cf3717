"""A floater measure that needs no ground truth: how much of a render lies outside the head.

    share = sum(alpha outside S) / sum(alpha)

S is the silhouette of the posed head mesh (with the mouth structure) z-buffered by the mesh rasterizer
(render/mesh.py) from the same camera and dilated by `dilate` of the longer image side. Gaussians bound
to the mesh stay within a few pixels of their faces, so a clean avatar scores ~0; splats that drifted
off the surface (floaters, blobs grown behind or beside the head, Gaussians that carve the mask by
learning the background colour only count where they are opaque) push it up. Hair, a beard or glasses
that the head model lacks lie partly outside S too: `outside_share` of the ground-truth mask from the
same camera (eval does this where there is one) is the share the true head has, the floor to compare
with. Seen from the front most floaters hide behind the head, so the measure is taken at side views
(`side_view_shares`: the camera turned about the head centre, as `geoavatar orbit` turns it).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from geoavatar.avatar import pose_avatar, rasterize_gaussians
from geoavatar.head.params import HeadParams
from geoavatar.head.regions import skull_centre
from geoavatar.render.camera import Camera, orbit_cameras, world_to_camera
from geoavatar.render.mesh import dilate_mask, dilation_pixels, rasterize_mesh

# (name, yaw, pitch) in degrees: the side views of `side_view_shares` (+ yaw toward the camera's right).
SIDE_VIEWS: tuple[tuple[str, float, float], ...] = (
    ("yaw+30", 30.0, 0.0), ("yaw-30", -30.0, 0.0), ("yaw+60", 60.0, 0.0), ("yaw-60", -60.0, 0.0),
    ("yaw+90", 90.0, 0.0), ("yaw-90", -90.0, 0.0), ("pitch+20", 0.0, 20.0), ("pitch-20", 0.0, -20.0),
)
DEFAULT_DILATE = 0.03  # of the longer image side: a few pixels of splat spread at 128-512 px


@dataclass
class FloaterConfig:
    dilate: float = DEFAULT_DILATE
    """Dilation of the head silhouette, as a fraction of the longer image side (at least 1 px when > 0)."""
    views: tuple[tuple[str, float, float], ...] = SIDE_VIEWS

    def dilate_px(self, width: int, height: int) -> int:
        return dilation_pixels(self.dilate, width, height)


def head_silhouette(vertices: Tensor, faces: Tensor, camera: Camera, dilate_px: int = 0) -> Tensor:
    """[H, W] bool: pixels covered by the mesh (vertices [V, 3] world, faces [F, 3]), dilated."""
    frags = rasterize_mesh(world_to_camera(vertices, camera.viewmat.to(vertices)), faces.to(vertices.device),
                           camera.K.to(vertices), camera.width, camera.height)
    return dilate_mask(frags.face_id >= 0, dilate_px)


def outside_share(alpha: Tensor, silhouette: Tensor) -> float:
    """Share of the opacity `alpha` ([H, W] or [H, W, 1] in [0, 1]) outside `silhouette` [H, W]; 0 when empty."""
    alpha = alpha.reshape(silhouette.shape).float()
    total = float(alpha.sum())
    if total <= 0.0:
        return 0.0
    return float((alpha * (~silhouette.to(alpha.device)).float()).sum()) / total


@torch.no_grad()
def side_view_shares(run, params: HeadParams, timestep: int | None, camera: Camera,
                     config: FloaterConfig | None = None, backend: str = "auto") -> dict[str, float]:
    """outside_share of the run's avatar posed by `params` (T `timestep`) at each side view: `camera`
    turned about the head centre (head.regions.skull_centre) by the view's yaw and pitch, aimed at it with the
    principal point at the image centre (render.camera.centred_intrinsics), as `geoavatar orbit` aims."""
    config = config or FloaterConfig()
    posed = pose_avatar(run.avatar, run.head, params, timestep, run.deformer)
    vertices = posed.vertices  # [V, 3]
    centre = skull_centre(vertices, run.head)  # [3]
    dilate = config.dilate_px(camera.width, camera.height)
    views = orbit_cameras(camera, centre, [(yaw, pitch) for _, yaw, pitch in config.views])
    shares = {}
    for (name, _, _), view in zip(config.views, views):
        alpha = rasterize_gaussians(posed.gaussians, view, None, backend).alpha  # [H, W, 1]
        shares[name] = outside_share(alpha, head_silhouette(vertices, run.head.faces, view, dilate))
    return shares


__all__ = ["DEFAULT_DILATE", "FloaterConfig", "SIDE_VIEWS", "dilate_mask", "head_silhouette", "outside_share",
           "side_view_shares"]
