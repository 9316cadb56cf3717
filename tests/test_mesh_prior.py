"""TrainConfig.mesh_prior (train/mesh_prior.py): the rendered weight behind the mesh's depth is ~0 for Gaussians on
the surface and positive for one planted behind it, its gradient asks the hidden Gaussian to fade and the front to
close; the alpha outside the dilated silhouette counts a floater beside the mesh; the trainer logs the terms.

A flat square mesh 1 m in front of a 64 px camera, Gaussians laid on it (a few hundred): no head model needed.
"""

from __future__ import annotations

import warnings
from dataclasses import replace

import pytest
import torch

from geoavatar.avatar.binding import GlobalGaussians
from geoavatar.config import MeshPriorConfig
from geoavatar.render.camera import Camera
from geoavatar.train.mesh_prior import behind_surface, camera_prior_terms, turned_angles

SIZE = 64
HALF = 0.3  # the square spans [-HALF, HALF]^2 at z = 1: pixels 12.8 .. 51.2


def camera() -> Camera:
    K = torch.tensor([[64.0, 0.0, SIZE / 2], [0.0, 64.0, SIZE / 2], [0.0, 0.0, 1.0]])
    return Camera(torch.eye(4), K, SIZE, SIZE)


def square() -> tuple[torch.Tensor, torch.Tensor]:
    vertices = torch.tensor([[-HALF, -HALF, 1.0], [HALF, -HALF, 1.0], [HALF, HALF, 1.0], [-HALF, HALF, 1.0]])
    return vertices, torch.tensor([[0, 1, 2], [0, 2, 3]])


def gaussians(means: torch.Tensor, opacities: torch.Tensor, last_scale: float = 0.02) -> GlobalGaussians:
    """Isotropic Gaussians of 2 cm, the last one `last_scale`."""
    n = means.shape[0]
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1.0
    scales = torch.full((n, 3), 0.02)
    scales[-1] = last_scale
    return GlobalGaussians(means, quats, scales, opacities, torch.full((n, 3), 0.5), None)


def surface_layer(opacity: float) -> tuple[torch.Tensor, torch.Tensor]:
    """[225, 3] means on the square (z = 1), [225] opacities."""
    axis = torch.linspace(-HALF + 0.02, HALF - 0.02, 15)
    ys, xs = torch.meshgrid(axis, axis, indexing="ij")
    means = torch.stack([xs.reshape(-1), ys.reshape(-1), torch.ones(225)], -1)
    return means, torch.full((225,), opacity)


def test_behind_surface_tests_each_point_against_the_depth_where_it_projects():
    depth = torch.full((4, 4), float("inf"))
    depth[:, :2] = 1.0  # the left half is covered at z = 1
    K = torch.tensor([[2.0, 0.0, 2.0], [0.0, 2.0, 2.0], [0.0, 0.0, 1.0]])
    points = torch.tensor([
        [-0.5, 0.0, 1.0],    # on the surface
        [-0.5, 0.0, 1.004],  # within the margin
        [-0.5, 0.0, 1.05],   # behind it
        [0.5, 0.0, 1.05],    # behind, but over an uncovered pixel
        [-5.0, 0.0, 1.05],   # off the image
        [-0.5, 0.0, -1.0],   # behind the camera
    ])
    assert behind_surface(points, depth, K, 0.005).tolist() == [False, False, True, False, False, False]


def test_behind_term_is_zero_on_the_surface_and_positive_for_a_planted_gaussian():
    vertices, faces = square()
    means, opacities = surface_layer(0.5)
    on_surface = camera_prior_terms(gaussians(means, opacities), vertices, faces, camera(), 0.005, 3)
    assert float(on_surface["behind"]) == 0.0 and float(on_surface["outside"]) < 1e-6

    planted_means = torch.cat([means, torch.tensor([[0.0, 0.0, 1.1]])])  # 10 cm behind the square's centre
    opacity = torch.cat([opacities, torch.tensor([0.9])]).requires_grad_(True)
    terms = camera_prior_terms(gaussians(planted_means, opacity, 0.05), vertices, faces, camera(), 0.005, 3)
    assert float(terms["behind"].detach()) > 1e-3
    assert float(terms["outside"].detach()) < 1e-6  # behind the square, not beside it
    terms["behind"].backward()
    assert float(opacity.grad[-1]) > 0  # the hidden Gaussian should fade ...
    assert float(opacity.grad[:-1].min()) < 0  # ... and the surface in front of it close
    assert float(opacity.grad[:-1].max()) <= 0


def test_outside_term_counts_alpha_beside_the_dilated_silhouette():
    vertices, faces = square()
    means, opacities = surface_layer(0.5)
    beside = torch.cat([means, torch.tensor([[0.45, 0.0, 1.0]])])  # pixel 60.8: 9 px off the square's edge
    terms = camera_prior_terms(gaussians(beside, torch.cat([opacities, torch.tensor([0.9])]), 0.01), vertices, faces,
                               camera(), 0.005, 3)
    assert float(terms["outside"]) > 1e-4 and float(terms["behind"]) == 0.0
    wide = camera_prior_terms(gaussians(beside, torch.cat([opacities, torch.tensor([0.9])]), 0.005), vertices, faces,
                              camera(), 0.005, 16)
    assert float(wide["outside"]) < 1e-6  # a dilation wide enough (room for hair) lets it be


def test_turned_angles_are_seeded_and_within_range():
    config = MeshPriorConfig(turned_yaw=45.0, turned_pitch=10.0)
    drawn = [turned_angles(config.turned_yaw, config.turned_pitch, 3, step) for step in range(1, 200)]
    assert drawn == [turned_angles(config.turned_yaw, config.turned_pitch, 3, step) for step in range(1, 200)]
    assert all(abs(y) <= 45.0 and abs(p) <= 10.0 for y, p in drawn)
    assert max(y for y, _ in drawn) > 30.0 and min(y for y, _ in drawn) < -30.0
    ranges = (config.turned_yaw, config.turned_pitch)
    assert turned_angles(*ranges, 4, 7) != turned_angles(*ranges, 3, 7)


def test_trainer_logs_the_mesh_prior_terms(tmp_path):
    from geoavatar.config import preset
    from geoavatar.data.splits import ShortVideoWarning
    from geoavatar.data.synth.generate import SynthConfig, generate_dataset
    from geoavatar.train.trainer import RunOptions, train

    data = tmp_path / "tiny"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ShortVideoWarning)
        generate_dataset(data, SynthConfig(subject=0, frames=8, size=48, seed=0), progress=False)
        config = preset("E", steps=3)
        config = replace(config, mesh_prior=MeshPriorConfig(lambda_behind=0.1, lambda_turned_behind=0.1,
                                                            lambda_turned_outside=0.1, turned_every=2))
        result = train(RunOptions(data=data, out=tmp_path / "run", device="cpu", progress=False, log_every=1), config)
    assert result.status == "finished"
    log = (tmp_path / "run" / "train.log").read_text()
    step1 = next(line for line in log.splitlines() if "step 1:" in line and " total " in line)
    step2 = next(line for line in log.splitlines() if "step 2:" in line and " total " in line)
    assert " behind " in step1 and "turned_behind" not in step1  # the turned camera every 2nd step
    assert "turned_behind" in step2 and "turned_outside" in step2
    with pytest.raises(ValueError, match="mesh_prior.turned_every"):
        replace(config, mesh_prior=MeshPriorConfig(turned_every=0)).validate()
