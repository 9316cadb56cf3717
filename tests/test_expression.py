"""Issue #27's additions: expression blendshapes of the Gaussians and the per-frame (row) Adam of the tracking
refinement."""

import torch

from geoavatar.avatar import GaussianAvatar, gaussian_param_groups
from geoavatar.avatar import densify as D
from geoavatar.avatar.binding import face_frames, local_to_global
from geoavatar.avatar.expression import (HEAD_CODE_DIM, POSE_CODE_DIM, code_masks, expression_code,
                                          expression_code_dims, expression_groups)
from geoavatar.config import LearningRates
from geoavatar.head.params import HeadParams
from geoavatar.train.frame_params import RowAdam
from tests.test_avatar import grid_mesh


def test_expression_code_takes_the_leading_modes_the_jaw_the_eyes_and_the_head():
    extra = POSE_CODE_DIM + HEAD_CODE_DIM
    assert expression_code_dims(23) == 23 + extra and expression_code_dims(100) == 50 + extra
    params = HeadParams(shape=torch.zeros(5), expr=torch.arange(100.0)[None], rotation=torch.tensor([[0.3, 0.0, 0.0]]),
                        neck_pose=torch.tensor([[0.0, 0.1, 0.0]]), jaw_pose=torch.tensor([[0.2, 0.0, 0.01]]),
                        eyes_pose=torch.full((1, 6), -0.1), translation=torch.zeros(1, 3))
    code = expression_code(params, expression_code_dims(23))
    assert code.shape == (38,)
    assert torch.equal(code[:23], torch.arange(23.0)) and torch.equal(code[23:26], torch.tensor([0.2, 0.0, 0.01]))
    assert torch.allclose(code[26:32], torch.full((6,), -0.1))
    assert torch.equal(code[32:], torch.tensor([0.3, 0.0, 0.0, 0.0, 0.1, 0.0]))
    short = expression_code(params.replace(expr=torch.ones(1, 10)), expression_code_dims(23))
    assert torch.equal(short[:23], torch.cat([torch.ones(10), torch.zeros(13)]))  # a model with fewer modes: zeros
    masks = code_masks("split", 38)  # the face follows the expression, the rest the head's turn
    assert masks[0, :32].eq(1).all() and masks[0, 32:].eq(0).all() and masks[1, :32].eq(0).all()
    assert masks[1, 32:].eq(1).all()
    assert code_masks("face", 38)[1].eq(0).all() and torch.equal(code_masks("all", 38)[1], masks[0])


def test_blendshapes_move_colour_and_mean_linearly_with_the_code_and_follow_densify():
    verts, faces = grid_mesh()
    k = 4
    avatar = GaussianAvatar(faces, expression_dims=k)
    plain = GaussianAvatar(faces)
    assert avatar.expression_dims == k and plain.expression_dims == 0
    code = torch.tensor([1.0, -2.0, 0.5, 0.0])
    # zero blendshapes (the start) and a zero code are the neutral avatar
    assert torch.equal(avatar(verts, code).colors, plain(verts).colors)
    with torch.no_grad():
        avatar.params["f_expr"].copy_(torch.randn(len(faces), 3 * k) * 0.01)  # colours stay in (0, 1): no clamp
        avatar.params["means_expr"].copy_(torch.randn(len(faces), 3 * k) * 0.1)
    assert torch.equal(avatar(verts, torch.zeros(k)).means, plain(verts).means)
    out = avatar(verts, code)
    colour = 0.5 + (avatar.params["f_expr"].view(-1, 3, k) * code).sum(-1)
    assert torch.allclose(out.colors, colour.clamp_min(0), atol=1e-6)
    local = (avatar.params["means_expr"].view(-1, 3, k) * code).sum(-1)
    p = avatar.params
    means, _, _ = local_to_global(local, p["quats"], p["scales"], avatar.binding, face_frames(verts, faces))
    assert torch.allclose(out.means, means, atol=1e-6)
    # linear: twice the code moves the colour twice as far from the neutral
    neutral = avatar(verts, torch.zeros(k)).colors
    assert torch.allclose(avatar(verts, 2 * code).colors - neutral, 2 * (out.colors - neutral), atol=1e-5)
    # Adam trains both; densify copies the rows with their Gaussians
    opt = torch.optim.Adam(gaussian_param_groups(avatar.params, LearningRates(), 1.0), eps=1e-15)
    assert {"f_expr", "means_expr"} <= {g["name"] for g in opt.param_groups}
    with torch.no_grad():
        avatar.params["f_expr"][:, 0] = torch.arange(len(faces), dtype=torch.float32)
    pick = torch.zeros(len(faces), dtype=torch.bool)
    pick[[2, 5]] = True
    avatar.binding = D.clone_gaussians(avatar.params, opt, avatar.binding, pick)
    assert avatar.params["means_expr"].shape == (avatar.num_gaussians, 3 * k)
    assert torch.equal(avatar.params["f_expr"][:, 0].round().long(), avatar.binding)
    out = avatar(verts, code)
    (out.colors.sum() + out.means.sum()).backward()
    assert avatar.params["f_expr"].grad.abs().sum() > 0 and avatar.params["means_expr"].grad.abs().sum() > 0
    fresh = GaussianAvatar(faces, expression_dims=k)
    fresh.load_state_dict(avatar.state_dict())
    assert torch.equal(fresh(verts, code).colors, avatar(verts, code).colors)


