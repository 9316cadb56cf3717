"""Mouth structure: molar extension geometry, placement inside the head, mesh validity, skinning."""

import numpy as np
import pytest
import torch

from geoavatar.head import HeadModel
from geoavatar.head.mouth import (
    MouthConfig, add_mouth_structure, molar_trajectory, mouth_line, pseudo_centre, reflect_points,
    trajectory_centre,
)
from head_fakes import head_by_name, procedural_head

HEADS = ["procedural", "flame5023", "openhead"]


@pytest.fixture(scope="module", params=HEADS)
def head(request):
    return head_by_name(request.param)


@pytest.fixture(scope="module")
def mouthed(head):
    return add_mouth_structure(head, "geoavatar")


def _front_teeth_trajectory(data):
    line = mouth_line(data)
    return line.points + np.array([0.0, -MouthConfig().setback * line.width]), line


def _winding_numbers(points, vertices, faces, chunk=8):
    """Generalised winding number of points [P, 3] w.r.t. a triangle mesh (Van Oosterom-Strackee solid angles)."""
    if len(points) > chunk:
        pieces = [_winding_numbers(points[i:i + chunk], vertices, faces) for i in range(0, len(points), chunk)]
        return np.concatenate(pieces)
    tri = vertices[faces][None] - points[:, None, None, :]  # [P, F, 3, 3]
    a, b, c = tri[:, :, 0], tri[:, :, 1], tri[:, :, 2]
    la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
    det = np.einsum("pfi,pfi->pf", a, np.cross(b, c))
    den = la * lb * lc + np.einsum("pfi,pfi->pf", a, b) * lc + np.einsum("pfi,pfi->pf", b, c) * la \
        + np.einsum("pfi,pfi->pf", c, a) * lb
    return (2 * np.arctan2(det, den)).sum(1) / (4 * np.pi)


def test_pseudo_centre_of_an_exact_circle_and_reflections():
    rng = np.random.default_rng(0)
    centre, radius = np.array([0.003, -0.01]), 0.03
    angles = np.sort(rng.uniform(np.pi / 5, 4 * np.pi / 5, 15))[::-1]  # uneven spacing, front arc
    front = centre + radius * np.stack([np.cos(angles), np.sin(angles)], 1)
    c = pseudo_centre(front[0], front[1], front[13], front[14])
    np.testing.assert_allclose(c, centre, atol=1e-12)
    trajectory, c2, source = molar_trajectory(front)
    assert trajectory.shape == (25, 2) and source.tolist() == [0] * 5 + list(range(15)) + [14] * 5
    np.testing.assert_allclose(np.linalg.norm(trajectory - centre, axis=1), radius, rtol=1e-12)
    # The reflection of T1 across C-T0 lies beyond T0: the angle keeps decreasing along the trajectory.
    ang = np.unwrap(np.arctan2(*(trajectory - centre).T[::-1]))
    assert np.all(np.diff(ang) < 0)
    # flattened corners (end segments along x, as OpenHead's): the bisectors are parallel, the circle fit is used
    flat_ends = front.copy()
    flat_ends[0, 1], flat_ends[14, 1] = flat_ends[1, 1], flat_ends[13, 1]
    flat_ends[0, 0], flat_ends[14, 0] = flat_ends[1, 0] - 0.004, flat_ends[13, 0] + 0.004
    c_fit, method = trajectory_centre(flat_ends, max_radius=0.1)
    assert method == "least_squares_circle" and c_fit[1] < flat_ends[:, 1].min()
    # reflecting twice is the identity; the line's own points stay
    p = rng.normal(size=(6, 2))
    np.testing.assert_allclose(reflect_points(reflect_points(p, c, front[0]), c, front[0]), p, atol=1e-12)
    np.testing.assert_allclose(reflect_points(front[:1], c, front[0]), front[:1], atol=1e-15)


