"""OpenHead rig: joint regressor, LBS weights and FLAME-like region masks (all from the template).

Joint placement (rest pose, metres): root in the middle of the neck, neck at the skull base
(atlanto-occipital joint), jaw on the mid-line between the two temporomandibular joints, eyes at
the eyeball centres. The regressor reproduces exactly these points from the template as convex
combinations of a few skin vertices (eyes: the mean of the eyeball's vertices), so identity modes
move the joints with the surface, as FLAME's regressor does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import nnls

from geoavatar.head.base import JOINT_NAMES
from geoavatar.head.openhead.surface import OpenHeadShape, SkinGrid

ROOT_JOINT = (0.0, -0.125, -0.020)
NECK_JOINT = (0.0, -0.040, -0.022)
JAW_JOINT = (0.0, -0.010, 0.004)  # mid-point of the temporomandibular joints (x = +-0.045)


@dataclass
class HeadLayout:
    """Template vertices plus the index sets the rig, regions and modes are built from."""

    vertices: np.ndarray  # [V, 3] all vertices: skin, then left eyeball, then right eyeball
    faces: np.ndarray  # [F, 3]
    skin: SkinGrid
    num_skin: int
    left_eyeball: np.ndarray  # vertex ids
    right_eyeball: np.ndarray
    shape: OpenHeadShape

    def eye_centre(self, side: int) -> np.ndarray:
        """side +1: subject's left eye, -1: right eye."""
        return np.asarray(self.shape.eye_centre) * np.array([side, 1.0, 1.0])

    @property
    def mouth_corners(self) -> np.ndarray:  # [2, 3] right, left
        return self.vertices[[self.skin.lip_ring_upper[0], self.skin.lip_ring_upper[-1]]]

    @property
    def mouth_centre(self) -> np.ndarray:
        mid = len(self.skin.lip_ring_upper) // 2
        return 0.5 * (self.vertices[self.skin.lip_ring_upper[mid]] + self.vertices[self.skin.lip_ring_lower[mid]])

    @property
    def nose_tip(self) -> np.ndarray:
        v = self.vertices[: self.num_skin]
        mid = np.abs(v[:, 0]) < 1e-6
        return v[mid][np.argmax(v[mid, 2])]

    def below_mouth(self) -> np.ndarray:
        """[V] 1 for skin on the lower-lip/chin side of the mouth line, 0 above, 0.5 on the corners."""
        s = self.skin
        side = np.zeros(len(self.vertices))
        side[: self.num_skin][s.row[: self.num_skin] < s.mouth_row] = 1.0
        side[: self.num_skin][s.lower_lip_copy] = 1.0
        side[s.lip_ring_upper[[0, -1]]] = 0.5
        return side


