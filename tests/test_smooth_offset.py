"""Smooth static offsets (geoavatar.head.smooth_offset) on OpenHead: exact on the handles, smooth and
fading elsewhere, rigid eyeballs, and an energy that is the field's own."""

from __future__ import annotations

import numpy as np
import pytest

from geoavatar.head.smooth_offset import graph_laplacian, smooth_offset


@pytest.fixture(scope="module")
def head():
    from geoavatar.head import load_head_data

    return load_head_data("openhead")


@pytest.fixture(scope="module")
def nose_handles(head):
    v = head.v_template
    return np.nonzero(np.linalg.norm(v - v[np.argmax(v[:, 2])], axis=-1) < 0.01)[0]  # around the nose tip


def test_field_is_exact_on_handles_and_fades_away(head, nose_handles):
    offsets = smooth_offset(head, nose_handles)
    theta = np.zeros((offsets.num_free, 3))
    theta[: len(offsets.handles), 2] = 0.005  # push the nose 5 mm forward
    field = offsets.extend(theta)  # [V, 3]
    assert np.allclose(field[offsets.handles], theta[: len(offsets.handles)])
    distance = np.linalg.norm(head.v_template - head.v_template[nose_handles].mean(0), axis=-1)
    assert field[distance > 0.08, 2].max() < 0.1 * 0.005  # the back of the head and the neck stay put
    near = (distance > 0.012) & (distance < 0.02)
    assert 0.0 < field[near, 2].min() and field[near, 2].max() < 0.005  # in between: a smooth falloff
    for name in ("left_eyeball", "right_eyeball"):  # no eyeball handle: the eyes do not move
        assert np.abs(field[head.regions[name]]).max() < 1e-12


def test_eyeballs_move_rigidly(head):
    offsets = smooth_offset(head, np.zeros(0, np.int64))
    assert offsets.num_free == 2  # one translation per eyeball
    field = offsets.extend(np.array([[0.001, 0.002, 0.003], [0.0, 0.0, 0.0]]))
    left = field[head.regions["left_eyeball"]]
    assert np.allclose(left, [0.001, 0.002, 0.003])
    skin = np.setdiff1d(np.arange(head.num_vertices), np.r_[head.regions["left_eyeball"], head.regions["right_eyeball"]])
    assert np.abs(field[skin]).max() < 1e-12  # a component without handles keeps the eyeballs apart


def test_energy_and_joints_are_the_fields_own(head, nose_handles):
    decay = 0.05
    offsets = smooth_offset(head, nose_handles, decay=decay)
    theta = np.random.default_rng(0).normal(0.0, 0.003, (offsets.num_free, 3))
    field = offsets.extend(theta)
    faces = head.faces
    edges = np.unique(np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), 1), axis=0)
    free = np.ones(head.num_vertices, bool)
    free[offsets.handles] = False
    for name in ("left_eyeball", "right_eyeball"):
        free[head.regions[name]] = False
    explicit = ((field[edges[:, 0]] - field[edges[:, 1]]) ** 2).sum() + decay * (field[free] ** 2).sum()
    assert np.isclose(np.trace(theta.T @ offsets.energy @ theta), explicit, rtol=1e-6)
    assert np.allclose(offsets.at_joints @ theta, head.j_regressor @ field, atol=1e-12)
    # The extension minimises that energy: a perturbation of the free vertices only raises it.
    laplacian = graph_laplacian(head.num_vertices, faces)
    bumped = field.copy()
    bumped[np.nonzero(free)[0][:50]] += 1e-4
    energy = lambda d: ((d[edges[:, 0]] - d[edges[:, 1]]) ** 2).sum() + decay * (d[free] ** 2).sum()  # noqa: E731
    assert energy(bumped) > energy(field)
    assert np.allclose(laplacian @ np.ones(head.num_vertices), 0.0)  # rows of a Laplacian sum to zero


def test_bad_arguments_are_clear_errors(head):
    with pytest.raises(ValueError, match="decay must be positive"):
        smooth_offset(head, np.array([0]), decay=0.0)
    with pytest.raises(ValueError, match="handle ids must be in"):
        smooth_offset(head, np.array([head.num_vertices]))
