"""Losses on where an avatar's rendered weight lies relative to the posed head mesh (TrainConfig.mesh_prior, issue #18).

    behind   = mean over pixels of sum_i w_i [z_i > depth_mesh(pixel of i) + margin]     (w_i: compositing weight)
    outside  = mean over pixels of alpha * [pixel outside the mesh silhouette dilated by d]

`behind` is rendered by a second pass of the same Gaussians with a 0/1 flag as their colour, so its gradient reaches
every Gaussian on the ray: the flagged ones (less opaque, smaller, aside) *and* the ones in front of them (more opaque
lowers the transmittance that reaches the hidden layers). The flags and the mesh z-buffer (render/mesh.py) carry no
gradient. A centre is tested against the mesh depth at the pixel it projects to (off the mesh or the image: never
behind), as benchmarks/novel_view_depth.py measures the behind-share. Both terms are taken at the training camera
(`behind` only: the mask already asks for transparency outside the head there) and at a camera turned about the head
(turned_camera), which no frame of the video shows.
"""

from __future__ import annotations

import torch
from torch import Tensor

from geoavatar.avatar.binding import GlobalGaussians
from geoavatar.avatar.render import rasterize_gaussians
from geoavatar.config import MeshPriorConfig
from geoavatar.head.regions import skull_centre
from geoavatar.render.camera import Camera, orbit_cameras, world_to_camera
from geoavatar.render.mesh import dilate_mask, rasterize_mesh


def behind_surface(
    points_cam: Tensor,  # [N, 3] camera coordinates (OpenCV axes)
    surface_depth: Tensor,  # [H, W] camera z of the visible surface, +inf where none (Fragments.depth)
    K: Tensor,  # [3, 3]
    margin: float,  # same unit as the depths
) -> Tensor:
    """[N] bool: the point lies more than `margin` behind the surface at the pixel it projects to. Points off the
    image, behind the camera or over pixels the surface does not cover are never behind."""
    height, width = surface_depth.shape
    z = points_cam[:, 2]  # [N]
    uv = (points_cam @ K.to(points_cam).T)[:, :2] / z.clamp_min(1e-6)[:, None]  # [N, 2] pixels
    px, py = uv[:, 0].floor().long(), uv[:, 1].floor().long()  # [N]
    inside = (z > 0) & (px >= 0) & (px < width) & (py >= 0) & (py < height)
    surface = surface_depth[py.clamp(0, height - 1), px.clamp(0, width - 1)]  # [N]
    return inside & (z > surface + margin)


def camera_prior_terms(
    gaussians: GlobalGaussians,  # the posed avatar (differentiable)
    vertices: Tensor,  # [V, 3] the posed head in world space
    faces: Tensor,  # [F, 3]
    camera: Camera,
    margin: float,
    dilate_px: int | None = None,  # None: no `outside` term
    backend: str = "auto",
) -> dict[str, Tensor]:
    """{"behind": [], "outside": []} (unweighted image means) of the avatar seen by `camera`."""
    viewmat, K = camera.viewmat.to(vertices), camera.K.to(vertices)
    frags = rasterize_mesh(world_to_camera(vertices, viewmat), faces.to(vertices.device), K, camera.width,
                           camera.height)  # no gradient
    with torch.no_grad():
        behind = behind_surface(world_to_camera(gaussians.means, viewmat), frags.depth, K, margin)  # [N]
        flags = torch.zeros_like(gaussians.colors)  # [N, 3]: the flag in the first channel, black elsewhere
        flags[:, 0] = behind.to(flags.dtype)
    result = rasterize_gaussians(gaussians._replace(colors=flags), camera, None, backend, check_values=False)
    terms = {"behind": result.rgb[..., 0].mean()}
    if dilate_px is not None:
        outside = ~dilate_mask(frags.mask, dilate_px)  # [H, W]
        terms["outside"] = (result.alpha[..., 0] * outside.to(result.alpha.dtype)).mean()
    return terms


def turned_angles(max_yaw: float, max_pitch: float, seed: int, step: int) -> tuple[float, float]:
    """(yaw, pitch) in degrees of `step`'s turned camera: uniform in [-max_yaw, max_yaw] x [-max_pitch, max_pitch], a
    pure function of (seed, step) so that a resumed run draws the same ones."""
    generator = torch.Generator().manual_seed(seed * 1_000_003 + 7_919 * step + 2)
    u = torch.rand(2, generator=generator, dtype=torch.float64).tolist()
    return (2.0 * u[0] - 1.0) * max_yaw, (2.0 * u[1] - 1.0) * max_pitch


def turned_camera(camera: Camera, vertices: Tensor, head, yaw: float, pitch: float) -> Camera:
    """`camera` turned about the posed head's centre by yaw / pitch (degrees), aimed at it with the principal point
    mid-image: as `geoavatar orbit` and eval's side views turn it."""
    return orbit_cameras(camera, skull_centre(vertices.detach(), head), [(yaw, pitch)])[0]


def mesh_prior_losses(
    gaussians: GlobalGaussians,
    vertices: Tensor,  # [V, 3] posed head (the trainer's frame.vertices)
    head,  # HeadModel: faces, and the skull centre of the turned camera
    camera: Camera,  # the training camera
    config: MeshPriorConfig,
    seed: int,
    step: int,
    backend: str = "auto",
) -> dict[str, Tensor]:
    """The weighted terms the configuration enables at this step: "behind" (training camera), "turned_behind",
    "turned_outside"; {} when none is on."""
    out: dict[str, Tensor] = {}
    if config.at_training_camera:
        out["behind"] = config.lambda_behind * camera_prior_terms(
            gaussians, vertices, head.faces, camera, config.margin, None, backend)["behind"]
    if config.at_turned_camera(step):
        yaw, pitch = turned_angles(config.turned_yaw, config.turned_pitch, seed, step)
        view = turned_camera(camera, vertices, head, yaw, pitch)
        dilate = max(1, int(round(config.outside_dilate * max(camera.width, camera.height))))
        terms = camera_prior_terms(gaussians, vertices, head.faces, view, config.margin, dilate, backend)
        if config.lambda_turned_behind > 0:
            out["turned_behind"] = config.lambda_turned_behind * terms["behind"]
        if config.lambda_turned_outside > 0:
            out["turned_outside"] = config.lambda_turned_outside * terms["outside"]
    return out


__all__ = ["behind_surface", "camera_prior_terms", "mesh_prior_losses", "turned_angles", "turned_camera"]
