"""OpenHead identity and expression bases, as smooth displacement fields over the template.

Each mode is a field Delta(p) = weight(p) * direction(p) per unit coefficient (metres), built from
Gaussian falloffs around anatomical anchor points of the template (mouth corners, eye centres, nose
tip, ...), so every mode is smooth and local. Identity units are about one standard deviation of
adult variation (+-2 gives clearly different but plausible people); expression units follow FLAME's
magnitude (about 1.0 = a strong expression). Eyeballs move rigidly with the skin around them for
identity modes and never move for expressions (gaze is the eye joints' job). Blinks are not
displacements from an anchor but the lid closing over the eyeball: the lid skin slides along the lid
sphere until the margins meet (`_blink`).
"""

from __future__ import annotations

import numpy as np

from geoavatar.head.openhead.rig import HeadLayout, _smoothstep
from geoavatar.head.openhead.surface import fissure_outline

LID_MARGIN = 0.0018  # skin within this distance of the eye opening is the lid margin


def _gauss(p: np.ndarray, centre, radii) -> np.ndarray:
    """Anisotropic Gaussian falloff, 1 at centre. p [N, 3] -> [N]."""
    q = (p - np.asarray(centre)) / np.asarray(radii)
    return np.exp(-0.5 * (q * q).sum(-1))


def _mirror(v) -> np.ndarray:
    return np.asarray(v, np.float64) * np.array([-1.0, 1.0, 1.0])


def _bilateral(p: np.ndarray, centre_left, radii, vec_left) -> np.ndarray:
    """Symmetric pair of bumps: left one moves by vec_left, right one by its mirror image. -> [N, 3]"""
    out = _gauss(p, centre_left, radii)[:, None] * np.asarray(vec_left)
    return out + _gauss(p, _mirror(centre_left), radii)[:, None] * _mirror(vec_left)


