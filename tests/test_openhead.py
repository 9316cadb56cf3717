"""OpenHead: the generated head model (geometry, rig, modes, regions, lip rings, landmarks, cache)."""

import time
from collections import defaultdict

import numpy as np
import pytest
import torch

from geoavatar.head import JOINT_NAMES, REGION_NAMES, HeadModel, load_head_model
from geoavatar.head import landmarks_mediapipe as mp
from geoavatar.head.base import PARENTS
from geoavatar.head.openhead import build_openhead, cache_path, generate_openhead


@pytest.fixture(scope="module")
def built():
    start = time.perf_counter()
    data = generate_openhead()
    seconds = time.perf_counter() - start
    print(f"\nOpenHead generated in {seconds:.2f} s")
    return data


@pytest.fixture(scope="module")
def head(built) -> HeadModel:
    return HeadModel(built)


def _boundary_loops(faces: np.ndarray) -> list[list[int]]:
    """Closed loops of edges used by exactly one face."""
    count = defaultdict(int)
    for tri in faces:
        for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])):
            count[(min(a, b), max(a, b))] += 1
    assert max(count.values()) == 2, "an edge is shared by more than two faces (non-manifold)"
    nbrs = defaultdict(list)
    for (a, b), c in count.items():
        if c == 1:
            nbrs[a].append(b)
            nbrs[b].append(a)
    assert all(len(n) == 2 for n in nbrs.values()), "boundary vertices must have exactly two boundary edges"
    loops, seen = [], set()
    for start in nbrs:
        if start in seen:
            continue
        loop, prev, cur = [start], None, start
        seen.add(start)
        while True:
            nxt = [n for n in nbrs[cur] if n != prev][0]
            if nxt == start:
                break
            loop.append(nxt)
            seen.add(nxt)
            prev, cur = cur, nxt
        loops.append(loop)
    return loops


def _params(head, batch=1, **changes):
    p = head.zero_params(batch)
    p.update(changes)
    return p


def test_zero_params_give_the_template(head):
    out = head.template_output()
    assert torch.allclose(out.vertices[0], head.v_template, atol=1e-6)


def test_size_proportions_and_axes(built):
    v = built.v_template
    assert built.num_vertices >= 3000
    skin = v[: built.regions["left_eyeball"].min()]
    height = skin[:, 1].max() - skin[skin[:, 2] > 0.05][:, 1].min()  # crown to chin
    assert 0.20 < height < 0.26
    assert 0.13 < skin[:, 0].max() - skin[:, 0].min() < 0.19  # with the ears
    nose = v[built.regions["nose"]]
    assert nose[:, 2].max() == pytest.approx(skin[:, 2].max())  # the nose points to +z
    assert v[built.regions["left_eyeball"]][:, 0].min() > 0  # left = +x
    assert built.metadata["source"] == "generated" and built.metadata["license"] == "Apache-2.0"
    assert len(built.metadata["shape_names"]) == built.shapedirs.shape[-1] >= 20
    assert len(built.metadata["expression_names"]) == built.exprdirs.shape[-1] >= 20


def test_closed_surface_apart_from_mouth_and_neck(built):
    loops = _boundary_loops(built.faces)
    assert len(loops) == 2
    loops.sort(key=len)
    mouth, neck = loops
    v = built.v_template
    ring = set(built.lip_ring_upper.tolist()) | set(built.lip_ring_lower.tolist())
    assert set(mouth) == ring and len(mouth) == 28  # 13 + 13 inner vertices and the 2 shared corners
    assert v[neck][:, 1].max() < -0.12  # the neck base


def test_no_degenerate_or_duplicate_faces(built):
    f = built.faces
    assert (f[:, 0] != f[:, 1]).all() and (f[:, 1] != f[:, 2]).all() and (f[:, 0] != f[:, 2]).all()
    assert len(np.unique(np.sort(f, axis=1), axis=0)) == len(f)
    tri = built.v_template[f].astype(np.float64)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=-1)
    assert area.min() > 1e-10
    # Outward orientation: positive enclosed volume of the skin.
    skin = f[(f < built.regions["left_eyeball"].min()).all(1)]
    t = built.v_template[skin].astype(np.float64)
    assert np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() > 0


