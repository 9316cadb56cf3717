"""Issue #27's addition: the Gaussians off the face follow the head's turn (model.hair_follows_head)."""

import torch

from geoavatar.avatar import GaussianAvatar, gaussian_param_groups
from geoavatar.avatar import densify as D
from geoavatar.avatar.binding import face_frames, local_to_global
from geoavatar.avatar.hair_motion import POSE_CODE_DIM, head_pose_code, moving_faces
from geoavatar.config import LearningRates
from geoavatar.head.params import HeadParams
from tests.test_avatar import grid_mesh


def test_the_code_is_the_head_rotation_and_the_neck():
    params = HeadParams(shape=torch.zeros(5), expr=torch.arange(10.0)[None], rotation=torch.tensor([[0.3, 0.0, 0.0]]),
                        neck_pose=torch.tensor([[0.0, 0.1, 0.0]]), jaw_pose=torch.tensor([[0.2, 0.0, 0.01]]),
                        eyes_pose=torch.full((1, 6), -0.1), translation=torch.zeros(1, 3))
    assert torch.equal(head_pose_code(params), torch.tensor([0.3, 0.0, 0.0, 0.0, 0.1, 0.0]))


def test_only_the_moving_faces_gaussians_move_linearly_with_the_code_and_follow_densify():
    verts, faces = grid_mesh()
    moving = torch.zeros(len(faces), dtype=torch.bool)
    moving[len(faces) // 2:] = True
    avatar = GaussianAvatar(faces, moving=moving)
    plain = GaussianAvatar(faces)
    assert avatar.follows_head and not plain.follows_head
    code = torch.tensor([0.3, -0.2, 0.1, 0.0, 0.05, 0.0])
    # zero offsets (the start) and a zero code are the plain avatar
    assert torch.equal(avatar(verts, code).colors, plain(verts).colors)
    with torch.no_grad():
        avatar.params["f_pose"].copy_(torch.randn(len(faces), 3 * POSE_CODE_DIM) * 0.01)  # colours stay in (0, 1)
        avatar.params["means_pose"].copy_(torch.randn(len(faces), 3 * POSE_CODE_DIM) * 0.1)
    assert torch.equal(avatar(verts, torch.zeros(POSE_CODE_DIM)).means, plain(verts).means)
    out = avatar(verts, code)
    weight = moving[:, None].float()
    colour = 0.5 + (avatar.params["f_pose"].view(-1, 3, POSE_CODE_DIM) * code).sum(-1) * weight
    assert torch.allclose(out.colors, colour.clamp_min(0), atol=1e-6)
    local = (avatar.params["means_pose"].view(-1, 3, POSE_CODE_DIM) * code).sum(-1) * weight
    p = avatar.params
    means, _, _ = local_to_global(local, p["quats"], p["scales"], avatar.binding, face_frames(verts, faces))
    assert torch.allclose(out.means, means, atol=1e-6)
    still = ~moving  # the face's Gaussians take no offset
    assert torch.equal(out.colors[still], plain(verts).colors[still])
    # linear: twice the code moves the colour twice as far from the rest pose's
    rest = avatar(verts, torch.zeros(POSE_CODE_DIM)).colors
    assert torch.allclose(avatar(verts, 2 * code).colors - rest, 2 * (out.colors - rest), atol=1e-5)
    # Adam trains both; densify copies the rows with their Gaussians; the gradient reaches only moving Gaussians
    opt = torch.optim.Adam(gaussian_param_groups(avatar.params, LearningRates(), 1.0), eps=1e-15)
    assert {"f_pose", "means_pose"} <= {g["name"] for g in opt.param_groups}
    with torch.no_grad():
        avatar.params["f_pose"][:, 0] = torch.arange(len(faces), dtype=torch.float32) * 1e-3
    pick = torch.zeros(len(faces), dtype=torch.bool)
    pick[[2, len(faces) - 1]] = True
    avatar.binding = D.clone_gaussians(avatar.params, opt, avatar.binding, pick)
    assert avatar.params["means_pose"].shape == (avatar.num_gaussians, 3 * POSE_CODE_DIM)
    assert torch.equal((avatar.params["f_pose"][:, 0] * 1e3).round().long(), avatar.binding)
    out = avatar(verts, code)
    (out.colors.sum() + out.means.sum()).backward()
    grad = avatar.params["means_pose"].grad.abs().sum(1)
    assert grad[moving[avatar.binding]].min() > 0 and grad[~moving[avatar.binding]].eq(0).all()
    fresh = GaussianAvatar(faces, moving=moving)
    fresh.load_state_dict(avatar.state_dict())
    assert torch.equal(fresh(verts, code).colors, avatar(verts, code).colors)


def test_the_moving_faces_are_the_hair_ears_and_neck_not_the_face_or_mouth():
    from geoavatar.head import load_head_model
    from geoavatar.head.regions import face_parts

    head = load_head_model("openhead", mouth="geoavatar")
    moving = moving_faces(head).numpy()
    parts = face_parts(head.data)
    assert not moving[parts.faces_of("lips")].any() and not moving[parts.faces_of("forehead")].any()
    assert not moving[parts.mouth_faces].any()
    assert moving[parts.faces_of("scalp")].all() and moving[parts.faces_of("neck")].all()
    assert moving[parts.faces_of("ears")].all()


def test_codes_beyond_the_training_frames_range_are_clamped_and_older_runs_load_without_a_range():
    verts, faces = grid_mesh()
    avatar = GaussianAvatar(faces, moving=torch.ones(len(faces), dtype=torch.bool))
    with torch.no_grad():
        avatar.params["means_pose"].copy_(torch.randn(len(faces), 3 * POSE_CODE_DIM) * 0.1)
    older = avatar.state_dict()  # a run trained before the range was kept
    codes = torch.tensor([[-0.1, 0.0, 0.0, 0.0, 0.0, 0.0], [0.2, 0.1, 0.1, 0.05, 0.05, 0.05]])  # [M, 6] training frames
    avatar.set_pose_range(codes)
    assert torch.equal(avatar.pose_range, torch.stack([codes.min(0).values, codes.max(0).values]))
    inside, beyond = torch.tensor([0.1, 0.05, 0.0, 0.0, 0.02, 0.01]), torch.tensor([0.6, -0.3, 0.1, 0.0, 0.2, 0.0])
    clamped = torch.tensor([0.2, 0.0, 0.1, 0.0, 0.05, 0.0])
    assert torch.equal(avatar.clamp_pose_code(beyond), clamped) and torch.equal(avatar.clamp_pose_code(inside), inside)
    assert torch.equal(avatar(verts, beyond).means, avatar(verts, clamped).means)
    assert not torch.allclose(avatar(verts, inside).means, avatar(verts, clamped).means)
    fresh = GaussianAvatar(faces, moving=torch.ones(len(faces), dtype=torch.bool))
    fresh.load_state_dict(avatar.state_dict())
    assert torch.equal(fresh.pose_range, avatar.pose_range)
    fresh.load_state_dict(older)
    assert fresh.pose_range is None and torch.equal(fresh.clamp_pose_code(beyond), beyond)
    assert not torch.allclose(fresh(verts, beyond).means, fresh(verts, clamped).means)


def test_a_run_follows_the_head_by_default_reloads_poses_and_exports_each_frames_code(tmp_path, capsys):
    import json
    import warnings

    import numpy as np

    from apps_fixtures import make_subject
    from geoavatar import cli
    from geoavatar.apps.web_export import export_web
    from geoavatar.data import open_subject
    from geoavatar.avatar.render import pose_avatar
    from geoavatar.data.splits import ShortVideoWarning
    from geoavatar.train.checkpoint import open_run
    from geoavatar.train.run_frames import RunFrames
    from geoavatar.web import pack

    data = make_subject(tmp_path / "data", frames=6, size=32)

    def train(out: str, *options: str):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ShortVideoWarning)
            code = cli.main(["train", "--data", str(data), "--out", str(tmp_path / out), "--steps", "3", "--device",
                             "cpu", "--no-progress", *options])
        assert code == 0, capsys.readouterr().err
        return open_run(tmp_path / out, "cpu")

    run = train("run")
    assert run.config.model.hair_follows_head and run.avatar.follows_head  # the default
    # the box of the training frames' codes as tracked, to which every code is clamped
    tracked = open_subject(data).params
    train_rows = [run.info.timesteps["all"].index(t) for t in run.info.timesteps["train"]]
    codes = torch.cat([tracked["rotation"][train_rows], tracked["neck_pose"][train_rows]], 1)  # [M, 6]
    assert torch.allclose(run.avatar.pose_range, torch.stack([codes.min(0).values, codes.max(0).values]))
    frames = RunFrames(run)
    params, timestep = frames.params(frames.timesteps[0])
    turned = pose_avatar(run.avatar, run.head, params.replace(rotation=params.rotation + 0.2), timestep, run.deformer)
    assert turned.gaussians.means.shape[0] == run.avatar.num_gaussians and torch.isfinite(turned.gaussians.means).all()
    manifest = json.loads((export_web(run, tmp_path / "web", show_progress=False) / pack.MANIFEST).read_text())
    assert manifest["avatar"]["followsHead"] and len(manifest["clip"]["pose"]) == manifest["clip"]["frames"]
    first = frames.params(manifest["clip"]["timesteps"][0])[0]
    clamped = run.avatar.clamp_pose_code(head_pose_code(first))  # the browser gets the code the CPU renderer poses by
    np.testing.assert_allclose(manifest["clip"]["pose"][0], clamped.numpy(), atol=1e-6)

    rigid = train("rigid", "--config.model.no-hair-follows-head")  # GaussianAvatars' rigging
    assert not rigid.avatar.follows_head
    manifest = json.loads((export_web(rigid, tmp_path / "web_rigid", show_progress=False) / pack.MANIFEST).read_text())
    assert "followsHead" not in manifest["avatar"] and "pose" not in manifest["clip"]