# --------------------------------------------------------------------------- identity
def identity_modes(layout: HeadLayout) -> tuple[list[str], np.ndarray]:
    """Names and shapedirs [V, 3, S]."""
    v = layout.vertices
    n_skin = layout.num_skin
    p = v[:n_skin]
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    ey = layout.shape.eye_centre[1]
    el = layout.eye_centre(1)
    tip = layout.nose_tip
    mc = layout.mouth_centre
    corner = layout.mouth_corners[1]
    face_front = _smoothstep(0.0, 0.05, z)[:, None]
    skull = _smoothstep(ey - 0.01, ey + 0.04, y)[:, None]
    chin_c = np.array([0.0, mc[1] - 0.038, mc[2] - 0.012])
    ear_c = np.array([0.074, 0.003, -0.010])

    def axis_field(axis: int, values: np.ndarray) -> np.ndarray:
        out = np.zeros_like(p)
        out[:, axis] = values
        return out

    modes: dict[str, np.ndarray] = {}
    modes["head_width"] = axis_field(0, 0.04 * x) * skull
    modes["head_length"] = axis_field(2, 0.045 * np.minimum(z + 0.01, 0.0)) * _smoothstep(-0.1, -0.04, y)[:, None]
    modes["head_height"] = axis_field(1, 0.05 * np.maximum(y - (ey + 0.02), 0.0))
    modes["face_width"] = axis_field(0, 0.045 * x) * (face_front * _smoothstep(-0.11, -0.05, y)[:, None]
                                                      * (1 - _smoothstep(ey + 0.03, ey + 0.07, y))[:, None])
    modes["face_length"] = axis_field(1, -0.07 * np.maximum(tip[1] - y, 0.0)) * _smoothstep(-0.02, 0.03, z + 0.3 * (y - tip[1]))[:, None]
    modes["nose_length"] = _gauss(p, tip, (0.012, 0.014, 0.02))[:, None] * np.array([0.0, -0.0012, 0.0022])
    modes["nose_width"] = axis_field(0, 0.09 * x) * _gauss(p, tip + [0, -0.004, -0.008], (0.016, 0.01, 0.02))[:, None]
    modes["nose_bridge"] = _gauss(p, [0.0, ey - 0.008, 0.094], (0.007, 0.015, 0.02))[:, None] * np.array([0.0, 0.0, 0.0016])
    modes["jaw_width"] = axis_field(0, 0.06 * x) * _gauss(p * [0.0, 1.0, 1.0], [0.0, mc[1] - 0.02, 0.0], (1.0, 0.025, 0.04))[:, None] * _smoothstep(0.02, 0.05, np.abs(x))[:, None]
    modes["chin_length"] = _gauss(p, chin_c, (0.02, 0.018, 0.03))[:, None] * np.array([0.0, -0.0030, 0.0008])
    modes["chin_protrusion"] = _gauss(p, chin_c + [0, 0.004, 0.01], (0.02, 0.016, 0.025))[:, None] * np.array([0.0, 0.0, 0.0028])
    modes["chin_width"] = axis_field(0, 0.1 * x) * _gauss(p, chin_c, (0.025, 0.016, 0.03))[:, None]
    modes["cheekbones"] = _bilateral(p, [0.050, ey - 0.018, 0.055], (0.014, 0.012, 0.018), [0.0022, 0.0, 0.0014])
    modes["cheek_fullness"] = _bilateral(p, [0.042, mc[1] + 0.005, 0.055], (0.014, 0.016, 0.02), [0.0025, 0.0, 0.0012])
    modes["brow_ridge"] = _bilateral(p, [0.022, ey + 0.016, 0.085], (0.02, 0.007, 0.015), [0.0, 0.0, 0.0018])
    modes["eye_spacing"] = _bilateral(p, el, (0.014, 0.013, 0.02), [0.0018, 0.0, 0.0])
    modes["eye_height"] = _bilateral(p, el, (0.016, 0.012, 0.02), [0.0, 0.0016, 0.0])
    modes["lip_thickness"] = (_gauss(p, mc + [0, 0.006, 0], (0.02, 0.004, 0.02))[:, None] * np.array([0.0, 0.0012, 0.0008])
                              + _gauss(p, mc + [0, -0.007, 0], (0.018, 0.005, 0.02))[:, None] * np.array([0.0, -0.0012, 0.0008]))
    mouth_w = _gauss(p, mc, (0.03, 0.012, 0.03))[:, None]
    modes["mouth_width"] = axis_field(0, 0.09 * x) * mouth_w * _smoothstep(0.0, corner[0], np.abs(x))[:, None] ** 0.5
    modes["lip_protrusion"] = _gauss(p, mc, (0.025, 0.014, 0.02))[:, None] * np.array([0.0, 0.0, 0.0025])
    side = np.where(x >= 0, 1.0, -1.0)
    ear_centre = np.stack([ear_c[0] * side, np.full_like(x, ear_c[1]), np.full_like(x, ear_c[2])], -1)
    ear_w = _gauss(p - ear_centre, [0, 0, 0], (0.016, 0.03, 0.02)) * _smoothstep(0.06, 0.075, np.abs(x))
    modes["ear_size"] = 0.12 * (p - ear_centre) * ear_w[:, None]
    modes["ear_protrusion"] = np.stack([side * 0.004 * np.clip((-(z - ear_c[2])) / 0.02, 0, 1.5), 0 * x, 0 * x], -1) * ear_w[:, None]
    modes["forehead_slope"] = axis_field(2, -0.04 * np.maximum(y - (ey + 0.02), 0.0)) * face_front
    modes["midface_depth"] = _gauss(p, [0.0, tip[1] + 0.005, 0.08], (0.04, 0.03, 0.04))[:, None] * np.array([0.0, 0.0, 0.0025])
    modes["neck_thickness"] = np.stack([0.05 * x, 0 * x, 0.05 * (z + 0.018)], -1) * (1 - _smoothstep(-0.11, -0.06, y))[:, None]

    names = list(modes)
    skin_dirs = np.stack([modes[n] for n in names], axis=-1)  # [Vs, 3, S]
    return names, _with_eyeballs(layout, skin_dirs, rigid_eyes=True)