def test_joints_and_weights(built):
    assert np.allclose(built.j_regressor.sum(1), 1.0, atol=1e-5)
    assert np.allclose(built.lbs_weights.sum(1), 1.0, atol=1e-5)
    assert (built.lbs_weights >= 0).all()
    joints = built.j_regressor @ built.v_template
    names = dict(zip(JOINT_NAMES, joints))
    assert PARENTS == (-1, 0, 1, 1, 1)
    assert names["root"][1] < names["neck"][1] < names["jaw"][1] + 0.05
    assert names["left_eye"][0] > 0 > names["right_eye"][0]
    for side in ("left_eyeball", "right_eyeball"):
        j = 3 if side == "left_eyeball" else 4
        assert np.allclose(built.lbs_weights[built.regions[side], j], 1.0)


def test_jaw_opens_the_mouth(head, built):
    rest = head.template_output().vertices[0]
    out = head.forward_params(_params(head, jaw_pose=torch.tensor([[0.3, 0.0, 0.0]]))).vertices[0]
    move = (out - rest).norm(dim=-1)
    assert move[torch.as_tensor(built.lip_ring_lower[5:10])].min() > 0.005
    chin = rest[:, 1] < rest[torch.as_tensor(built.lip_ring_lower), 1].min() - 0.02
    chin &= rest[:, 2] > 0.05
    assert move[chin].mean() > 0.01
    assert move[torch.as_tensor(built.regions["forehead"])].max() < 1e-6
    assert move[torch.as_tensor(built.lip_ring_upper[3:12])].max() < 1e-3  # the upper lip stays
    # Opening: the lower lip goes down.
    assert (out[built.lip_ring_lower[7], 1] - rest[built.lip_ring_lower[7], 1]) < -0.005


def test_neck_turns_the_head_rigidly(head, built):
    rest = head.template_output().vertices[0]
    out = head.forward_params(_params(head, neck_pose=torch.tensor([[0.1, 0.5, 0.05]]))).vertices[0]
    rigid = torch.as_tensor(built.lbs_weights[:, 0] < 1e-6)
    ids = torch.nonzero(rigid)[:, 0][::37]
    d_rest = (rest[ids, None] - rest[None, ids]).norm(dim=-1)
    d_out = (out[ids, None] - out[None, ids]).norm(dim=-1)
    assert torch.allclose(d_rest, d_out, atol=1e-5)
    assert (out[rigid] - rest[rigid]).norm(dim=-1).mean() > 0.01
    base = torch.as_tensor(built.lbs_weights[:, 0] > 0.999)
    assert base.any() and (out[base] - rest[base]).norm(dim=-1).max() < 2e-4


def test_eyes_rotate_the_eyeballs(head, built):
    rest = head.template_output().vertices[0]
    out = head.forward_params(_params(head, eyes_pose=torch.tensor([[0.0, 0.3, 0.0, 0.0, -0.3, 0.0]]))).vertices[0]
    left, right = (torch.as_tensor(built.regions[n]) for n in ("left_eyeball", "right_eyeball"))
    front_left = left[rest[left, 2].argmax()]
    assert out[front_left, 0] - rest[front_left, 0] > 0.002  # looks to the subject's left
    front_right = right[rest[right, 2].argmax()]
    assert out[front_right, 0] - rest[front_right, 0] < -0.002
    others = torch.ones(len(rest), dtype=torch.bool)
    others[left] = False
    others[right] = False
    assert (out[others] - rest[others]).norm(dim=-1).max() < 1e-6
    # Rotation about the centre: distances to the eye joint are kept.
    centre = head.template_output().joints[0, 3]
    assert torch.allclose((out[left] - centre).norm(dim=-1), (rest[left] - centre).norm(dim=-1), atol=1e-6)


def test_batched_and_unbatched_agree(head):
    g = torch.Generator().manual_seed(0)
    p = {k: torch.randn(v.shape, generator=g) * 0.2 for k, v in head.zero_params(3).items()}
    p["shape"] = torch.randn(300, generator=g)
    p["expr"] = torch.randn(3, 100, generator=g) * 0.5
    batched = head.forward_params(p)
    for i in range(3):
        single = head(p["shape"], p["expr"][i], p["rotation"][i], p["neck_pose"][i], p["jaw_pose"][i],
                      p["eyes_pose"][i], p["translation"][i])
        assert torch.allclose(single.vertices, batched.vertices[i], atol=1e-5)
        assert torch.allclose(single.landmarks, batched.landmarks[i], atol=1e-5)


def test_gradients_reach_every_parameter(head):
    p = {k: (v + 0.05).requires_grad_(True) for k, v in head.zero_params(2).items()}
    out = head.forward_params(p)
    (out.vertices.square().sum() + out.landmarks.sum()).backward()
    for name, value in p.items():
        assert value.grad is not None and value.grad.abs().sum() > 0, name
    # Every mode the model has gets a gradient.
    assert (p["shape"].grad[: head.num_shape].abs() > 0).all()
    assert (p["expr"].grad[:, : head.num_expr].abs() > 0).all()


