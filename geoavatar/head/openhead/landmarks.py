"""MediaPipe (478-point) landmark embedding of OpenHead: (face, barycentric) per landmark id.

How each group is placed (geoavatar.head.landmarks_mediapipe holds the ids and a measured frontal
reference face):
- inner lip contours: exactly on the mouth-opening edge (the lip rings), at the reference's
  relative x between the corners (the corners 78/308 are the ring corners);
- outer lip contours: corners 61/291 on the ring corners, the others at the reference's relative
  x and at its height above/below the corner line (scaled to OpenHead), projected onto the skin;
- eyelid contours: on the lid skin just outside OpenHead's eye opening (the almond that
  `surface.fissure_outline` carves), at the reference's relative x between the eye corners, so
  they follow the lids when OpenHead blinks;
- irises: on the eyeball meshes (centre at the pupil, rim points 5.8 mm from it);
- nose tip (id 1): the most forward point of the nose;
- brows, the rest of the nose and the face oval: the reference positions mapped into OpenHead by
  a per-axis map (x scale; y scale and offset) fitted on the eyelid and lip landmarks placed from
  OpenHead's own contours, then projected onto the skin along -z (the frontmost hit), as a frontal
  photo would see them.
The reference face is one person's; the tracker (geoavatar.prep.tracking) fits a smooth static
offset of the mesh per video, which absorbs the difference between that face, OpenHead and the
person filmed.
"""

from __future__ import annotations

import numpy as np

from geoavatar.head import landmarks_mediapipe as mp
from geoavatar.head.openhead.rig import HeadLayout
from geoavatar.head.openhead.surface import fissure_outline

IRIS_RADIUS = 0.0058
# Groups placed from the reference face, and the groups (OpenHead's own contours) that fit that map.
REFERENCE_MAPPED = ("right_brow_upper", "right_brow_lower", "left_brow_upper", "left_brow_lower",
                    "nose_ridge", "nose_right", "nose_left", "face_oval")
ANCHOR_GROUPS = ("lips_outer_upper", "lips_outer_lower", "lips_inner_upper", "lips_inner_lower",
                 "right_eye_upper", "right_eye_lower", "left_eye_upper", "left_eye_lower")


def frontal_hits(points_xy: np.ndarray, vertices: np.ndarray, faces: np.ndarray, face_ids: np.ndarray):
    """Frontmost surface point under each (x, y), looking along -z.

    points_xy [N, 2]; faces restricted to face_ids. Returns face index [N] (-1 = miss), bary [N, 3].
    """
    tri = vertices[faces[face_ids]]  # [F, 3, 3]
    a, b, c = tri[:, 0, :2], tri[:, 1, :2], tri[:, 2, :2]
    v0, v1 = b - a, c - a  # [F, 2]
    den = v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1]  # [F]
    ok = np.abs(den) > 1e-14
    den = np.where(ok, den, 1.0)
    d = points_xy[:, None, :] - a[None]  # [N, F, 2]
    w1 = (d[..., 0] * v1[None, :, 1] - v1[None, :, 0] * d[..., 1]) / den
    w2 = (v0[None, :, 0] * d[..., 1] - d[..., 0] * v0[None, :, 1]) / den
    w0 = 1.0 - w1 - w2
    inside = (w0 >= -1e-9) & (w1 >= -1e-9) & (w2 >= -1e-9) & ok[None]
    depth = w0 * tri[None, :, 0, 2] + w1 * tri[None, :, 1, 2] + w2 * tri[None, :, 2, 2]
    depth = np.where(inside, depth, -np.inf)
    best = np.argmax(depth, axis=1)  # [N]
    hit = np.isfinite(depth[np.arange(len(points_xy)), best])
    bary = np.stack([w0, w1, w2], -1)[np.arange(len(points_xy)), best]
    return np.where(hit, face_ids[best], -1), np.clip(bary, 0.0, 1.0) / np.clip(bary, 0.0, 1.0).sum(-1, keepdims=True)


