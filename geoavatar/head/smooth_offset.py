"""Smooth static offsets of a head mesh, driven by a few handle vertices.

A tracker that fits only landmarks sees the ~500 vertices under them (the handles); the person's
face differs from the head model's around them too, and a static offset (FLAME/VHAP's
`static_offset`) must be a smooth field over the mesh. The free values are the handles' offsets;
every other vertex takes the damped harmonic extension of them on the mesh graph:

    minimise  sum over edges |d_i - d_j|^2 + decay * sum over other vertices |d_i|^2,  d = theta on handles

i.e. (L_ff + decay I) d_f = -L_fk d_k (L: the uniform graph Laplacian). `decay` makes the field fade
to zero a few rings away from the handles (the back of the head, the neck) and keeps a mesh
component without a handle where it is. Eyeballs are rigid: each eyeball region takes one
translation, so iris landmarks move the whole eyeball.

The field is linear in theta [P, 3] (P = handles + eyeballs): offset = matrix @ theta, [V, P]
dense (a few MB), so a landmark-only tracker can use the rows of the vertices it needs and the
joint regressor's rows (`at_joints`) and reproduce the full model exactly. `energy` [P, P] is the
minimised objective above as a quadratic form of theta: the membrane energy a smoothness prior
penalises.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from geoavatar.head.base import HeadModelData

EYEBALL_REGIONS = ("left_eyeball", "right_eyeball")


def graph_laplacian(num_vertices: int, faces: np.ndarray) -> sp.csr_matrix:
    """Uniform graph Laplacian D - A [V, V] of the mesh's edges."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]], 0)  # [3F, 2]
    edges = np.unique(np.sort(edges, 1), axis=0)
    i, j = edges[:, 0], edges[:, 1]
    ones = np.ones(len(edges))
    adjacency = sp.coo_matrix((np.r_[ones, ones], (np.r_[i, j], np.r_[j, i])), shape=(num_vertices, num_vertices))
    adjacency = adjacency.tocsr()
    return (sp.diags(np.asarray(adjacency.sum(1)).ravel()) - adjacency).tocsr()


@dataclass
class SmoothOffset:
    """offset [V, 3] = matrix [V, P] @ theta [P, 3]; see the module doc."""

    matrix: np.ndarray  # [V, P]
    energy: np.ndarray  # [P, P]
    at_joints: np.ndarray  # [J, P]  j_regressor @ matrix
    handles: np.ndarray  # [H] handle vertex ids, eyeballs excluded (theta rows 0..H-1; the eyeballs follow)

    @property
    def num_free(self) -> int:
        return self.matrix.shape[1]

    def extend(self, theta: np.ndarray) -> np.ndarray:
        """[P, 3] -> the whole mesh's offset [V, 3]."""
        return self.matrix @ np.asarray(theta, np.float64)


def smooth_offset(data: HeadModelData, handles: np.ndarray, decay: float = 0.05) -> SmoothOffset:
    """The smooth static-offset map of `data` driven by `handles` (vertex ids) and its eyeballs."""
    num_v = data.num_vertices
    if decay <= 0:
        raise ValueError(f"smooth_offset: decay must be positive, got {decay}")
    handles = np.unique(np.asarray(handles, np.int64))
    if len(handles) and (handles.min() < 0 or handles.max() >= num_v):
        raise ValueError(f"smooth_offset: handle ids must be in [0, {num_v})")
    eyeball_of = np.full(num_v, -1, np.int64)
    eyeballs = [np.asarray(data.regions[name], np.int64) for name in EYEBALL_REGIONS if len(data.regions.get(name, ())) > 0]
    for k, ids in enumerate(eyeballs):
        eyeball_of[ids] = k
    handles = handles[eyeball_of[handles] < 0]
    eyeball_ids = np.nonzero(eyeball_of >= 0)[0]
    known = np.concatenate([handles, eyeball_ids])  # [K]
    num_free = len(handles) + len(eyeballs)
    expand = np.zeros((len(known), num_free))  # [K, P]
    expand[np.arange(len(handles)), np.arange(len(handles))] = 1.0
    expand[len(handles) + np.arange(len(eyeball_ids)), len(handles) + eyeball_of[eyeball_ids]] = 1.0

    laplacian = graph_laplacian(num_v, data.faces)
    is_known = np.zeros(num_v, bool)
    is_known[known] = True
    free = np.nonzero(~is_known)[0]
    matrix = np.zeros((num_v, num_free))
    matrix[known] = expand
    l_fk = laplacian[free][:, known]  # [F, K] sparse
    if len(free):
        solve = spla.factorized((laplacian[free][:, free] + decay * sp.identity(len(free))).tocsc())
        rhs = -(l_fk @ expand)  # [F, P]
        matrix[free] = np.stack([solve(np.ascontiguousarray(rhs[:, c])) for c in range(num_free)], 1)
    # Energy at the minimum: sum over edges |d_i - d_j|^2 + decay |d_f|^2 = d^T (L + decay P_f) d.
    damped = laplacian + sp.diags(np.where(is_known, 0.0, decay))
    energy = matrix.T @ (damped @ matrix)  # [P, P]
    at_joints = np.asarray(data.j_regressor, np.float64) @ matrix  # [J, P]
    return SmoothOffset(matrix, 0.5 * (energy + energy.T), at_joints, handles)


__all__ = ["SmoothOffset", "smooth_offset", "graph_laplacian", "EYEBALL_REGIONS"]