def _mode_motion(built, kind: str, name: str) -> np.ndarray:
    names = built.metadata["shape_names" if kind == "shape" else "expression_names"]
    dirs = built.shapedirs if kind == "shape" else built.exprdirs
    return np.linalg.norm(dirs[:, :, names.index(name)], axis=-1)  # [V] metres per unit


@pytest.mark.parametrize(
    "name, region, other",
    [
        ("blink_left", "left_eye_region", "right_eye_region"),
        ("blink_right", "right_eye_region", "left_eye_region"),
        ("smile", "lips", "forehead"),
        ("lip_pucker", "lips", "eye_region"),
        ("brow_raise", "forehead", "lips"),
        ("nose_wrinkle", "nose", "neck"),
        ("mouth_left", "lips", "eye_region"),
        ("cheek_puff", "face", "scalp"),
    ],
)
def test_expression_moves_its_region(built, name, region, other):
    motion = _mode_motion(built, "expr", name)
    inside = motion[built.regions[region]].max()
    assert inside > 0.002  # a strong expression at 1.0
    assert inside > 5 * motion[built.regions[other]].mean()


def test_every_mode_is_local_smooth_and_nonzero(built):
    for kind, dirs in (("shape", built.shapedirs), ("expr", built.exprdirs)):
        mags = np.linalg.norm(dirs, axis=1).max(0)  # [modes]
        assert (mags > 5e-4).all() and (mags < 0.015).all(), (kind, mags)


def test_blink_closes_the_lids_over_the_eyeball(head, built):
    names = built.metadata["expression_names"]
    expr = torch.zeros(1, head.num_expr)
    expr[0, names.index("blink_left")] = 1.0
    out = head.forward_params(_params(head, expr=expr)).vertices[0].numpy()
    ball = built.v_template[built.regions["left_eyeball"]]
    centre = ball.mean(0)
    radius = np.linalg.norm(ball - centre, axis=-1).max()
    # Look at the eye from the front: every skin point of the eye region in front of the eyeball's
    # silhouette must now lie outside the eyeball (the lids cover it).
    skin_ids = built.regions["left_eye_region"]
    rel = out[skin_ids] - centre
    front = (np.hypot(rel[:, 0], rel[:, 1]) < 0.006) & (rel[:, 2] > 0)
    assert front.sum() >= 5
    assert (np.linalg.norm(rel[front], axis=-1) > radius).all()
    rel0 = built.v_template[skin_ids] - centre
    assert (np.linalg.norm(rel0[(np.hypot(rel0[:, 0], rel0[:, 1]) < 0.004) & (rel0[:, 2] > 0)], axis=-1) < radius).all()


def test_regions(built):
    assert set(built.regions) == set(REGION_NAMES) and len(REGION_NAMES) == 14
    v = built.v_template
    for name, ids in built.regions.items():
        assert len(ids) > 0, name
        assert ids.min() >= 0 and ids.max() < len(v)
    assert v[built.regions["left_eye_region"]][:, 0].min() > 0 > v[built.regions["right_eye_region"]][:, 0].max()
    assert v[built.regions["left_ear"]][:, 0].min() > 0.05
    assert v[built.regions["scalp"]][:, 1].mean() > v[built.regions["face"]][:, 1].mean()
    assert v[built.regions["neck"]][:, 1].mean() < v[built.regions["lips"]][:, 1].min()
    assert v[built.regions["forehead"]][:, 1].min() > v[built.regions["nose"]][:, 1].mean()


def test_lip_rings(built):
    v = built.v_template
    loops = _boundary_loops(built.faces)
    mouth = set(min(loops, key=len))
    for ring in (built.lip_ring_upper, built.lip_ring_lower):
        assert ring.shape == (15,)
        assert set(ring.tolist()) <= mouth
        assert (np.diff(v[ring, 0]) > 0).all()  # subject's right -> left
    assert built.lip_ring_upper[0] == built.lip_ring_lower[0] and built.lip_ring_upper[-1] == built.lip_ring_lower[-1]
    assert (v[built.lip_ring_upper[1:-1], 1] > v[built.lip_ring_lower[1:-1], 1]).all()