def _edge_point(faces: np.ndarray, a: int, b: int, t: float, prefer: np.ndarray) -> tuple[int, np.ndarray]:
    """A face containing edge (a, b) (from `prefer`, the faces on the wanted side) and the bary of (1-t)a + t b."""
    for f in prefer:
        tri = faces[f]
        if a in tri and (b in tri or t == 0.0):
            bary = np.zeros(3)
            bary[list(tri).index(a)] += 1.0 - t
            if t > 0.0:
                bary[list(tri).index(b)] += t
            return int(f), bary
    raise RuntimeError(f"OpenHead landmarks: no face holds the lip-ring edge ({a}, {b})")


def _ring_points(layout: HeadLayout, ring: np.ndarray, rel_x: np.ndarray, side_faces: np.ndarray):
    """Points on a lip ring polyline at relative x in [-1, 1] between its corners."""
    v = layout.vertices[ring]
    xs = v[:, 0]
    target = rel_x * xs[-1]
    out = []
    for tx in target:
        i = int(np.clip(np.searchsorted(xs, tx) - 1, 0, len(xs) - 2))
        t = float(np.clip((tx - xs[i]) / (xs[i + 1] - xs[i]), 0.0, 1.0))
        out.append(_edge_point(layout.faces, int(ring[i]), int(ring[i + 1]), t, side_faces))
    return out


def _reference(ids) -> np.ndarray:
    return np.array([mp.REFERENCE_FACE[i] for i in ids], np.float64) * 1e-4  # [N, 3] metres


