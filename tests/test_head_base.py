"""LBS core of HeadModel on a small hand-made model (no generated or user-supplied asset needed)."""

import numpy as np
import pytest
import torch

from geoavatar.geometry import axis_angle_to_matrix, matrix_to_quaternion, quaternion_to_matrix
from geoavatar.head.base import HeadModel, HeadModelData


def toy_head() -> HeadModel:
    rng = np.random.default_rng(0)
    # A column of points: base (neck), middle (head), front-bottom (chin, on the jaw).
    v = np.array([[0, -0.1, 0], [0, 0.1, 0], [0, 0.2, 0.05], [0, -0.02, 0.08], [0.03, 0.0, 0.09], [-0.03, 0.05, 0.07]],
                 np.float32)
    faces = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]], np.int64)
    weights = np.zeros((6, 5), np.float32)
    weights[0, 0] = 1  # root
    weights[[1, 2, 5], 1] = 1  # neck/head
    weights[[3, 4], 2] = 1  # jaw
    jreg = np.zeros((5, 6), np.float32)
    jreg[0, 0] = 1
    jreg[1, 1] = 1
    jreg[2, [1, 3]] = 0.5
    jreg[3, 5] = 1
    jreg[4, 5] = 1
    data = HeadModelData(
        name="toy", v_template=v, faces=faces,
        shapedirs=rng.normal(size=(6, 3, 4)).astype(np.float32) * 0.01,
        exprdirs=rng.normal(size=(6, 3, 3)).astype(np.float32) * 0.01,
        j_regressor=jreg, lbs_weights=weights,
        posedirs=rng.normal(size=(6, 3, 36)).astype(np.float32) * 0.001,
        landmark_ids=np.array([7, 9]), landmark_faces=np.array([0, 2]),
        landmark_bary=np.array([[1 / 3] * 3, [0.2, 0.3, 0.5]], np.float32),
    )
    return HeadModel(data)


def test_zero_params_give_template():
    head = toy_head()
    out = head.template_output()
    assert torch.allclose(out.vertices[0], head.v_template, atol=1e-6)
    assert out.landmarks.shape == (1, 2, 3)


def test_jaw_rotation_moves_only_jaw_vertices():
    head = toy_head()
    head = HeadModel(head.data.copy_with(posedirs=None))  # correctives would move every vertex a little
    p = head.zero_params(1)
    p["jaw_pose"] = torch.tensor([[0.3, 0.0, 0.0]])
    out = head.forward_params(p).vertices[0]
    assert torch.allclose(out[[0, 1, 2, 5]], head.v_template[[0, 1, 2, 5]], atol=1e-6)
    assert (out[[3, 4]] - head.v_template[[3, 4]]).norm(dim=-1).min() > 1e-3


def test_batched_equals_unbatched_and_mode_padding():
    head = toy_head()
    g = torch.Generator().manual_seed(1)
    b = {k: torch.randn(v.shape, generator=g) * 0.2 for k, v in head.zero_params(3).items()}
    b["shape"] = torch.randn(300, generator=g)  # more modes than the model: leading ones are used
    batched = head.forward_params(b)
    for i in range(3):
        single = head(b["shape"], *(b[k][i] for k in ("expr", "rotation", "neck_pose", "jaw_pose", "eyes_pose", "translation")))
        assert torch.allclose(single.vertices, batched.vertices[i], atol=1e-5)
        assert torch.allclose(single.landmarks, batched.landmarks[i], atol=1e-5)


def test_gradients_reach_every_parameter():
    head = toy_head()
    p = {k: (v + 0.1).requires_grad_() for k, v in head.zero_params(2).items()}
    p["static_offset"] = torch.zeros(1, 6, 3, requires_grad=True)
    out = head.forward_params(p)
    (out.vertices.square().sum() + out.landmarks.sum()).backward()
    for k, v in p.items():
        assert v.grad is not None and v.grad.abs().sum() > 0, k


def test_invalid_arrays_are_named():
    head = toy_head()
    with pytest.raises(ValueError, match="lbs_weights"):
        HeadModel(head.data.copy_with(lbs_weights=np.zeros((5, 5), np.float32)))


def test_rotation_helpers_roundtrip():
    aa = torch.randn(64, 3, generator=torch.Generator().manual_seed(0))
    aa[0] = 0
    m = axis_angle_to_matrix(aa)
    assert torch.allclose(m @ m.transpose(-1, -2), torch.eye(3).expand(64, 3, 3), atol=1e-5)
    assert torch.allclose(quaternion_to_matrix(matrix_to_quaternion(m)), m, atol=1e-5)
