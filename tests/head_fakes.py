"""Hand-made head models for the head-layer tests (no FLAME, no generated asset needed).

- `procedural_head()`: an ellipsoid head (lat-long grid, outward faces) with a mouth slit whose
  two edges are the lip rings, two eyeball spheres, the 14 FLAME region names defined by position
  (overlapping, and leaving a band of faces in no region), 5-joint skinning, smooth blend shapes.
- `write_fake_flame()`: the same head written as FLAME pickles (keys and types of generic_model.pkl:
  chumpy `Ch` shapedirs with 300 + 100 modes, scipy.sparse csc J_regressor, protocol 2), plus
  FLAME_masks.pkl. With num_vertices=5023 the vertices are renumbered so that the lip rings sit at
  FLAME's inner-lip-ring ids, and padded with unreferenced vertices up to 5023.
"""

from __future__ import annotations

import pickle
import sys
import types
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from geoavatar.head.base import HeadModelData
from geoavatar.head.flame import FLAME_LIP_RING_LOWER, FLAME_LIP_RING_UPPER, MASKS_FILE, MODEL_FILES

RADII = np.array([0.075, 0.105, 0.095])  # x, y, z semi-axes in metres
MOUTH_Y = -0.35  # mouth height, as a fraction of the y radius
MOUTH_HALF_ANGLE = 0.36  # longitude half-span of the mouth (w ~ 5 cm)
SLIT_OPENING = 0.002  # each lip ring moves this far from the mouth line at the middle


def _ellipsoid(theta, phi):
    """Points on the ellipsoid for longitude theta (0 = front, +z) and latitude phi."""
    return np.stack([RADII[0] * np.cos(phi) * np.sin(theta), RADII[1] * np.sin(phi),
                     RADII[2] * np.cos(phi) * np.cos(theta)], -1)


def _uv_sphere(centre, radius, n_lat=6, n_long=10):
    """Closed outward-facing sphere: vertices [n_lat*n_long + 2, 3], faces."""
    phi = np.linspace(-np.pi / 2, np.pi / 2, n_lat + 2)[1:-1]
    theta = np.linspace(0, 2 * np.pi, n_long, endpoint=False)
    p, t = np.meshgrid(phi, theta, indexing="ij")
    grid = np.stack([np.cos(p) * np.sin(t), np.sin(p), np.cos(p) * np.cos(t)], -1).reshape(-1, 3)
    verts = np.concatenate([grid, [[0, -1, 0], [0, 1, 0]]]) * radius + centre
    faces = _grid_faces(n_lat, n_long, np.arange(n_lat * n_long).reshape(n_lat, n_long), n_lat * n_long,
                        n_lat * n_long + 1)
    return verts, faces


def _grid_faces(n_lat, n_long, ids, south, north, upper_ids=None):
    """Faces of a lat-long grid (rows ascending in y, columns cyclic in longitude), outward normals.

    upper_ids: optional replacement ids for row faces *above* a row (the slit duplicates).
    """
    faces = []
    for j in range(n_lat - 1):
        for k in range(n_long):
            k1 = (k + 1) % n_long
            below = ids[j]
            above = ids[j + 1]
            lo_k, lo_k1 = below[k], below[k1]
            if upper_ids is not None:  # the row-j vertices as seen from the band above row j
                lo_k, lo_k1 = upper_ids.get((j, k), lo_k), upper_ids.get((j, k1), lo_k1)
            faces += [[lo_k, lo_k1, above[k1]], [lo_k, above[k1], above[k]]]
    for k in range(n_long):
        k1 = (k + 1) % n_long
        faces.append([south, ids[0][k1], ids[0][k]])
        faces.append([north, ids[-1][k], ids[-1][k1]])
    faces = np.asarray(faces, np.int64)
    return faces


def _orient_outward(verts, faces, centre):
    n = np.cross(verts[faces[:, 1]] - verts[faces[:, 0]], verts[faces[:, 2]] - verts[faces[:, 0]])
    out = (n * (verts[faces].mean(1) - centre)).sum(-1) < 0
    faces = faces.copy()
    faces[out] = faces[out][:, ::-1]
    return faces