def _with_eyeballs(layout: HeadLayout, skin_dirs: np.ndarray, rigid_eyes: bool) -> np.ndarray:
    """Append eyeball rows: the skin displacement at the eye centre (identity) or zero (expression)."""
    out = np.zeros((len(layout.vertices), 3, skin_dirs.shape[-1]))
    out[: layout.num_skin] = skin_dirs
    if rigid_eyes:
        skin = layout.vertices[: layout.num_skin]
        for ids, side in ((layout.left_eyeball, 1), (layout.right_eyeball, -1)):
            # The field at the eye centre, from the skin vertices nearest to it (inverse-distance weights).
            d = np.linalg.norm(skin - layout.eye_centre(side), axis=-1)
            near = np.argsort(d)[:24]
            w = 1.0 / d[near] ** 2
            out[ids] = (skin_dirs[near] * (w / w.sum())[:, None, None]).sum(0)[None]
    return out


# --------------------------------------------------------------------------- expression
def _blink(layout: HeadLayout, side: int) -> np.ndarray:
    """Full lid closure of one eye [Vs, 3]: lids slide over the eyeball until the margins meet."""
    shape = layout.shape
    p = layout.vertices[: layout.num_skin]
    e = layout.eye_centre(side)
    rel = p - e
    lateral = side * rel[:, 0]  # towards the outer corner
    s = (lateral - 0.0015) / shape.fissure_half_width
    upper, lower = fissure_outline(s, shape)
    closure = lower + 0.32 * (upper - lower)  # where the closed lids meet
    # The lid margins are ~1 mm thick bands around the opening: all of them meet on the closure line.
    upper, lower = upper + LID_MARGIN, lower - LID_MARGIN
    crease, fold = upper + 0.0085, lower - 0.0065
    yy = rel[:, 1]
    new_y = yy.copy()
    up = (yy >= upper) & (yy < crease)
    new_y[up] = closure[up] + (yy[up] - upper[up]) * (crease[up] - closure[up]) / (crease[up] - upper[up])
    inside = (yy < upper) & (yy > lower)
    new_y[inside] = closure[inside]
    low = (yy <= lower) & (yy > fold)
    new_y[low] = closure[low] - (lower[low] - yy[low]) * (closure[low] - fold[low]) / (lower[low] - fold[low])
    r = np.linalg.norm(rel, axis=-1)
    new_r = np.maximum(r, shape.lid_radius + 0.0004)
    z2 = new_r**2 - rel[:, 0] ** 2 - new_y**2
    new_z = np.where(z2 > 0, np.sqrt(np.maximum(z2, 0.0)), rel[:, 2])
    active = (rel[:, 2] > 0.0) & (r < 0.02) & (np.abs(s) < 1.6)
    weight = (1.0 - _smoothstep(1.0, 1.5, np.abs(s))) * active
    delta = np.stack([0 * yy, new_y - yy, new_z - rel[:, 2]], -1)
    return delta * weight[:, None]