def test_molar_points_lie_on_the_pseudo_circle(head):
    """Reflection across a line through C keeps |p - C| exactly (float64 rounding only, rtol 1e-12);
    R(T1) is at |C - T0| because C lies on the bisector of T0T1. The lip ring itself must be close
    to a circle for the extension to continue it smoothly: radii within 10% (the paper's assumption)."""
    front, line = _front_teeth_trajectory(head)
    centre, method = trajectory_centre(front, MouthConfig().max_centre_distance * line.width)
    trajectory, centre, _ = molar_trajectory(front, centre)
    r_front = np.linalg.norm(front - centre, axis=1)
    r_traj = np.linalg.norm(trajectory - centre, axis=1)
    np.testing.assert_allclose(r_traj[:5], r_front[5:0:-1], rtol=1e-12)
    np.testing.assert_allclose(r_traj[20:], r_front[13:8:-1], rtol=1e-12)
    if method == "bisectors":  # C on the bisector of T0T1: R(T1) on the circle through T0 and T1
        np.testing.assert_allclose(r_traj[4], r_front[0], rtol=1e-12)
        np.testing.assert_allclose(r_traj[20], r_front[14], rtol=1e-12)
        np.testing.assert_allclose(r_front[0], r_front[1], rtol=1e-12)
    assert r_front.std() / r_front.mean() < 0.10
    # the molars lie further back (smaller z) than the mouth corners and wider out
    assert trajectory[0, 1] < front[0, 1] and trajectory[-1, 1] < front[-1, 1]
    assert trajectory[0, 0] < front[0, 0] and trajectory[-1, 0] > front[-1, 0]


def test_palate_and_floor_sit_behind_the_teeth_and_inside_the_head(head, mouthed):
    v = mouthed.v_template.astype(np.float64)
    groups = mouthed.vertex_groups
    n_teeth_ring = 25
    upper_front = groups["teeth_upper"][:n_teeth_ring]
    palate_inner = groups["palate"][n_teeth_ring:]  # without the ring shared with the teeth
    floor_inner = groups["floor"][n_teeth_ring:]
    assert v[palate_inner, 2].max() < v[upper_front, 2].max()
    assert v[floor_inner, 2].max() < v[upper_front, 2].max()
    # the palate apex is behind every front-teeth point, the floor below the palate
    assert v[palate_inner[-1], 2] < v[upper_front, 2].min()
    assert v[floor_inner, 1].max() < v[palate_inner, 1].min()
    # behind the lips: every mouth vertex has smaller z than the lip ring's front-most point
    rings = np.concatenate([head.lip_ring_upper, head.lip_ring_lower])
    added = np.arange(head.num_vertices, mouthed.num_vertices)
    assert v[added, 2].max() < v[rings, 2].max()
    # inside the head surface: generalised winding number ~1 (0.5 tolerates the open mouth slit)
    probe = np.unique(np.concatenate([added[::5], added[-1:], mouthed.vertex_groups["palate"][-1:]]))  # incl. apexes
    winding = _winding_numbers(v[probe], head.v_template.astype(np.float64), head.faces)
    assert winding.min() > 0.5, winding.min()


def test_teeth_are_tooth_sized(mouthed):
    v = mouthed.v_template
    up = mouthed.vertex_groups["teeth_upper"]
    height = v[up[:25], 1] - v[up[25:50], 1]  # root ring minus edge ring
    assert np.all((height > 0.006) & (height < 0.015)), height  # ~1 cm crowns
    width = mouthed.metadata["mouth"]["mouth_width"]
    assert 0.03 < width < 0.08


def _edges(faces):
    return np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])