def procedural_head(n_lat: int = 24, n_rest: int = 34, shape_modes: int = 8, expr_modes: int = 4,
                    seed: int = 0) -> HeadModelData:
    """A small head (~1k vertices) with a mouth slit, lip rings, regions and 5-joint skinning."""
    rng = np.random.default_rng(seed)
    phi = np.linspace(-np.pi / 2, np.pi / 2, n_lat + 2)[1:-1]
    m = int(np.argmin(np.abs(np.sin(phi) - MOUTH_Y)))
    phi[m] = np.arcsin(MOUTH_Y)
    front = np.linspace(-MOUTH_HALF_ANGLE, MOUTH_HALF_ANGLE, 15)
    rest = np.linspace(MOUTH_HALF_ANGLE, 2 * np.pi - MOUTH_HALF_ANGLE, n_rest + 2)[1:-1]
    theta = np.concatenate([front, rest])  # the 15 mouth columns are 0..14
    n_long = len(theta)
    p, t = np.meshgrid(phi, theta, indexing="ij")
    verts = _ellipsoid(t, p).reshape(-1, 3)
    ids = np.arange(n_lat * n_long).reshape(n_lat, n_long)
    south, north = len(verts), len(verts) + 1
    verts = np.concatenate([verts, [[0, -RADII[1], 0], [0, RADII[1], 0]]])

    # Mouth slit: the mouth-row vertices of the 15 columns get an upper copy used by the faces above.
    lower_ring = ids[m, :15].copy()
    upper_ring = np.arange(len(verts), len(verts) + 15)
    profile = 0.1 + 0.9 * np.sin(np.pi * np.arange(15) / 14)  # open in the middle, nearly shut at the corners
    upper_pos = verts[lower_ring] + np.array([0, SLIT_OPENING, 0]) * profile[:, None]
    verts[lower_ring] -= np.array([0, SLIT_OPENING, 0]) * profile[:, None]
    verts = np.concatenate([verts, upper_pos])
    upper_ids = {(m, k): upper_ring[k] for k in range(15)}
    faces = _grid_faces(n_lat, n_long, ids, south, north, upper_ids)
    faces = _orient_outward(verts, faces, np.zeros(3))
    num_head = len(verts)

    # Eyeballs: closed spheres partly sunk into the head.
    eye_ids = {}
    for name, sx in (("left_eyeball", 1), ("right_eyeball", -1)):
        c = np.array([sx * 0.032, 0.016, 0.077])
        ev, ef = _uv_sphere(c, 0.012)
        eye_ids[name] = np.arange(len(verts), len(verts) + len(ev))
        faces = np.concatenate([faces, ef + len(verts)])
        verts = np.concatenate([verts, ev])
    num_v = len(verts)

    # Regions by position (normalised head coordinates), overlapping like FLAME's.
    X, Y, Z = (verts[:num_head] / RADII).T
    head_ids = np.arange(num_head)
    sel = lambda mask: head_ids[mask]  # noqa: E731
    eye = (Z > 0.5) & (Y > -0.05) & (Y < 0.4) & (np.abs(X) < 0.75)
    regions = {
        "face": sel((Z > 0.35) & (Y < 0.6) & (Y > -0.75)),
        "forehead": sel((Z > 0.3) & (Y > 0.35) & (Y < 0.75)),
        "scalp": sel((Y > 0.45) | ((Z < 0.35) & (Y > -0.45))),
        "eye_region": sel(eye),
        "left_eye_region": sel(eye & (X > 0.05)),
        "right_eye_region": sel(eye & (X < -0.05)),
        "nose": sel((np.abs(X) < 0.22) & (Y > -0.3) & (Y < 0.1) & (Z > 0.6)),
        "lips": sel((np.abs(X) < 0.5) & (Y > -0.55) & (Y < -0.15) & (Z > 0.5)),
        "left_ear": sel((X > 0.85) & (np.abs(Y) < 0.25)),
        "right_ear": sel((X < -0.85) & (np.abs(Y) < 0.25)),
        "neck": sel(Y < -0.6),
        "boundary": sel(Y < -0.85),
        **eye_ids,
    }

    # Skinning: root at the bottom, jaw below the mouth at the front, eyes, neck (head) elsewhere.
    weights = np.zeros((num_v, 5), np.float32)
    weights[:num_head, 1] = 1
    jaw = (Y < MOUTH_Y - 1e-6) & (Y > -0.8) & (Z > 0.3)
    jaw[upper_ring] = False
    jaw[lower_ring] = True
    weights[:num_head][jaw] = [0, 0, 1, 0, 0]
    weights[:num_head][Y < -0.9] = [1, 0, 0, 0, 0]
    weights[eye_ids["left_eyeball"]] = [0, 0, 0, 1, 0]
    weights[eye_ids["right_eyeball"]] = [0, 0, 0, 0, 1]

    j_reg = np.zeros((5, num_v), np.float32)
    j_reg[0, south] = 1
    neck_row = ids[int(np.argmin(np.abs(np.sin(phi) + 0.7)))]
    j_reg[1, neck_row] = 1 / len(neck_row)
    side = ids[m + 1, [15 + n_rest // 4, 15 + 3 * n_rest // 4]]  # left and right of the head at mouth height
    j_reg[2, side] = 0.5
    j_reg[3, eye_ids["left_eyeball"]] = 1 / len(eye_ids["left_eyeball"])
    j_reg[4, eye_ids["right_eyeball"]] = 1 / len(eye_ids["right_eyeball"])

    # Smooth blend shapes: affine fields for identity, bumps around the mouth for expression.
    shapedirs = np.einsum("kab,vb->vak", rng.normal(size=(shape_modes, 3, 3)) * 0.05, verts).astype(np.float32)
    bump = np.exp(-((verts - np.array([0, MOUTH_Y * RADII[1], RADII[2]])) ** 2).sum(-1) / 0.03 ** 2)
    exprdirs = (bump[:, None, None] * rng.normal(size=(1, 3, expr_modes)) * 0.01).astype(np.float32)
    posedirs = (rng.normal(size=(num_v, 3, 36)) * 1e-4).astype(np.float32)

    return HeadModelData(
        name="procedural", v_template=verts.astype(np.float32), faces=faces, shapedirs=shapedirs,
        exprdirs=exprdirs, j_regressor=j_reg, lbs_weights=weights, posedirs=posedirs,
        regions={k: np.asarray(v, np.int64) for k, v in regions.items()},
        lip_ring_upper=upper_ring.astype(np.int64), lip_ring_lower=lower_ring.astype(np.int64),
        metadata={"num_head_vertices": num_head},
    ).validate()


def renumber_to_flame(data: HeadModelData, num_vertices: int = 5023) -> HeadModelData:
    """Pad with unreferenced vertices to `num_vertices` and renumber so the lip rings get FLAME's ids.

    FLAME's lists run from the subject's left corner to the right (assumed, as in GaussianAvatars'
    left_half), so our increasing-x ring maps onto the reversed list.
    """
    pad = num_vertices - data.num_vertices
    assert pad >= 0
    centre = data.v_template.mean(0, keepdims=True)
    old_targets = np.concatenate([data.lip_ring_upper, data.lip_ring_lower])
    new_targets = np.concatenate([np.asarray(FLAME_LIP_RING_UPPER)[::-1], np.asarray(FLAME_LIP_RING_LOWER)[::-1]])
    new_of_old = np.full(num_vertices, -1, np.int64)
    new_of_old[old_targets] = new_targets
    free = np.setdiff1d(np.arange(num_vertices), new_targets)
    new_of_old[new_of_old < 0] = free
    v = np.concatenate([data.v_template, np.repeat(centre, pad, 0)])
    out = np.empty_like(v)
    out[new_of_old] = v

    def move(a):  # per-vertex array [V, ...] -> padded and renumbered
        a = np.concatenate([a, np.zeros((pad, *a.shape[1:]), a.dtype)])
        b = np.empty_like(a)
        b[new_of_old] = a
        return b

    weights = move(data.lbs_weights)
    weights[new_of_old[data.num_vertices:], 1] = 1  # padding vertices follow the head
    j_reg = np.zeros((5, num_vertices), np.float32)
    j_reg[:, new_of_old[: data.num_vertices]] = data.j_regressor
    return data.copy_with(
        v_template=out, faces=new_of_old[data.faces], shapedirs=move(data.shapedirs), exprdirs=move(data.exprdirs),
        j_regressor=j_reg, lbs_weights=weights, posedirs=move(data.posedirs),
        regions={k: new_of_old[v] for k, v in data.regions.items()},
        lip_ring_upper=new_of_old[data.lip_ring_upper], lip_ring_lower=new_of_old[data.lip_ring_lower],
    ).validate()


@contextmanager
def fake_chumpy():
    """A module `chumpy.ch` with a class `Ch` that pickles like chumpy's (state dict with 'x')."""

    class Ch:
        def __init__(self, x):
            self.x = np.asarray(x)

        def __getstate__(self):  # chumpy drops its weak dicts and keeps these
            return {"x": self.x, "_dirty_vars": set(), "_itr": None, "_depends_on_deps": {},
                    "_make_dense": False, "_make_sparse": False}

    Ch.__module__, Ch.__qualname__ = "chumpy.ch", "Ch"
    chumpy, chumpy_ch = types.ModuleType("chumpy"), types.ModuleType("chumpy.ch")
    chumpy_ch.Ch = Ch
    chumpy.ch = chumpy_ch
    saved = {k: sys.modules.get(k) for k in ("chumpy", "chumpy.ch")}
    sys.modules.update({"chumpy": chumpy, "chumpy.ch": chumpy_ch})
    try:
        yield Ch
    finally:
        for k, v in saved.items():
            if v is None:
                sys.modules.pop(k, None)
            else:
                sys.modules[k] = v


def flame_pickle_dicts(data: HeadModelData, Ch) -> tuple[dict, dict]:
    """A FLAME-layout model dict (300 + 100 modes) and masks dict from HeadModelData."""
    v = data.num_vertices
    dirs = np.zeros((v, 3, 400), np.float32)
    dirs[:, :, : data.shapedirs.shape[2]] = data.shapedirs
    dirs[:, :, 300: 300 + data.exprdirs.shape[2]] = data.exprdirs
    model = {
        "v_template": data.v_template.astype(np.float64),
        "f": data.faces.astype(np.uint32),
        "shapedirs": Ch(dirs),
        "posedirs": data.posedirs.astype(np.float64),
        "J_regressor": sp.csc_matrix(data.j_regressor.astype(np.float64)),
        "weights": data.lbs_weights.astype(np.float64),
        "kintree_table": np.array([[4294967295, 0, 1, 1, 1], [0, 1, 2, 3, 4]], np.int64),
        "J": (data.j_regressor @ data.v_template).astype(np.float64),  # extras are ignored by the loader
        "bs_style": "lbs",
        "bs_type": "lrotmin",
    }
    masks = {k: np.asarray(ids, np.int64) for k, ids in data.regions.items()}
    return model, masks


def write_fake_flame(folder: Path, data: HeadModelData, version: str = "2023", masks_extra: dict | None = None,
                     write_masks: bool = True) -> Path:
    """Write `data` as FLAME pickles (protocol 2, chumpy Ch shapedirs) into `folder`."""
    folder.mkdir(parents=True, exist_ok=True)
    with fake_chumpy() as Ch:
        model, masks = flame_pickle_dicts(data, Ch)
        (folder / MODEL_FILES[version]).write_bytes(pickle.dumps(model, protocol=2))
    if write_masks:
        (folder / MASKS_FILE).write_bytes(pickle.dumps({**masks, **(masks_extra or {})}, protocol=2))
    return folder


def openhead_data_or_skip() -> HeadModelData:
    """OpenHead's arrays when geoavatar.head.openhead is available, else skip the test."""
    import pytest

    try:
        from geoavatar.head.openhead import build_openhead  # noqa: F401
    except ImportError as err:
        pytest.skip(f"OpenHead not available yet: {err}")
    from geoavatar.head import load_head_data

    return load_head_data("openhead")


def head_by_name(name: str) -> HeadModelData:
    """'procedural', 'flame5023' (the procedural head renumbered to FLAME's lip-ring ids) or 'openhead'."""
    if name == "procedural":
        return procedural_head()
    if name == "flame5023":
        return renumber_to_flame(procedural_head(), 5023)
    if name == "openhead":
        return openhead_data_or_skip()
    raise ValueError(name)
