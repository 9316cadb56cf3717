"""TrainConfig.warped_view (train/warped_view.py): the training frame warped through the mesh to a turned camera.

A textured square 1 m in front of a 64 px camera stands in for the head: its image is a smooth colour ramp over the
square, so the colour a turned camera should see at each pixel is known in closed form (the square point it sees,
projected into the training camera). A second square hides part of the first to test the depth test.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import replace

import pytest
import torch

from geoavatar.config import WarpedViewConfig
from geoavatar.render.camera import Camera, orbit_viewmat, world_to_camera
from geoavatar.render.mesh import rasterize_mesh
from geoavatar.train.warped_view import warp_to_camera, warped_view_loss

SIZE = 64
HALF = 0.3


def camera(viewmat: torch.Tensor | None = None) -> Camera:
    K = torch.tensor([[64.0, 0.0, SIZE / 2], [0.0, 64.0, SIZE / 2], [0.0, 0.0, 1.0]])
    return Camera(torch.eye(4) if viewmat is None else viewmat, K, SIZE, SIZE)


def square(z: float = 1.0, half: float = HALF) -> tuple[torch.Tensor, torch.Tensor]:
    """Two triangles facing the camera at the origin (normal -z, toward it)."""
    vertices = torch.tensor([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]])
    return vertices, torch.tensor([[0, 2, 1], [0, 3, 2]])


def normals_toward_camera(faces: torch.Tensor) -> torch.Tensor:
    return torch.tensor([[0.0, 0.0, -1.0]]).expand(faces.shape[0], 3)


def ramp_image(source: Camera, vertices: torch.Tensor, faces: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """[H, W, 3] colours that are affine in the square's x and y (so bilinear sampling is exact), [H, W] mask."""
    frags = rasterize_mesh(world_to_camera(vertices, source.viewmat), faces, source.K, SIZE, SIZE)
    points = (frags.bary[..., None] * vertices[faces[frags.face_id.clamp_min(0)]]).sum(-2)  # [H, W, 3]
    image = torch.stack([0.5 + points[..., 0], 0.5 + points[..., 1], torch.full_like(points[..., 0], 0.3)], -1)
    return image * frags.mask[..., None], frags.mask.float()


def expected_colour(points: torch.Tensor) -> torch.Tensor:
    return torch.stack([0.5 + points[..., 0], 0.5 + points[..., 1], torch.full_like(points[..., 0], 0.3)], -1)


def turned(yaw: float) -> Camera:
    return camera(orbit_viewmat(torch.eye(4), torch.tensor([0.0, 0.0, 1.0]), yaw, 0.0))


def test_the_warp_gives_the_colour_of_the_surface_point_each_turned_pixel_sees():
    vertices, faces = square()
    source = camera()
    image, mask = ramp_image(source, vertices, faces)
    target = turned(25.0)
    usable = torch.ones(faces.shape[0], dtype=torch.bool)
    warped = warp_to_camera(image, mask, vertices, faces, normals_toward_camera(faces), usable, source, target,
                            0.005, 70.0)
    frags = rasterize_mesh(world_to_camera(vertices, target.viewmat), faces, target.K, SIZE, SIZE)
    points = (frags.bary[..., None] * vertices[faces[frags.face_id.clamp_min(0)]]).sum(-2)
    assert int(warped.valid.sum()) > 0.8 * int(frags.mask.sum())  # all but the square's border pixels
    assert not bool((warped.valid & ~frags.mask).any())
    error = (warped.colour - expected_colour(points)).abs()[warped.valid]
    assert float(error.max()) < 1e-3
    # a render that shows exactly that has no loss; one that is off by 0.1 everywhere has 0.1
    perfect = torch.where(warped.valid[..., None], expected_colour(points), torch.zeros(3))
    assert float(warped_view_loss(perfect, warped)) < 1e-3
    assert abs(float(warped_view_loss(perfect + 0.1, warped)) - 0.1) < 1e-3


def test_points_hidden_from_the_training_camera_grazing_faces_and_other_parts_are_not_valid():
    far, far_faces = square(1.2)
    near, near_faces = square(1.0, 0.1)  # hides the far square's middle from the training camera
    vertices = torch.cat([far, near])
    faces = torch.cat([far_faces, near_faces + 4])
    source = camera()
    image, mask = ramp_image(source, vertices, faces)
    usable = torch.tensor([True, True, False, False])  # only the far square's faces are "skin"
    target = turned(40.0)
    warped = warp_to_camera(image, mask, vertices, faces, normals_toward_camera(faces), usable, source, target,
                            0.005, 70.0)
    frags = rasterize_mesh(world_to_camera(vertices, target.viewmat), faces, target.K, SIZE, SIZE)
    on_far = frags.mask & (frags.face_id < 2)
    points = (frags.bary[..., None] * vertices[faces[frags.face_id.clamp_min(0)]]).sum(-2)
    hidden = on_far & (points[..., 0].abs() < 0.08) & (points[..., 1].abs() < 0.08)  # behind the near square
    assert int(hidden.sum()) > 4 and not bool((warped.valid & hidden).any())
    assert not bool((warped.valid & frags.mask & (frags.face_id >= 2)).any())  # not a usable part
    assert int((warped.valid & on_far).sum()) > 100
    # normals turned 30 degrees away: every point is seen at least 16 degrees off its normal, so a 10 degree limit
    # leaves nothing valid
    tilted = torch.tensor([[math.sin(math.radians(30)), 0.0, -math.cos(math.radians(30))]]).expand(4, 3)
    strict = warp_to_camera(image, mask, vertices, faces, tilted, usable, source, target, 0.005, 10.0)
    assert int(strict.valid.sum()) == 0


def test_trainer_logs_the_warped_view_term_and_the_config_checks_its_options(tmp_path):
    from geoavatar.config import preset
    from geoavatar.data.splits import ShortVideoWarning
    from geoavatar.data.synth.generate import SynthConfig, generate_dataset
    from geoavatar.train.options import RunOptions
    from geoavatar.train.trainer import train

    data = tmp_path / "tiny"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ShortVideoWarning)
        generate_dataset(data, SynthConfig(subject=0, frames=8, size=48, seed=0), progress=False)
        # preset A: face sets without APS parts, the loss must still find its skin faces
        config = replace(preset("A", steps=2), warped_view=WarpedViewConfig(weight=0.5, every=2))
        result = train(RunOptions(data=data, out=tmp_path / "run", device="cpu", progress=False, log_every=1), config)
    assert result.status == "finished"
    log = (tmp_path / "run" / "train.log").read_text()
    step1 = next(line for line in log.splitlines() if "step 1:" in line and " total " in line)
    step2 = next(line for line in log.splitlines() if "step 2:" in line and " total " in line)
    assert "warped_view" not in step1 and "warped_view" in step2  # every 2nd step
    assert float(step2.split("warped_view ")[1].split()[0]) > 0  # pixels were valid and the render differs
    with pytest.raises(ValueError, match="warped_view.parts"):
        replace(config, warped_view=WarpedViewConfig(parts=("cheeks",))).validate()
    with pytest.raises(ValueError, match="warped_view.max_angle"):
        replace(config, warped_view=WarpedViewConfig(max_angle=120.0)).validate()