def expression_modes(layout: HeadLayout) -> tuple[list[str], np.ndarray]:
    """Names and exprdirs [V, 3, E]."""
    p = layout.vertices[: layout.num_skin]
    x = p[:, 0]
    ey = layout.shape.eye_centre[1]
    el, er = layout.eye_centre(1), layout.eye_centre(-1)
    mc = layout.mouth_centre
    cr, cl = layout.mouth_corners
    tip = layout.nose_tip
    below = layout.below_mouth()[: layout.num_skin][:, None]
    above = 1.0 - below
    mouth = _gauss(p, mc, (0.024, 0.014, 0.03))[:, None]
    lips_near = _gauss(p, mc, (0.022, 0.009, 0.03))[:, None] * _smoothstep(0.06, 0.08, p[:, 2])[:, None]
    corner_l = _gauss(p, cl, (0.013, 0.012, 0.02))[:, None]
    corner_r = _gauss(p, cr, (0.013, 0.012, 0.02))[:, None]
    cheek_l = _gauss(p, [0.036, mc[1] + 0.02, 0.068], (0.014, 0.012, 0.02))[:, None]
    cheek_r = _gauss(p, [-0.036, mc[1] + 0.02, 0.068], (0.014, 0.012, 0.02))[:, None]
    brow_l = _gauss(p, [0.030, ey + 0.018, 0.08], (0.020, 0.010, 0.03))[:, None]
    brow_r = _gauss(p, [-0.030, ey + 0.018, 0.08], (0.020, 0.010, 0.03))[:, None]
    brow_in = _bilateral(p, [0.014, ey + 0.016, 0.088], (0.009, 0.009, 0.03), [1.0, 1.0, 1.0])  # weights only
    forehead = _gauss(p, [0.0, ey + 0.04, 0.08], (0.05, 0.02, 0.04))[:, None]
    cheek_puff = _bilateral(p, [0.040, mc[1], 0.060], (0.012, 0.013, 0.02), [0.006, 0.0, 0.003])

    def smile(side_w, cheek_w, sx):
        return side_w * np.array([0.005 * sx, 0.006, -0.003]) + cheek_w * np.array([0.0015 * sx, 0.003, 0.0015])

    m: dict[str, np.ndarray] = {}
    m["smile"] = smile(corner_l, cheek_l, 1) + smile(corner_r, cheek_r, -1)
    m["frown"] = corner_l * np.array([0.002, -0.005, -0.001]) + corner_r * np.array([-0.002, -0.005, -0.001])
    m["lip_pucker"] = mouth * np.stack([-0.35 * (x - mc[0]), 0 * x, 0 * x + 0.008], -1)
    funnel_open = lips_near * (above * [0.0, 0.003, 0.0] + below * [0.0, -0.004, 0.0])
    m["lip_funnel"] = mouth * np.stack([-0.25 * (x - mc[0]), 0 * x, 0 * x + 0.006], -1) + funnel_open
    m["lip_press"] = lips_near * (above * [0.0, -0.0016, -0.0015] + below * [0.0, 0.0018, -0.0015])
    m["mouth_left"] = mouth * np.array([0.008, 0.0, -0.001])
    m["mouth_right"] = mouth * np.array([-0.008, 0.0, -0.001])
    m["brow_raise"] = (brow_l + brow_r) * np.array([0.0, 0.007, 0.0005]) + forehead * np.array([0.0, 0.002, 0.0])
    m["brow_lower"] = (brow_l * np.array([-0.002, -0.0045, 0.001]) + brow_r * np.array([0.002, -0.0045, 0.001]))
    m["brow_inner_raise"] = brow_in[:, :1] * np.array([0.0, 0.006, 0.0])
    m["blink_left"] = _blink(layout, 1)
    m["blink_right"] = _blink(layout, -1)
    m["cheek_puff"] = cheek_puff
    nose_side = _bilateral(p, tip + [0.011, 0.008, -0.01], (0.008, 0.01, 0.02), [0.0, 0.003, 0.0005])
    m["nose_wrinkle"] = nose_side + _gauss(p, [0.0, ey, 0.09], (0.012, 0.01, 0.02))[:, None] * [0.0, -0.002, 0.0] \
        + lips_near * above * [0.0, 0.0015, 0.0]
    m["upper_lip_raise"] = _gauss(p, mc + [0, 0.004, 0], (0.02, 0.008, 0.03))[:, None] * above * [0.0, 0.004, 0.0005]
    m["lower_lip_depress"] = _gauss(p, mc + [0, -0.006, 0], (0.02, 0.009, 0.03))[:, None] * below * [0.0, -0.004, 0.0005]
    m["mouth_stretch"] = (corner_l * [0.005, -0.001, -0.001] + corner_r * [-0.005, -0.001, -0.001])
    m["chin_raise"] = _gauss(p, mc + [0, -0.03, -0.005], (0.018, 0.016, 0.03))[:, None] * below * [0.0, 0.003, 0.001]
    m["lips_roll_in"] = lips_near * (above * [0.0, -0.001, -0.003] + below * [0.0, 0.001, -0.003])
    m["smile_left"] = smile(corner_l, cheek_l, 1)
    m["smile_right"] = smile(corner_r, cheek_r, -1)
    squint = lambda ec: _gauss(p, ec + [0, -0.010, 0.01], (0.014, 0.005, 0.02))[:, None] * [0.0, 0.0025, 0.0005]  # noqa: E731
    m["eye_squint"] = squint(el) + squint(er)
    m["eye_wide"] = -0.3 * (m["blink_left"] + m["blink_right"]) * (p[:, 1:2] > ey)  # upper lids up
    names = list(m)
    return names, _with_eyeballs(layout, np.stack([m[n] for n in names], axis=-1), rigid_eyes=False)