def test_mouth_faces_are_valid_and_consistently_oriented(mouthed, head):
    v = mouthed.v_template.astype(np.float64)
    for part in ("mouth_upper", "mouth_lower"):
        faces = mouthed.faces[mouthed.face_groups[part]]
        assert faces.min() >= head.num_vertices  # only appended vertices
        area = 0.5 * np.linalg.norm(np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]]), axis=1)
        assert area.min() > 1e-9, area.min()  # > 1 mm^2 / 1000: no slivers
        assert len(np.unique(np.sort(faces, 1), axis=0)) == len(faces)  # no duplicate triangles
        directed = _edges(faces)
        assert len(np.unique(directed, axis=0)) == len(directed)  # each directed edge once: consistent winding
        undirected, counts = np.unique(np.sort(directed, 1), axis=0, return_counts=True)
        assert counts.max() <= 2  # manifold
    normals = np.cross(v[mouthed.faces[:, 1]] - v[mouthed.faces[:, 0]], v[mouthed.faces[:, 2]] - v[mouthed.faces[:, 0]])
    # visible sides face the mouth cavity: palate down, floor up
    palate = set(mouthed.vertex_groups["palate"][25:].tolist())
    floor = set(mouthed.vertex_groups["floor"][25:].tolist())
    for group, sign in ((palate, -1), (floor, 1)):
        ids = [f for f in mouthed.face_groups["mouth"] if set(mouthed.faces[f].tolist()) <= group]
        assert len(ids) > 0 and np.all(sign * normals[ids, 1] > 0)
    # the front of the upper teeth at the middle column faces forward
    up = mouthed.vertex_groups["teeth_upper"]
    quad = {up[12], up[13], up[37], up[38]}  # root and edge rings, middle columns
    front_mid = [f for f in mouthed.face_groups["mouth_upper"] if set(mouthed.faces[f].tolist()) <= quad]
    assert len(front_mid) == 2 and np.all(normals[front_mid, 2] > 0)


def test_groups_skinning_and_blend_shapes(head, mouthed):
    added = np.arange(head.num_vertices, mouthed.num_vertices)
    upper, lower = mouthed.vertex_groups["mouth_upper"], mouthed.vertex_groups["mouth_lower"]
    np.testing.assert_array_equal(np.sort(np.concatenate([upper, lower])), added)
    faces_up, faces_lo = mouthed.face_groups["mouth_upper"], mouthed.face_groups["mouth_lower"]
    np.testing.assert_array_equal(np.sort(np.concatenate([faces_up, faces_lo])), mouthed.face_groups["mouth"])
    assert set(mouthed.faces[faces_up].ravel()) <= set(upper) and set(mouthed.faces[faces_lo].ravel()) <= set(lower)
    np.testing.assert_array_equal(mouthed.lbs_weights[upper], np.eye(5)[[1] * len(upper)])  # neck joint
    np.testing.assert_array_equal(mouthed.lbs_weights[lower], np.eye(5)[[2] * len(lower)])  # jaw joint
    assert not mouthed.j_regressor[:, added].any() and not mouthed.exprdirs[added].any()
    assert mouthed.posedirs is None or not mouthed.posedirs[added].any()
    # identity: a front-teeth column copies the mean basis of its lip-ring column
    line = mouth_line(head)
    up = mouthed.vertex_groups["teeth_upper"]
    np.testing.assert_allclose(mouthed.shapedirs[up[5 + 7]], line.shapedirs[7], rtol=1e-6)
    np.testing.assert_allclose(mouthed.shapedirs[up[0]], line.shapedirs[0], rtol=1e-6)  # molar: corner column
    # the original arrays are untouched
    np.testing.assert_array_equal(mouthed.v_template[: head.num_vertices], head.v_template)
    np.testing.assert_array_equal(mouthed.faces[: len(head.faces)], head.faces)


def test_jaw_moves_the_lower_part_rigidly_and_not_the_upper(mouthed):
    head = HeadModel(mouthed)
    params = head.zero_params(1)
    params["jaw_pose"] = torch.tensor([[0.35, 0.05, 0.0]])
    rest = head.template_output()
    posed = head.forward_params(params)
    upper = torch.as_tensor(mouthed.vertex_groups["mouth_upper"])
    lower = torch.as_tensor(mouthed.vertex_groups["mouth_lower"])
    assert torch.allclose(posed.vertices[0, upper], rest.vertices[0, upper], atol=1e-6)
    moved = (posed.vertices[0, lower] - rest.vertices[0, lower]).norm(dim=-1)
    assert moved.min() > 1e-3
    # rigid: the lower part is the rest lower part rotated about the jaw joint
    from geoavatar.geometry import axis_angle_to_matrix

    rot = axis_angle_to_matrix(params["jaw_pose"][0])
    joint = rest.joints[0, 2]
    expected = (rest.vertices[0, lower] - joint) @ rot.T + joint
    assert torch.allclose(posed.vertices[0, lower], expected, atol=1e-5)