def test_landmarks(head, built):
    lm = head.template_output().landmarks[0].numpy()
    ids = built.landmark_ids.tolist()
    assert built.landmark_convention == "mediapipe478"
    assert len(set(ids)) == len(ids) and max(ids) < 478
    for group in ("lips_outer_upper", "lips_inner_lower", "left_eye_upper", "right_eye_lower", "left_brow_upper",
                  "nose_ridge", "face_oval", "left_iris", "right_iris"):
        assert set(mp.CONTOURS[group]) <= set(ids), group
    at = {i: lm[k] for k, i in enumerate(ids)}
    # On the surface: barycentric coordinates of real faces.
    assert np.allclose(built.landmark_bary.sum(1), 1.0, atol=1e-5) and (built.landmark_bary >= 0).all()
    assert max(at, key=lambda i: at[i][2]) == 1  # the nose tip is the most forward landmark
    for name in ("left_eye_upper", "left_eye_lower", "left_brow_upper", "left_iris"):
        assert all(at[i][0] > 0 for i in mp.CONTOURS[name])
    for name in ("right_eye_upper", "right_eye_lower", "right_brow_upper", "right_iris"):
        assert all(at[i][0] < 0 for i in mp.CONTOURS[name])
    for name in ("lips_outer_upper", "lips_inner_upper", "right_eye_upper", "left_eye_upper"):
        xs = [at[i][0] for i in mp.CONTOURS[name]]
        assert (np.diff(xs) > 0).all(), name
    # Inner-lip corners are the ring corners; mid-lip ids are on the mid-line.
    assert np.allclose(at[78], built.v_template[built.lip_ring_upper[0]], atol=1e-6)
    assert np.allclose(at[308], built.v_template[built.lip_ring_upper[-1]], atol=1e-6)
    for i in (0, 13, 14, 17, 1, 168, 152):
        assert abs(at[i][0]) < 1e-3, i
    assert at[0][1] > at[13][1] > at[14][1] > at[17][1] > at[152][1]
    assert at[10][1] > at[168][1] > at[1][1]
    # Human proportions: eye line to chin is 1.4-2.1x eye line to mouth line, and the chin (152) is on
    # the face, not on the neck below it (the reference map is fitted on the eyelids and lips).
    eye_y, mouth_y = 0.5 * (at[33][1] + at[263][1]), 0.5 * (at[61][1] + at[291][1])
    assert 1.4 < (eye_y - at[152][1]) / (eye_y - mouth_y) < 2.1
    chin_face = built.faces[built.landmark_faces[ids.index(152)]]
    assert np.isin(chin_face, built.regions["face"]).all() and not np.isin(chin_face, built.regions["neck"]).any()
    # Irises lie on the eyeballs.
    left_iris = [ids.index(i) for i in mp.LEFT_IRIS]
    assert np.isin(built.faces[built.landmark_faces[left_iris]], built.regions["left_eyeball"]).all()


def test_landmarks_follow_a_blink(head, built):
    names = built.metadata["expression_names"]
    expr = torch.zeros(1, head.num_expr)
    expr[0, names.index("blink_right")] = 1.0
    ids = built.landmark_ids.tolist()
    open_ = head.template_output().landmarks[0]
    closed = head.forward_params(_params(head, expr=expr)).landmarks[0]
    gap = lambda lm: (lm[ids.index(159), 1] - lm[ids.index(145), 1]).item()  # noqa: E731
    assert gap(open_) > 0.006 and abs(gap(closed)) < 0.002


def test_deterministic_and_cached(built, tmp_path, monkeypatch):
    again = generate_openhead()
    for name in ("v_template", "faces", "shapedirs", "exprdirs", "j_regressor", "lbs_weights", "landmark_bary"):
        assert np.array_equal(getattr(built, name), getattr(again, name)), name
    monkeypatch.setenv("GEOAVATAR_CACHE", str(tmp_path))
    first = build_openhead()
    path = cache_path()
    assert path.parent == tmp_path and path.is_file()
    cached = build_openhead()
    assert np.array_equal(cached.v_template, built.v_template)
    assert cached.metadata == built.metadata
    assert all(np.array_equal(cached.regions[k], first.regions[k]) for k in REGION_NAMES)
    path.write_bytes(b"not a zip file")  # a corrupt cache is rebuilt
    rebuilt = build_openhead()
    assert np.array_equal(rebuilt.faces, built.faces)
    with np.load(path, allow_pickle=False) as arrays:
        assert "v_template" in arrays.files


def test_load_head_model_serves_openhead():
    head = load_head_model("openhead")
    assert head.name == "openhead" and head.num_vertices >= 3000