def test_row_adam_moves_only_the_rows_a_gradient_reaches_one_step_per_visit():
    rows = torch.nn.Parameter(torch.zeros(5, 3))
    opt = RowAdam([{"params": [rows], "lr": 0.1}])
    target = torch.tensor([1.0, -1.0, 2.0])
    for visit in range(3):
        opt.zero_grad()
        ((rows[2] - target) ** 2).sum().backward()
        before = rows.detach().clone()
        opt.step()
        moved = (rows.detach() - before).abs().sum(1)
        assert moved[2] > 0 and moved[[0, 1, 3, 4]].eq(0).all()  # only the visited row, never the others
        if visit == 0:  # Adam's first step of a row moves each entry by exactly the rate, towards the target
            assert torch.allclose(rows.detach()[2], 0.1 * torch.sign(target), atol=1e-6)
    opt.zero_grad()
    ((rows[4] - target) ** 2).sum().backward()
    opt.step()  # a row's first visit is a first step, whatever the others have seen
    assert torch.allclose(rows.detach()[4], 0.1 * torch.sign(target), atol=1e-6)
    state = opt.state[rows]
    assert state["row_steps"].tolist() == [0, 0, 3, 0, 1]


def test_blendshapes_drive_each_group_by_its_own_code_entries():
    verts, faces = grid_mesh()
    k = 4
    groups = torch.zeros(len(faces), dtype=torch.long)
    groups[len(faces) // 2:] = 1
    masks = torch.tensor([[1.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 1.0]])
    avatar = GaussianAvatar(faces, expression_dims=k, expression_groups=groups, code_masks=masks)
    with torch.no_grad():
        avatar.params["f_expr"].fill_(0.05)
        avatar.params["means_expr"].fill_(0.1)
    still = avatar(verts, torch.zeros(k))
    first = avatar(verts, torch.tensor([1.0, 1.0, 0.0, 0.0]))  # only group 0's entries
    face = groups == 0
    assert (first.colors[face] - still.colors[face]).abs().min() > 0.05
    assert torch.equal(first.colors[~face], still.colors[~face]) and torch.equal(first.means[~face], still.means[~face])
    second = avatar(verts, torch.tensor([0.0, 0.0, 1.0, 1.0]))  # only group 1's entries
    assert torch.equal(second.colors[face], still.colors[face])
    assert (second.colors[~face] - still.colors[~face]).abs().min() > 0.05
    (first.colors.sum() + first.means.sum()).backward()
    grad = avatar.params["f_expr"].grad.view(-1, 3, k)
    assert grad[~face].abs().sum() == 0 and grad[face][..., 2:].abs().sum() == 0 and grad[face][..., :2].abs().sum() > 0


def test_the_face_group_is_the_face_skin_and_the_mouth_not_the_hair():
    from geoavatar.head import load_head_model
    from geoavatar.head.regions import face_parts

    head = load_head_model("openhead", mouth="geoavatar")
    group = expression_groups(head).numpy()
    parts = face_parts(head.data)
    assert (group[parts.faces_of("lips")] == 0).all() and (group[parts.faces_of("forehead")] == 0).all()
    assert (group[parts.mouth_faces] == 0).all()
    assert (group[parts.faces_of("scalp")] == 1).all() and (group[parts.faces_of("neck")] == 1).all()