def test_forward_with_mouth_shapes_and_gradients(head, mouthed):
    model = HeadModel(mouthed)
    params = {k: (v + 0.05).requires_grad_() for k, v in model.zero_params(2).items()}
    params["static_offset"] = torch.zeros(1, head.num_vertices, 3, requires_grad=True)  # written for the bare head
    out = model.forward_params(params)
    assert out.vertices.shape == (2, mouthed.num_vertices, 3)
    added = torch.arange(head.num_vertices, mouthed.num_vertices)
    out.vertices[:, added].square().sum().backward()
    assert params["shape"].grad.abs().sum() > 0  # identity moves the mouth
    assert params["jaw_pose"].grad.abs().sum() > 0 and params["neck_pose"].grad.abs().sum() > 0
    assert params["expr"].grad.abs().sum() > 0  # only through the joints (expression moves the jaw joint)
    # no expression blend shapes on the rigid parts: at zero pose the expression cannot move them
    expr = torch.zeros(1, model.num_expr, requires_grad=True)
    zero = model.zero_params(1)
    pose = (zero[k] for k in ("rotation", "neck_pose", "jaw_pose", "eyes_pose", "translation"))
    still = model(zero["shape"], expr, *pose)
    still.vertices[0, added].sum().backward()
    assert expr.grad.abs().sum() == 0


def test_gaussianavatars_kind_is_frontal_teeth_only():
    head = procedural_head()
    ga = add_mouth_structure(head, "gaussianavatars")
    geo = add_mouth_structure(head, "geoavatar")
    assert ga.num_vertices - head.num_vertices == 120 and len(ga.face_groups["mouth"]) == 168
    assert geo.num_vertices - head.num_vertices > 120
    assert "palate" not in ga.vertex_groups and "floor" not in ga.vertex_groups
    added = np.arange(head.num_vertices, ga.num_vertices)
    x = ga.v_template[added, 0]
    ring_x = head.v_template[head.lip_ring_upper, 0]
    assert x.min() >= ring_x.min() - 1e-7 and x.max() <= ring_x.max() + 1e-7  # no molars
    # jaw skinning as in GaussianAvatars
    assert (ga.lbs_weights[ga.vertex_groups["mouth_lower"], 2] == 1).all()
    valid = ga.faces[ga.face_groups["mouth"]]
    assert len(np.unique(np.sort(valid, 1), axis=0)) == len(valid)


def test_none_kind_and_errors():
    head = procedural_head()
    assert add_mouth_structure(head, "none") is head
    with pytest.raises(ValueError, match="lip rings"):
        add_mouth_structure(head.copy_with(lip_ring_upper=None), "geoavatar")
    with pytest.raises(ValueError, match="already"):
        add_mouth_structure(add_mouth_structure(head, "geoavatar"), "geoavatar")
    with pytest.raises(ValueError, match="unknown mouth"):
        add_mouth_structure(head, "tongue")
    with pytest.raises(ValueError, match="increasing x"):
        add_mouth_structure(head.copy_with(lip_ring_upper=head.lip_ring_upper[::-1].copy()), "geoavatar")
    # a straight lip line: the bisectors of its ends are parallel, no pseudo-centre
    flat = head.v_template.copy()
    rings = np.concatenate([head.lip_ring_upper, head.lip_ring_lower])
    flat[rings, 2] = flat[rings, 2].max()
    with pytest.raises(ValueError, match="straight"):
        add_mouth_structure(head.copy_with(v_template=flat), "geoavatar")