def _smoothstep(edge0: float, edge1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - edge0) / (edge1 - edge0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _regress_point(target: np.ndarray, candidates: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """Non-negative weights on `candidates` (sum 1) whose combination of vertices equals target."""
    pts = vertices[candidates]  # [K, 3]
    lam = 10.0  # weight of the sum-to-one row
    a = np.concatenate([pts.T, lam * np.ones((1, len(candidates)))], axis=0)  # [4, K]
    b = np.concatenate([target, [lam]])
    w, _ = nnls(a, b)
    w = w / w.sum()
    err = np.linalg.norm(w @ pts - target)
    if err > 1e-5:
        raise RuntimeError(f"OpenHead rig: cannot express joint {target} from the surface (error {err:.2e} m)")
    return w


def joint_regressor(layout: HeadLayout) -> np.ndarray:
    """[J, V] regressor, rows sum to 1, mirror-symmetric."""
    v = layout.vertices
    skin = v[: layout.num_skin]
    reg = np.zeros((len(JOINT_NAMES), len(v)))
    for j, target in ((0, ROOT_JOINT), (1, NECK_JOINT), (2, JAW_JOINT)):
        target = np.asarray(target)
        # Candidates: skin vertices in a horizontal slab around the joint (a ring around it), both sides.
        slab = np.nonzero(np.abs(skin[:, 1] - target[1]) < 0.012)[0]
        w = _regress_point(target, slab, v)
        # Symmetrise: average with the mirrored solution (the mesh is mirror-symmetric).
        mirror = _mirror_index(skin)
        reg[j, slab] += 0.5 * w
        reg[j, mirror[slab]] += 0.5 * w
    for j, ids in ((3, layout.left_eyeball), (4, layout.right_eyeball)):
        reg[j, ids] = 1.0 / len(ids)
    return reg


def _mirror_index(points: np.ndarray) -> np.ndarray:
    """Index of the mirror image (x -> -x) of every point (the skin grid is exactly symmetric)."""
    from scipy.spatial import cKDTree

    dist, idx = cKDTree(points).query(points * np.array([-1.0, 1.0, 1.0]))
    if dist.max() > 1e-6:
        raise RuntimeError("OpenHead rig: the skin is not mirror-symmetric")
    return idx


def skinning_weights(layout: HeadLayout) -> np.ndarray:
    """[V, J] smooth LBS weights.

    root: the lower neck (full weight at the neck base, none above the middle of the neck);
    jaw: lower lip, chin, lower face and the under-chin, with a smooth falloff over the cheeks up to
    the jaw joint and none above the mouth line (the upper lip stays with the head);
    eyes: their eyeballs (100 %); neck: everything else (the head).
    """
    v = layout.vertices
    n_skin = layout.num_skin
    skin = v[:n_skin]
    x, y, z = skin[:, 0], skin[:, 1], skin[:, 2]
    weights = np.zeros((len(v), len(JOINT_NAMES)))

    root = 1.0 - _smoothstep(-0.18, -0.115, y)

    # Jaw line seen from the front and side: the mouth line between the corners, rising towards the
    # jaw joint in front of the ear. Above it (plus a blend band) the skin follows the head.
    corner_x = layout.shape.mouth_half_width
    mouth_y = layout.mouth_centre[1]
    lateral = np.clip((np.abs(x) - corner_x) / 0.035, 0.0, 1.0)  # 0 at the corners, 1 at the cheek side
    line_y = mouth_y + (JAW_JOINT[1] - 0.012 - mouth_y) * lateral**1.2
    band = 0.002 + 0.016 * lateral
    below = layout.below_mouth()[:n_skin]
    near_mouth = (np.abs(x) <= corner_x + 1e-6) & (np.abs(y - mouth_y) < 0.02) & (z > 0.05)
    jaw = 1.0 - _smoothstep(line_y - band, line_y + band, y)
    jaw = np.where(near_mouth, below, jaw)
    # Fade out behind the jaw joint and the jaw angle, and down the neck.
    jaw *= 1.0 - _smoothstep(-0.005, 0.02, -(z - 0.012 * (y + 0.03) / 0.06))
    jaw *= _smoothstep(-0.125, -0.085, y + 0.3 * np.clip(z, 0.0, None))
    jaw = np.clip(jaw, 0.0, 1.0) * (1.0 - root)

    weights[:n_skin, 0] = root
    weights[:n_skin, 2] = jaw
    weights[:n_skin, 1] = 1.0 - root - jaw
    weights[layout.left_eyeball, 3] = 1.0
    weights[layout.right_eyeball, 4] = 1.0
    return weights


def region_masks(layout: HeadLayout) -> dict[str, np.ndarray]:
    """The 14 FLAME mask names with FLAME-like meaning (regions overlap as FLAME's do)."""
    v = layout.vertices
    n_skin = layout.num_skin
    skin = v[:n_skin]
    x, y, z = skin[:, 0], skin[:, 1], skin[:, 2]
    ax = np.abs(x)
    eye_y = layout.shape.eye_centre[1]
    chin_y = skin[:, 1][(ax < 0.01) & (z > 0.03)].min()

    # Face: the frontal oval from the hairline to the chin, between the ears (FLAME's 'face').
    oval = (ax / 0.060) ** 2 + ((y - (eye_y - 0.040)) / 0.105) ** 2  # < 1 inside
    face = (oval < 1.0) & (z > 0.010 + 0.3 * ax) & (y > chin_y - 0.008)
    # Boundary: a ring around the rim of the face region.
    boundary = (oval > 0.80) & (oval < 1.25) & (z > 0.0 + 0.3 * ax) & (y > chin_y - 0.015) & (y < eye_y + 0.08)

    ears = {}
    for name, side in (("left_ear", 1.0), ("right_ear", -1.0)):
        ear_c = np.array([0.074 * side, 0.003, -0.010])
        ears[name] = np.nonzero((np.linalg.norm((skin - ear_c) / [0.03, 0.042, 0.03], axis=-1) < 1.0) & (side * x > 0.062))[0]
    ear_any = np.zeros(n_skin, bool)
    for ids in ears.values():
        ear_any[ids] = True

    neck = (y < chin_y - 0.004 - 0.25 * np.clip(z - 0.02, 0.0, None)) & (y < -0.04) | (y < -0.12)
    neck &= ~((z > 0.02) & (y > chin_y - 0.015))
    scalp = ~face & ~ear_any & ~neck & ((y > eye_y + 0.035) | (z < -0.01))

    forehead = (y > eye_y + 0.018) & (y < eye_y + 0.075) & (ax < 0.052) & (z > 0.05)
    eye_regions = {}
    for name, side in (("left_eye_region", 1.0), ("right_eye_region", -1.0)):
        ec = layout.eye_centre(int(side))
        rel = (skin - ec) / [0.024, 0.016, 0.03]
        eye_regions[name] = np.nonzero((np.linalg.norm(rel, axis=-1) < 1.0) & (z > ec[2] - 0.012))[0]
    tip = layout.nose_tip
    nose = (ax < 0.019 + 0.004 * np.clip((eye_y - y) / 0.04, 0, 1)) & (y < eye_y + 0.006) & (y > tip[1] - 0.011) & (z > 0.082)
    mc = layout.mouth_centre
    lips = (np.linalg.norm((skin - mc) / [layout.shape.mouth_half_width + 0.004, 0.016, 0.05], axis=-1) < 1.0) & (z > 0.065)

    ids = lambda m: np.nonzero(m)[0].astype(np.int64)  # noqa: E731
    regions = {
        "face": ids(face), "boundary": ids(boundary), "scalp": ids(scalp), "neck": ids(neck),
        "forehead": ids(forehead), "nose": ids(nose), "lips": ids(lips),
        "left_ear": ears["left_ear"].astype(np.int64), "right_ear": ears["right_ear"].astype(np.int64),
        "left_eye_region": eye_regions["left_eye_region"].astype(np.int64),
        "right_eye_region": eye_regions["right_eye_region"].astype(np.int64),
        "left_eyeball": layout.left_eyeball.astype(np.int64), "right_eyeball": layout.right_eyeball.astype(np.int64),
    }
    regions["eye_region"] = np.union1d(regions["left_eye_region"], regions["right_eye_region"])
    return regions