def embed_landmarks(layout: HeadLayout) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """landmark ids [L], faces [L], bary [L, 3] in the mediapipe478 convention."""
    shape = layout.shape
    v, faces = layout.vertices, layout.faces
    n_skin = layout.num_skin
    skin_faces = np.nonzero((faces < n_skin).all(1))[0]
    front_skin = skin_faces  # the frontmost hit is what a frontal view sees
    placed: dict[int, tuple[int, np.ndarray]] = {}

    hw = shape.fissure_half_width
    tip = layout.nose_tip
    mouth_corner = layout.mouth_corners[1]

    def project(ids, xy, face_ids):
        f, bary = frontal_hits(xy, v, faces, face_ids)
        for k, i in enumerate(ids):
            xy_k = xy[k].copy()
            while f[k] < 0 and abs(xy_k[0]) > 1e-3:  # off the silhouette: step towards the mid-line
                xy_k[0] *= 0.98
                fk, bk = frontal_hits(xy_k[None], v, faces, face_ids)
                f[k], bary[k] = fk[0], bk[0]
            if f[k] < 0:
                raise RuntimeError(f"OpenHead landmarks: landmark {i} does not project onto the head")
            placed[int(i)] = (int(f[k]), bary[k])

    # Inner lips: on the rings.
    ring_u, ring_l = layout.skin.lip_ring_upper, layout.skin.lip_ring_lower
    upper_faces = skin_faces[(layout.skin.row[faces[skin_faces]].max(1) > layout.skin.mouth_row)]
    lower_faces = skin_faces[(layout.skin.row[faces[skin_faces]].min(1) < layout.skin.mouth_row)]
    for ids, ring, side_faces in ((mp.LIPS_INNER_UPPER, ring_u, upper_faces), (mp.LIPS_INNER_LOWER, ring_l, lower_faces)):
        r = _reference(ids)
        rel = r[:, 0] / r[-1, 0]
        rel[0], rel[-1] = -1.0, 1.0
        for i, (f, bary) in zip(ids, _ring_points(layout, ring, rel, side_faces)):
            placed[int(i)] = (f, bary)

    # Outer lips: relative x between the corners, height relative to the corner line.
    for ids in (mp.LIPS_OUTER_UPPER, mp.LIPS_OUTER_LOWER):
        r = _reference(ids)
        corner_ref_y = 0.5 * (r[0, 1] + r[-1, 1])
        # Height above the corner line: the reference's, scaled by OpenHead's to reference mouth width.
        sy_lips = mouth_corner[0] / r[-1, 0]
        xy = np.stack([r[:, 0] / r[-1, 0] * mouth_corner[0], mouth_corner[1] + sy_lips * (r[:, 1] - corner_ref_y)], -1)
        project(list(ids[1:-1]), xy[1:-1], front_skin)
    for i, vid in ((mp.LIPS_OUTER_UPPER[0], ring_u[0]), (mp.LIPS_OUTER_UPPER[-1], ring_u[-1])):
        f, bary = _edge_point(faces, int(vid), int(vid), 0.0, upper_faces)
        placed[int(i)] = (f, bary)

    # Eyelids: just outside the carved opening, on the lid skin.
    for side, groups in ((1, ("left_eye_upper", "left_eye_lower")), (-1, ("right_eye_upper", "right_eye_lower"))):
        e = layout.eye_centre(side)
        for g_index, name in enumerate(groups):
            ids = mp.CONTOURS[name]
            r = _reference(ids)
            # Reference relative position between the inner (0) and outer (1) corner.
            inner_x, outer_x = (r[0, 0], r[-1, 0]) if side > 0 else (r[-1, 0], r[0, 0])
            u = (r[:, 0] - inner_x) / (outer_x - inner_x)
            s = -1.0 + 2.0 * u
            upper, lower = fissure_outline(s, shape)
            y = np.where(g_index == 0, upper + 0.0002, lower - 0.0002)  # on the lid margin
            y[np.abs(s) > 0.999] = upper[np.abs(s) > 0.999]
            lateral = 0.0015 + s * hw * 0.985
            xy = np.stack([e[0] + side * lateral, e[1] + y], -1)
            project(list(ids), xy, front_skin)

    # Brows, nose and face oval: the reference face mapped into OpenHead by a per-axis map fitted on the
    # eyelid and lip landmarks placed above (OpenHead's own contours; a chin anchor would have to be
    # picked on a mid-line profile that curves into the neck), then projected onto the frontmost skin.
    anchors = [i for name in ANCHOR_GROUPS for i in mp.CONTOURS[name] if int(i) in placed]
    ref = _reference(anchors)
    got = np.stack([(v[faces[placed[int(i)][0]]] * placed[int(i)][1][:, None]).sum(0) for i in anchors])  # [A, 3]
    sx = float((ref[:, 0] * got[:, 0]).sum() / max((ref[:, 0] ** 2).sum(), 1e-12))
    sy, ty = np.linalg.lstsq(np.stack([ref[:, 1], np.ones(len(ref))], -1), got[:, 1], rcond=None)[0]
    generic = [i for name in REFERENCE_MAPPED for i in mp.CONTOURS[name]]
    generic = [i for i in dict.fromkeys(generic) if i != 1]
    r = _reference(generic)
    project(generic, np.stack([sx * r[:, 0], sy * r[:, 1] + ty], -1), front_skin)

    # Nose tip: the most forward skin point on the mid-line.
    project([1], np.array([[0.0, tip[1]]]), front_skin)

    # Irises on the eyeballs.
    for ids, eyeball, side in ((mp.LEFT_IRIS, layout.left_eyeball, 1), (mp.RIGHT_IRIS, layout.right_eyeball, -1)):
        e = layout.eye_centre(side)
        ball_faces = np.nonzero(np.isin(faces, eyeball).all(1))[0]
        medial = -side * IRIS_RADIUS
        offsets = np.array([[0, 0], [medial, 0], [0, IRIS_RADIUS], [-medial, 0], [0, -IRIS_RADIUS]])
        project(list(ids), e[None, :2] + offsets, ball_faces)

    ids = np.array(sorted(placed), np.int64)
    return ids, np.array([placed[i][0] for i in ids], np.int64), np.array([placed[i][1] for i in ids], np.float64)
