"""AVATAR layer: face frames, local -> global, densify/prune with binding, APS, mouth deformation."""

import json
import math

import numpy as np
import pytest
import torch

from geoavatar.avatar import (
    APSState, GaussianAvatar, MouthDeformer, assign_parts, face_frames, face_set_ids, gaussian_param_groups,
    local_to_global, part_distances, polar_coordinates, positional_encoding, posed_head,
)
from geoavatar.avatar import densify as D
from geoavatar.avatar.aps import FLEXIBLE, MOUTH, RIGID, BASELINE
from geoavatar.config import DensifyConfig, LearningRates, MouthDeformConfig
from geoavatar.geometry import axis_angle_to_matrix, quaternion_to_matrix
from geoavatar.head.base import HeadModel, HeadModelData


def grid_mesh(n: int = 6, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """A bumpy n x n vertex sheet: (vertices [n*n, 3], faces [2(n-1)^2, 3])."""
    g = torch.Generator().manual_seed(seed)
    ys, xs = torch.meshgrid(torch.arange(n, dtype=torch.float32), torch.arange(n, dtype=torch.float32), indexing="ij")
    verts = torch.stack([xs.reshape(-1), ys.reshape(-1), 0.1 * torch.randn(n * n, generator=g)], -1) * 0.01
    faces = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, i * n + j + 1, (i + 1) * n + j, (i + 1) * n + j + 1
            faces += [[a, b, d], [a, d, c]]
    return verts, torch.tensor(faces)


# --- frames and local -> global ---------------------------------------------------------------


def test_local_to_global_matches_hand_computation_on_one_triangle():
    verts = torch.tensor([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    faces = torch.tensor([[0, 1, 2]])
    frames = face_frames(verts, faces)
    # a0 = (1,0,0); a1 = a0 x (0,1,0) = (0,0,1) (normal); a2 = a0 x a1 = (0,-1,0); k = (2 + 1) / 2.
    expected_r = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    assert torch.allclose(frames.rotation[0], expected_r, atol=1e-6)
    assert torch.allclose(frames.centre[0], torch.tensor([2 / 3, 1 / 3, 0.0]), atol=1e-6)
    assert frames.scale[0].item() == pytest.approx(1.5)

    mu = torch.tensor([[0.1, 0.2, 0.3]])
    local_rot = axis_angle_to_matrix(torch.tensor([math.pi / 2, 0.0, 0.0]))
    q = torch.tensor([[math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0]]) * 3.0  # not unit on purpose
    s = torch.log(torch.tensor([[0.5, 1.0, 2.0]]))
    means, quats, scales = local_to_global(mu, q, s, torch.tensor([0]), frames)
    # 0.1 a0 + 0.2 a1 + 0.3 a2 = (0.1, -0.3, 0.2), times k, plus C
    assert torch.allclose(means[0], 1.5 * torch.tensor([0.1, -0.3, 0.2]) + torch.tensor([2 / 3, 1 / 3, 0.0]), atol=1e-6)
    assert torch.allclose(scales[0], torch.tensor([0.75, 1.5, 3.0]), atol=1e-6)
    assert torch.allclose(quaternion_to_matrix(quats[0]), expected_r @ local_rot, atol=1e-5)
    assert quats.norm(dim=-1).item() == pytest.approx(1.0, abs=1e-6)


def test_frames_are_rotations_and_batching_agrees():
    verts, faces = grid_mesh()
    frames = face_frames(verts, faces)
    r = frames.rotation
    assert torch.allclose(r.transpose(-1, -2) @ r, torch.eye(3).expand_as(r), atol=1e-5)
    assert torch.allclose(torch.linalg.det(r), torch.ones(len(faces)), atol=1e-5)
    batch = torch.stack([verts, verts * 2.0 + 1.0])
    fb = face_frames(batch, faces)
    assert torch.allclose(fb.rotation[0], r, atol=1e-6) and torch.allclose(fb.rotation[1], r, atol=1e-5)
    assert torch.allclose(fb.scale[1], 2.0 * frames.scale, atol=1e-6)
    # the global placement follows a rigid motion of the mesh
    avatar = GaussianAvatar(faces)
    with torch.no_grad():
        avatar.params["means"].normal_(0, 0.5)
    rot = axis_angle_to_matrix(torch.tensor([0.3, -0.5, 0.2]))
    a, b = avatar(verts), avatar(verts @ rot.T + torch.tensor([0.1, 0.2, 0.3]))
    assert torch.allclose(b.means, a.means @ rot.T + torch.tensor([0.1, 0.2, 0.3]), atol=1e-5)
    assert torch.allclose(quaternion_to_matrix(b.quats), rot @ quaternion_to_matrix(a.quats), atol=1e-4)


def test_initial_avatar_has_one_gaussian_per_face_at_its_centre():
    verts, faces = grid_mesh()
    avatar = GaussianAvatar(faces)
    out = avatar(verts)
    frames = face_frames(verts, faces)
    assert avatar.num_gaussians == len(faces) and torch.equal(avatar.binding, torch.arange(len(faces)))
    assert torch.allclose(out.means, frames.centre, atol=1e-7)
    assert torch.allclose(out.scales, frames.scale[:, None].expand(-1, 3), atol=1e-7)
    assert torch.allclose(out.opacities, torch.full((len(faces),), 0.1), atol=1e-6)
    assert torch.allclose(out.colors, torch.full((len(faces), 3), 0.5))


def test_polar_coordinates_measure_angle_to_the_normal():
    mu = torch.tensor([[0.0, 2.0, 0.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 0.0]])
    r, phi = polar_coordinates(mu)
    assert torch.allclose(r, torch.tensor([2.0, 1.0, 1.0, math.sqrt(2.0), 0.0]), atol=1e-6)
    assert torch.allclose(phi, torch.tensor([0.0, math.pi / 2, math.pi, math.pi / 4, 0.0]), atol=1e-6)
    _, phi2 = polar_coordinates(mu, two_sided=True)
    assert phi2[2].item() == pytest.approx(0.0, abs=1e-6)
    leaf = mu.clone().requires_grad_()
    r, phi = polar_coordinates(leaf)
    (r.sum() + phi.sum()).backward()
    assert torch.isfinite(leaf.grad).all()


def test_gradients_flow_from_global_gaussians_to_local_parameters_and_vertices():
    verts, faces = grid_mesh()
    verts = verts.clone().requires_grad_()
    avatar = GaussianAvatar(faces)
    with torch.no_grad():
        avatar.params["quats"].add_(0.1 * torch.randn_like(avatar.params["quats"]))
    out = avatar(verts)
    g = torch.Generator().manual_seed(3)
    loss = sum((t * torch.randn(t.shape, generator=g)).sum()
               for t in (out.means, out.quats, out.scales, out.opacities, out.colors))
    loss.backward()
    for name, p in avatar.params.items():
        assert p.grad is not None and p.grad.abs().sum() > 0, name
    assert verts.grad.abs().sum() > 0


# --- densification ----------------------------------------------------------------------------


def _trained_setup(seed: int = 0):
    """An avatar with 2-3 Gaussians per face, an Adam with non-zero moments and an extra MLP group."""
    torch.manual_seed(seed)
    verts, faces = grid_mesh()
    avatar = GaussianAvatar(faces)
    params = avatar.params
    extra = D.clone_gaussians(params, None, avatar.binding, torch.rand(len(faces)) < 0.7)
    avatar.binding = extra
    with torch.no_grad():
        for p in params.values():
            p.add_(0.05 * torch.randn_like(p))
    mlp = torch.nn.Linear(4, 3)
    groups = gaussian_param_groups(params, LearningRates(), scene_extent=1.0)
    opt = torch.optim.Adam(groups + [{"params": list(mlp.parameters()), "lr": 1e-3, "name": "mlp"}], eps=1e-15)
    out = avatar(verts)
    (out.means.square().sum() + out.quats[:, 1].sum() + out.colors.sum() + out.opacities.sum() + out.scales.sum()
     + mlp(torch.ones(4)).sum()).backward()
    opt.step()
    opt.zero_grad()
    return verts, faces, avatar, opt, mlp


def _assert_consistent(avatar: GaussianAvatar, opt: torch.optim.Optimizer, state=None):
    n = avatar.num_gaussians
    for name, p in avatar.params.items():
        assert p.shape[0] == n, name
        holders = [g for g in opt.param_groups if any(q is p for q in g["params"])]
        assert len(holders) == 1, f"{name} not (or twice) in the optimizer"
        st = opt.state[p]
        assert st["exp_avg"].shape == p.shape and st["exp_avg_sq"].shape == p.shape, name
    for value in (state or {}).values():
        assert value.shape[0] == n
    assert (avatar.gaussians_per_face() >= 1).all(), "a face lost its last Gaussian"


def test_clone_and_split_inherit_binding_and_keep_optimizer_state_in_step():
    verts, faces, avatar, opt, mlp = _trained_setup()
    params, n0 = avatar.params, avatar.num_gaussians
    state = D.new_state(n0)
    old_binding = avatar.binding.clone()
    old_means, old_scales = params["means"].detach().clone(), params["scales"].detach().clone()
    old_moment = opt.state[params["f_dc"]]["exp_avg"].clone()
    mask = torch.zeros(n0, dtype=torch.bool)
    mask[::3] = True
    avatar.binding = D.clone_gaussians(params, opt, avatar.binding, mask, state)
    assert avatar.num_gaussians == n0 + int(mask.sum())
    assert torch.equal(avatar.binding[n0:], old_binding[mask])
    assert torch.equal(params["means"][n0:], old_means[mask])
    assert torch.equal(opt.state[params["f_dc"]]["exp_avg"][:n0], old_moment)
    assert (opt.state[params["f_dc"]]["exp_avg"][n0:] == 0).all()
    _assert_consistent(avatar, opt, state)

    n1 = avatar.num_gaussians
    split = torch.zeros(n1, dtype=torch.bool)
    split[1:n0:4] = True
    parents = torch.nonzero(split).squeeze(-1)
    avatar.binding = D.split_gaussians(params, opt, avatar.binding, split, state, generator=torch.Generator().manual_seed(0))
    m = len(parents)
    assert avatar.num_gaussians == n1 - m + 2 * m
    children = slice(avatar.num_gaussians - 2 * m, avatar.num_gaussians)
    assert torch.equal(avatar.binding[children], old_binding[parents].repeat(2))
    assert torch.allclose(params["scales"][children], (old_scales[parents] - math.log(1.6)).repeat(2, 1), atol=1e-6)
    # children are sampled around the parent's local mean, within a few parent standard deviations
    spread = (params["means"][children] - old_means[parents].repeat(2, 1)).norm(dim=-1)
    assert (spread < 6 * torch.exp(old_scales[parents]).amax(-1).repeat(2)).all()
    _assert_consistent(avatar, opt, state)

    # the optimizer still works after the surgery (MLP group untouched)
    out = avatar(verts)
    (out.means.square().sum() + mlp(torch.ones(4)).sum()).backward()
    opt.step()
    assert all(torch.isfinite(p).all() for p in params.values())


def test_prune_never_removes_the_last_gaussian_of_a_face():
    verts, faces, avatar, opt, _ = _trained_setup(1)
    params = avatar.params
    n = avatar.num_gaussians
    opacities = params["opacities"].detach().clone()
    old_binding = avatar.binding.clone()
    state = D.new_state(n)
    avatar.binding = D.prune_gaussians(params, opt, avatar.binding, torch.ones(n, dtype=torch.bool), len(faces), state)
    assert torch.equal(avatar.gaussians_per_face(), torch.ones(len(faces), dtype=torch.long))
    # the survivor of each face is its most opaque Gaussian
    best = torch.full((len(faces),), -1e9).scatter_reduce(0, old_binding, opacities, "amax")
    assert torch.allclose(params["opacities"].detach()[torch.argsort(avatar.binding)], best)
    _assert_consistent(avatar, opt, state)

    # a partial prune removes exactly what it can
    verts, faces, avatar, opt, _ = _trained_setup(2)
    n = avatar.num_gaussians
    mask = torch.rand(n, generator=torch.Generator().manual_seed(5)) < 0.5
    expected = D.protect_last_of_each_face(mask, avatar.binding, len(faces), avatar.params["opacities"].detach())
    avatar.binding = D.prune_gaussians(avatar.params, opt, avatar.binding, mask, len(faces))
    assert avatar.num_gaussians == n - int(expected.sum())
    _assert_consistent(avatar, opt)


def test_densify_and_prune_clones_small_and_splits_large_high_gradient_gaussians():
    verts, faces, avatar, opt, _ = _trained_setup(3)
    params, n = avatar.params, avatar.num_gaussians
    cfg = DensifyConfig()
    state = D.new_state(n)
    # pixel-space gradients; NDC scaling by (W/2, H/2) puts index 0,1 above the threshold
    grad = torch.zeros(n, 2)
    grad[:2, 0] = 2.0 * cfg.grad_threshold / (64 / 2)
    D.accumulate_stats(state, grad, torch.ones(n, dtype=torch.bool), width=64, height=48, radii=torch.full((n, 2), 3.0))
    assert state["grad2d"][0].item() == pytest.approx(2 * cfg.grad_threshold, rel=1e-5)
    assert state["max_radii"][0].item() == 3.0
    with torch.no_grad():
        params["opacities"].fill_(2.0)
        params["scales"][0] = math.log(1e-3)  # tiny -> clone
        params["scales"][1] = math.log(10.0)  # large -> split
    face_scale = face_frames(verts, faces).scale
    binding, counts = D.densify_and_prune(params, opt, avatar.binding, state, cfg, step=cfg.start + cfg.every,
                                          face_scale=face_scale, extent=1.0)
    avatar.binding = binding
    assert counts["cloned"] == 1 and counts["split"] == 1 and counts["pruned"] == 0
    assert avatar.num_gaussians == n + 1 + 1
    assert (state["grad2d"] == 0).all()
    _assert_consistent(avatar, opt, state)


def test_schedule_resets_opacity_and_stops():
    verts, faces, avatar, opt, _ = _trained_setup(4)
    cfg = DensifyConfig(start=2, stop=10, every=4, reset_opacity_every=6)
    state = D.new_state(avatar.num_gaussians)
    with torch.no_grad():
        avatar.params["opacities"].fill_(3.0)
    n = avatar.num_gaussians
    visible = torch.ones(n, dtype=torch.bool)
    face_scale = face_frames(verts, faces).scale
    strategy = D.DensifyStrategy(cfg, 1.0)
    binding, report = strategy.step_post_backward(avatar.params, opt, state, 4, D.DensifyInfo(
        avatar.binding, face_scale, torch.zeros(n, 2), visible, None, 64, 64))
    assert report is not None and report["total"] == n
    avatar.binding = binding
    binding, report = strategy.step_post_backward(avatar.params, opt, state, 6,
                                                  D.DensifyInfo(avatar.binding, face_scale))
    assert report is None
    assert torch.sigmoid(avatar.params["opacities"]).max().item() == pytest.approx(0.01, rel=1e-4)
    assert (opt.state[avatar.params["opacities"]]["exp_avg"] == 0).all()
    before = state["grad2d"].clone()
    strategy.step_post_backward(avatar.params, opt, state, 12, D.DensifyInfo(
        avatar.binding, face_scale, torch.ones(n, 2), visible, None, 64, 64))
    assert torch.equal(state["grad2d"], before)  # past `stop`: nothing accumulates


def test_checkpoint_round_trip_after_densification():
    verts, faces, avatar, opt, _ = _trained_setup(5)
    fresh = GaussianAvatar(faces)
    fresh.load_state_dict(avatar.state_dict())
    assert fresh.num_gaussians == avatar.num_gaussians
    assert torch.allclose(fresh(verts).means, avatar(verts).means)
    bad = avatar.state_dict()
    bad["binding"] = bad["binding"].clone()
    bad["binding"][0] = len(faces) + 5
    with pytest.raises(ValueError, match="binding"):
        GaussianAvatar(faces).load_state_dict(bad)


def test_normal_shading_follows_the_world_normal_and_survives_densify_and_checkpoints():
    """model.normal_shading: colour = SH-0 colour + F n with n the face normal in world axes, so turning the
    mesh changes the colour (lights fixed to the world); zero F is the plain colour; F rows move with
    clone / split / prune and through a checkpoint; Adam trains F."""
    verts, faces = grid_mesh()
    avatar = GaussianAvatar(faces, normal_shading=True)
    assert avatar.normal_shading and not GaussianAvatar(faces).normal_shading
    assert torch.allclose(avatar(verts).colors, torch.full((len(faces), 3), 0.5))  # F = 0 at the start
    with torch.no_grad():
        avatar.params["f_normal"].copy_(torch.tensor([0.0, 0.0, 0.2, 0.0, 0.0, 0.0, 0.0, 0.0, -0.2]).expand(len(faces), 9))
    rot = axis_angle_to_matrix(torch.tensor([math.pi / 2, 0.0, 0.0]))  # turns the sheet's normal from z to -y
    normal = face_frames(verts, faces).rotation[:, :, 1]  # [F, 3]
    expected = 0.5 + 0.2 * normal[:, 2:3] * torch.tensor([1.0, 0.0, -1.0])
    assert torch.allclose(avatar(verts).colors, expected, atol=1e-6)
    turned = avatar(verts @ rot.T).colors
    assert torch.allclose(turned, 0.5 + 0.2 * (normal @ rot.T)[:, 2:3] * torch.tensor([1.0, 0.0, -1.0]), atol=1e-5)
    assert (turned - avatar(verts).colors).abs().max() > 0.1
    # densify keeps the rows with their Gaussians; Adam trains F
    with torch.no_grad():
        avatar.params["f_normal"].add_(torch.arange(len(faces), dtype=torch.float32)[:, None])
    opt = torch.optim.Adam(gaussian_param_groups(avatar.params, LearningRates(), 1.0), eps=1e-15)
    assert any(g["name"] == "f_normal" for g in opt.param_groups)
    pick = torch.zeros(len(faces), dtype=torch.bool)
    pick[[1, 4]] = True
    avatar.binding = D.clone_gaussians(avatar.params, opt, avatar.binding, pick)
    avatar.binding = D.split_gaussians(avatar.params, opt, avatar.binding, torch.cat([pick, torch.zeros(2, dtype=torch.bool)]))
    rows = avatar.params["f_normal"][:, 0]  # column 0 holds the face index added above
    assert avatar.params["f_normal"].shape == (avatar.num_gaussians, 9)
    assert torch.equal(rows.round().long(), avatar.binding)
    fresh = GaussianAvatar(faces, normal_shading=True)
    fresh.load_state_dict(avatar.state_dict())
    assert torch.equal(fresh(verts).colors, avatar(verts).colors)
    avatar(verts @ rot.T).colors.sum().backward()
    assert avatar.params["f_normal"].grad.abs().sum() > 0


def test_scene_extent_has_a_floor_for_one_camera():
    assert D.scene_extent(torch.zeros(1, 3), minimum=0.7) == 0.7
    centres = torch.tensor([[1.0, 0, 0], [-1.0, 0, 0]])
    assert D.scene_extent(centres, minimum=0.1) == pytest.approx(1.1)


# --- APS ------------------------------------------------------------------------------------------


def test_aps_assigns_parts_by_the_mean_distance_rule():
    # 8 faces: parts 0,0,1,1,2,2 and two mouth faces (-1); hand-made local means.
    part_of_face = torch.tensor([0, 0, 1, 1, 2, 2, -1, -1])
    binding = torch.tensor([0, 1, 1, 2, 3, 4, 5, 6, 7])
    r = torch.tensor([0.1, 0.2, 0.4, 1.0, 2.0, 0.5, 0.5, 9.0, 9.0])  # the mouth values must not matter
    means = torch.zeros(9, 3)
    means[:, 2] = r
    # face means: f0 .1, f1 .3, f2 1.0, f3 2.0, f4 .5, f5 .5 -> Distance = [.2, 1.5, .5], tau = 2.2/3
    flexible, distances, tau = assign_parts(means, binding, part_of_face, num_parts=4)
    assert torch.allclose(distances[:3], torch.tensor([0.2, 1.5, 0.5]), atol=1e-6)
    assert torch.isnan(distances[3])  # part with no faces: not part of tau, stays rigid
    assert tau == pytest.approx(2.2 / 3, abs=1e-6)
    assert flexible.tolist() == [False, True, False, False]

    sets = face_set_ids(part_of_face, "aps", flexible)
    assert sets.tolist() == [RIGID, RIGID, FLEXIBLE, FLEXIBLE, RIGID, RIGID, MOUTH, MOUTH]
    assert face_set_ids(part_of_face, "aps", None).tolist() == [RIGID] * 6 + [MOUTH] * 2
    assert (face_set_ids(part_of_face, "flexible") == FLEXIBLE).all()
    assert (face_set_ids(part_of_face, "rigid") == RIGID).all()
    # H / I: GeoAvatar's mouth structure keeps its own set (tau_m) when every other face is rigid / flexible.
    assert face_set_ids(part_of_face, "flexible", mouth_set=True).tolist() == [FLEXIBLE] * 6 + [MOUTH] * 2
    assert face_set_ids(part_of_face, "rigid", mouth_set=True).tolist() == [RIGID] * 6 + [MOUTH] * 2
    assert (face_set_ids(part_of_face, "gaussianavatars", mouth_set=True) == BASELINE).all()
    assert (face_set_ids(part_of_face, "gaussianavatars") == BASELINE).all()
    with pytest.raises(ValueError, match="face-set mode"):
        face_set_ids(part_of_face, "bogus")


def test_aps_state_serialises_and_reports():
    part_of_face = torch.tensor([0, 1, 1, 2])
    means = torch.tensor([[0.0, 0.1, 0.0], [0.0, 3.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.2, 0.0]])
    state = APSState(part_names=["face", "scalp", "nose"])
    assert "not run" in state.report()
    assert state.face_sets(part_of_face).tolist() == [RIGID] * 4
    state.run(means, torch.arange(4), part_of_face, step=100)
    restored = APSState.from_dict(json.loads(json.dumps(state.to_dict())))
    assert restored == state
    assert restored.face_sets(part_of_face).tolist() == [RIGID, FLEXIBLE, FLEXIBLE, RIGID]
    text = restored.report()
    assert "scalp" in text and "flexible" in text and "step 100" in text
    with pytest.raises(ValueError, match="malformed"):
        APSState.from_dict({"done": True})
    # distances measured on real avatar parameters
    dist = part_distances(means, torch.arange(4), part_of_face, 3)
    assert torch.allclose(dist, torch.tensor([0.1, 2.5, 0.2]))


# --- mouth deformation ----------------------------------------------------------------------------


def toy_head_with_mouth() -> HeadModel:
    """8 vertices: 0-3 skin on the head, 4-5 'mouth_upper' on the neck joint, 6-7 'mouth_lower' on the jaw."""
    rng = np.random.default_rng(0)
    v = rng.normal(size=(8, 3)).astype(np.float32) * 0.05
    faces = np.array([[0, 1, 2], [1, 2, 3], [4, 5, 0], [6, 7, 3]], np.int64)
    w = np.zeros((8, 5), np.float32)
    w[[0, 1], 0] = 1
    w[[2, 3, 4, 5], 1] = 1
    w[[6, 7], 2] = 1
    jreg = np.zeros((5, 8), np.float32)
    jreg[:, :4] = 0.25
    data = HeadModelData(
        name="toy-mouth", v_template=v, faces=faces,
        shapedirs=np.zeros((8, 3, 2), np.float32), exprdirs=rng.normal(size=(8, 3, 4)).astype(np.float32) * 0.01,
        j_regressor=jreg, lbs_weights=w,
        vertex_groups={"mouth_upper": np.array([4, 5]), "mouth_lower": np.array([6, 7])},
        face_groups={"mouth": np.array([2, 3])},
    )
    return HeadModel(data)


def test_part_offsets_move_every_vertex_of_a_part_alike_and_nothing_else():
    head = toy_head_with_mouth()
    cfg = MouthDeformConfig(hidden_width=16, hidden_layers=2, frequencies=4, expr_dim=6)
    deformer = MouthDeformer.for_head(head, num_frames=50, cfg=cfg)
    params = head.zero_params(2)
    params["expr"] = torch.randn(2, 4)
    params["jaw_pose"] = torch.tensor([[0.3, 0.0, 0.0], [0.1, 0.2, 0.0]])
    params["rotation"] = torch.tensor([[0.0, 0.5, 0.0], [0.2, 0.0, 0.1]])
    plain = posed_head(head, params).vertices
    assert torch.allclose(posed_head(head, params, deformer, timestep=7).vertices, plain, atol=1e-7)  # zero init

    torch.manual_seed(0)
    with torch.no_grad():
        for mlp in deformer.phi.values():
            mlp[-1].weight.normal_(0, 1.0)
            mlp[-1].bias.normal_(0, 1.0)
    offsets = deformer(params["expr"], torch.zeros(2, 12), timestep=torch.tensor([3, 9]))
    assert torch.equal(offsets[:, :4], torch.zeros(2, 4, 3))
    assert torch.allclose(offsets[:, 4], offsets[:, 5]) and torch.allclose(offsets[:, 6], offsets[:, 7])
    assert not torch.allclose(offsets[:, 4], offsets[:, 6])

    moved = posed_head(head, params, deformer, timestep=torch.tensor([3, 9])).vertices
    delta = moved - plain  # [2, 8, 3]
    assert torch.allclose(delta[:, :4], torch.zeros(2, 4, 3), atol=1e-7)
    assert torch.allclose(delta[:, 4], delta[:, 5], atol=1e-6) and torch.allclose(delta[:, 6], delta[:, 7], atol=1e-6)
    assert delta[:, 4:].norm(dim=-1).min() > 1e-4
    # relative positions inside each part are preserved
    assert torch.allclose((moved[:, 4] - moved[:, 5]), (plain[:, 4] - plain[:, 5]), atol=1e-6)

    # inference: T = None is T = 0; other timesteps differ
    pose = torch.zeros(2, 12)
    assert torch.allclose(deformer(params["expr"], pose, None), deformer(params["expr"], pose, 0))
    assert not torch.allclose(deformer(params["expr"], pose, None), deformer(params["expr"], pose, 25))


def test_deformation_gradients_reach_the_mlps_and_the_gaussians():
    head = toy_head_with_mouth()
    deformer = MouthDeformer.for_head(head, 10, MouthDeformConfig(hidden_width=8, hidden_layers=2, frequencies=2, expr_dim=4))
    avatar = GaussianAvatar(head.faces)
    params = head.zero_params(1)
    out = avatar(posed_head(head, params, deformer, timestep=3).vertices[0])
    out.means.square().sum().backward()
    for name in ("upper", "lower"):
        last = deformer.phi[name][-1]
        assert last.weight.grad.abs().sum() > 0 and last.bias.grad.abs().sum() > 0, name
    assert avatar.params["means"].grad.abs().sum() > 0
    # once the last layer is non-zero, the hidden layers learn too
    with torch.no_grad():
        for mlp in deformer.phi.values():
            mlp[-1].weight.fill_(0.1)
    deformer.zero_grad()
    avatar(posed_head(head, params, deformer, timestep=3).vertices[0]).means.square().sum().backward()
    assert deformer.phi["lower"][0].weight.grad.abs().sum() > 0


def test_positional_encoding_and_errors():
    pe = positional_encoding(torch.tensor([0.0, 0.25]), 3)
    assert pe.shape == (2, 6)
    assert torch.allclose(pe[0], torch.tensor([0, 0, 0, 1, 1, 1.0]))
    assert pe[1, 0].item() == pytest.approx(math.sin(math.pi / 4))
    head = toy_head()
    with pytest.raises(ValueError, match="mouth_upper"):
        MouthDeformer.for_head(head, 10)
    with pytest.raises(ValueError, match="faces"):
        GaussianAvatar(torch.zeros(4, 2, dtype=torch.long))


def toy_head() -> HeadModel:
    data = toy_head_with_mouth().data
    return HeadModel(data.copy_with(vertex_groups={}))


def test_face_colours_come_from_the_pixels_that_show_each_face():
    """model.init_colour = "images": a sheet in front of a camera, the image red on the left and blue on the
    right: faces take the colour of their side; a face hidden behind the sheet, seen by no pixel, takes
    the colour of the nearest seen face; pixels outside the mask do not count."""
    from geoavatar.avatar.colour_init import face_colours
    from geoavatar.render.camera import intrinsics_from_fov, look_at

    verts, faces = grid_mesh(n=8)  # 7 cm sheet in the z = 0 plane, x and y in [0, 0.07]
    verts = verts - torch.tensor([0.035, 0.035, 0.0])
    hidden = torch.tensor([[0.030, 0.030, -0.02], [0.034, 0.030, -0.02], [0.030, 0.034, -0.02]])  # behind, right side
    all_verts = torch.cat([verts, hidden])
    all_faces = torch.cat([faces, torch.tensor([[64, 65, 66]])])
    size = 32
    viewmat = look_at(torch.tensor([0.0, 0.0, 0.3]), torch.zeros(3)).float()
    K = intrinsics_from_fov(20.0, size, size)
    image = torch.zeros(size, size, 3)
    image[:, : size // 2, 0] = 1.0  # image left: red (the sheet's -x side seen from +z)
    image[:, size // 2 :, 2] = 1.0  # image right: blue
    mask = torch.ones(size, size, 1)
    mask[: size // 2] = 0.0  # the top half is outside the mask
    colour, seen = face_colours(all_faces, [(all_verts, image, mask, viewmat, K)])
    centres = all_verts[all_faces].mean(1)  # [F, 3]
    visible = seen[:-1]
    assert not bool(seen[-1]) and int(visible.sum()) > 10
    left = visible & (centres[:-1, 0] < -0.005)
    right = visible & (centres[:-1, 0] > 0.005)
    assert bool(left.any()) and bool(right.any())
    assert torch.allclose(colour[:-1][left], torch.tensor([1.0, 0.0, 0.0]).expand(int(left.sum()), 3), atol=1e-5)
    assert torch.allclose(colour[:-1][right], torch.tensor([0.0, 0.0, 1.0]).expand(int(right.sum()), 3), atol=1e-5)
    assert torch.allclose(colour[-1], torch.tensor([0.0, 0.0, 1.0]))  # the nearest seen face is blue
    # faces that only the masked-out half shows are not seen (their colour comes from a neighbour)
    top = centres[:-1, 1] > 0.01  # +y is up in the world, the image's top half
    assert not bool(seen[:-1][top].any())
