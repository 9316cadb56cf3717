"""The mouth structure F_m appended to a head model with lip rings (paper §3.2 and appendix).

    data = add_mouth_structure(data, kind="geoavatar")   # or "gaussianavatars", or "none"

Everything is built on the neutral template from the two lip rings (15 vertices each, ordered by
increasing x). The mouth line M_i is the midpoint of upper ring vertex i and lower ring vertex i;
like GaussianAvatars we flatten it to one height y0 (the paper observes that the teeth trajectory
lies in an xz-plane) and measure every size as a fraction of the mouth width w = |x_14 - x_0|, so
the structure scales with the head (at w = 5 cm the defaults give ~1 cm tall, ~7 mm thick teeth).
The lip rings we keep are the inner rings, which touch in a closed mouth, so their gap cannot give
a scale (GaussianAvatars takes its scale from the outer-ring gap instead).

kind="gaussianavatars" (our own version of GaussianAvatars' `add_teeth`): the teeth trajectory T is
the mouth line pushed back by `setback`; each of the upper and lower teeth is a U-shaped shell of
4 rings x 15 columns (root and edge at the front, edge and root at the back, `thickness` behind),
3 strips of quads (front, biting edge, back), open at the root: 120 vertices, 168 faces. The lower
teeth sit `lower_teeth_back` behind the upper ones. "Back" is -z, as in GaussianAvatars.

kind="geoavatar" (appendix "Structural Details"): the same teeth on a trajectory extended to the
molars. The pseudo-centre C is the intersection of the perpendicular bisectors of T0T1 and T13T14
(in the xz-plane) — or, when those bisectors are nearly parallel or meet in front of the mouth or
more than `max_centre_distance` (x w) away (lip rings whose corners flatten out, as OpenHead's),
the centre of the least-squares circle through the 15 points (metadata "centre_method" says which),
and then the 15 teeth points are moved radially onto that circle, since a ring whose ends leave the
arc would otherwise pass its kinks on to the molars;
T1..T5 are reflected across the line C-T0 and T9..T13 across C-T14, giving
25 points (reflected T5..T1, T0..T14, reflected T13..T9). A reflection across a line through C
keeps the distance to C, so the molars continue the circle through the ring ends. Because the
trajectory now runs along z at the molars, "backward" (thickness, palate, floor) is taken toward
the pseudo-centre instead of along -z: for the front teeth the two agree. The palate continues the
upper teeth shell from its inner root ring toward C in `palate_rows` rings and ends in one apex
vertex, rising by `palate_vault`; the floor does the same from the lower teeth's inner root ring.
Each ring is the previous one shifted backward (toward C), i.e. a homothety of the trajectory
about C, so the rings never cross as long as T's angle around C is monotone (checked). C lies at
the circle's radius behind the front teeth; when that is more than `max_depth` (x w) — a nearly
straight lip ring — the apex is pulled forward to that depth. Upper part = upper teeth + palate,
lower part = lower teeth + floor; each is one connected, consistently oriented surface whose
visible side faces the mouth cavity (teeth front +z, palate -y, floor +y).

Skinning and blend shapes of the appended vertices:
- LBS: the upper part follows the neck joint (like the skull), the lower part the jaw joint;
  they take no part in the joint regressor and have no pose correctives.
- identity (shapedirs): each column copies the mean shapedirs of its lip-ring column (upper and
  lower vertex), so the teeth follow the mouth's width and position across identities, as in
  GaussianAvatars; molar columns copy their mouth-corner column; the apexes the mean of all columns.
- expression: zero. The parts are rigid; GeoAvatar's part-wise deformation network moves them.

Groups added to the data: vertex_groups mouth_upper / mouth_lower (and teeth_upper, teeth_lower,
palate, floor; palate and floor start with the inner root ring they share with the teeth),
face_groups mouth (F_m), mouth_upper, mouth_lower. Vertex layout per part: ring-major, ring r
column i at r * N + i (N = 15 or 25 columns, x increasing through the front), the apex last.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from geoavatar.head.base import JOINT_NAMES, HeadModelData

MOUTH_KINDS = ("geoavatar", "gaussianavatars", "none")
NECK_JOINT = JOINT_NAMES.index("neck")
JAW_JOINT = JOINT_NAMES.index("jaw")
NUM_REFLECTED = 5  # T1..T5 and T9..T13 are reflected (paper appendix)


@dataclass(frozen=True)
class MouthConfig:
    """Sizes as fractions of the mouth width w (corner-to-corner distance of the lip rings)."""

    setback: float = 0.15  # mouth line -> front surface of the upper front teeth (7.5 mm at w = 5 cm)
    tooth_height: float = 0.20  # crown height, root to biting edge (1 cm)
    tooth_thickness: float = 0.14  # front to back of a tooth (7 mm)
    bite_gap: float = 0.01  # each biting edge sits this far from the mouth line height y0
    lower_teeth_back: float = 0.04  # lower front teeth sit behind the upper ones (2 mm overjet)
    palate_rows: int = 3  # rings between the teeth and the apex, palate and floor alike
    palate_vault: float = 0.10  # the palate rises this much toward its apex (5 mm)
    floor_drop: float = 0.0  # the floor drops this much toward its apex
    max_depth: float = 1.3  # apex at most this far behind the front teeth (6.5 cm)
    max_centre_distance: float = 2.0  # a pseudo-centre further than this from the front is not trusted


def add_mouth_structure(data: HeadModelData, kind: str = "geoavatar",
                        config: MouthConfig | None = None) -> HeadModelData:
    """Append the mouth structure of `kind` ('geoavatar', 'gaussianavatars', 'none') to `data`."""
    if kind not in MOUTH_KINDS:
        raise ValueError(f"unknown mouth structure '{kind}'; choose one of {', '.join(MOUTH_KINDS)}")
    if kind == "none":
        return data
    config = config or MouthConfig()
    if data.lip_ring_upper is None or data.lip_ring_lower is None:
        raise ValueError(
            f"head model '{data.name}' has no lip rings (lip_ring_upper / lip_ring_lower): "
            f"the '{kind}' mouth structure is built from them"
        )
    if "mouth" in data.face_groups:
        raise ValueError(f"head model '{data.name}' already has a mouth structure")

    line = mouth_line(data)
    if kind == "gaussianavatars":
        parts, info = _gaussianavatars_parts(line, config), {}
    else:
        parts, info = _geoavatar_parts(line, config)
    return _append(data, kind, line, parts, config, info)


# --- the mouth line and the trajectory -------------------------------------------------------------


@dataclass(frozen=True)
class MouthLine:
    points: np.ndarray  # [15, 2] (x, z) midpoints of the lip rings
    y: float  # common height y0
    width: float  # corner-to-corner distance w
    shapedirs: np.ndarray  # [15, 3, S] mean identity basis of each ring column


def mouth_line(data: HeadModelData) -> MouthLine:
    upper = np.asarray(data.lip_ring_upper, dtype=np.int64)
    lower = np.asarray(data.lip_ring_lower, dtype=np.int64)
    for name, ring in (("lip_ring_upper", upper), ("lip_ring_lower", lower)):
        if ring.shape != (15,):
            raise ValueError(f"head model '{data.name}': {name} must hold 15 vertex ids, has shape {ring.shape}")
        x = data.v_template[ring, 0]
        if not np.all(np.diff(x) > 0):
            raise ValueError(f"head model '{data.name}': {name} must be ordered by increasing x "
                             "(subject's right mouth corner to left corner)")
    mid = 0.5 * (data.v_template[upper] + data.v_template[lower]).astype(np.float64)  # [15, 3]
    width = float(mid[-1, 0] - mid[0, 0])
    shapedirs = 0.5 * (data.shapedirs[upper] + data.shapedirs[lower])  # [15, 3, S]
    return MouthLine(points=mid[:, [0, 2]], y=float(mid[:, 1].mean()), width=width, shapedirs=shapedirs)


def pseudo_centre(p0: np.ndarray, p1: np.ndarray, p13: np.ndarray, p14: np.ndarray) -> np.ndarray:
    """Intersection [2] of the perpendicular bisectors of p0p1 and p13p14 (points in the xz-plane)."""
    d1, d2 = p1 - p0, p14 - p13  # bisector l_k: {q : (q - m_k) . d_k = 0}
    m1, m2 = 0.5 * (p0 + p1), 0.5 * (p13 + p14)
    system = np.stack([d1, d2])  # [2, 2]
    det = float(np.linalg.det(system))
    scale = float(np.linalg.norm(d1) * np.linalg.norm(d2))
    if abs(det) <= 1e-6 * scale:
        raise ValueError("the lip ring ends are parallel: their perpendicular bisectors do not meet, "
                         "so the molar extension has no pseudo-centre (is the lip ring a straight line?)")
    return np.linalg.solve(system, np.array([d1 @ m1, d2 @ m2]))


def reflect_points(points: np.ndarray, centre: np.ndarray, through: np.ndarray) -> np.ndarray:
    """Reflect points [N, 2] across the line through `centre` and `through`."""
    u = (through - centre) / np.linalg.norm(through - centre)  # [2]
    rel = points - centre  # [N, 2]
    return centre + 2.0 * (rel @ u)[:, None] * u[None] - rel


def circle_fit_centre(points: np.ndarray) -> np.ndarray:
    """Least-squares (Kasa) circle centre [2] of points [N, 2]; error for (nearly) collinear points."""
    x, z = points[:, 0], points[:, 1]
    system = np.stack([x, z, np.ones_like(x)], axis=1)  # x^2 + z^2 = 2 cx x + 2 cz z + k
    sol, _, rank, sv = np.linalg.lstsq(system, x * x + z * z, rcond=None)
    span = float(np.ptp(points, axis=0).max())
    centre = 0.5 * sol[:2]
    if rank < 3 or sv[-1] <= 1e-9 * sv[0] or np.linalg.norm(centre - points.mean(0)) > 1e3 * span:
        raise ValueError("the lip ring is (nearly) straight: no circle fits it")
    return centre


def trajectory_centre(front: np.ndarray, max_radius: float) -> tuple[np.ndarray, str]:
    """The pseudo-centre of the front teeth trajectory [15, 2] and how it was found.

    The paper's construction (perpendicular bisectors of the end segments) is used when it gives a
    point behind the mouth within `max_radius` of the front; it needs the ring's end segments to
    follow the arc. Rings whose corners flatten out (OpenHead's do: its end segments run almost
    along x) make those bisectors nearly parallel and the point lands far away or in front of the
    face; then the least-squares circle through all 15 points is used instead.
    """
    mid = front[len(front) // 2]

    def usable(c):
        return c[1] < front[:, 1].min() and np.linalg.norm(c - mid) <= max_radius

    reason = ""
    try:
        centre = pseudo_centre(front[0], front[1], front[13], front[14])
        if usable(centre):
            return centre, "bisectors"
    except ValueError as err:
        reason = str(err)
    try:
        centre = circle_fit_centre(front)
    except ValueError as err:
        raise ValueError(f"{err}{'; ' + reason if reason else ''}; cannot extend the teeth to the molars") from err
    if not usable(centre):
        raise ValueError("the lip ring does not curve backward like a mouth (its best-fit circle centre is "
                         f"at {centre.tolist()}, not behind the ring): cannot extend the teeth to the molars")
    return centre, "least_squares_circle"


def molar_trajectory(front: np.ndarray, centre: np.ndarray | None = None,
                     max_radius: float = np.inf) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Extend the 15-point teeth trajectory to the molars.

    front [15, 2] (x, z) -> trajectory [25, 2], pseudo-centre [2], source column [25] (the ring
    column whose identity basis each point copies: the corner column for reflected points).
    """
    if centre is None:
        centre, _ = trajectory_centre(front, max_radius)
    n = NUM_REFLECTED
    right = reflect_points(front[n:0:-1], centre, front[0])  # reflections of T5..T1 (beyond T0)
    left = reflect_points(front[13:13 - n:-1], centre, front[14])  # reflections of T13..T9 (beyond T14)
    trajectory = np.concatenate([right, front, left])  # [25, 2]
    source = np.concatenate([np.zeros(n, np.int64), np.arange(15), np.full(n, 14, np.int64)])
    return trajectory, centre, source


# --- the two parts ---------------------------------------------------------------------------------


@dataclass
class _Part:
    rings: list[np.ndarray]  # each [N, 3], in strip order (front root, front edge, back edge, back root, ...)
    apex: np.ndarray | None  # [3] or None
    source: np.ndarray  # [N] lip-ring column per trajectory column
    front_normal: tuple[float, float, float]  # expected normal of the front strip
    teeth_rings: int = 4


def _xz_to_3d(xz: np.ndarray, y: float) -> np.ndarray:
    return np.stack([xz[:, 0], np.full(len(xz), y), xz[:, 1]], axis=-1)  # [N, 3]


def _teeth_heights(line: MouthLine, cfg: MouthConfig) -> tuple[float, float, float, float]:
    w = line.width
    up_edge, lo_edge = line.y + cfg.bite_gap * w, line.y - cfg.bite_gap * w
    return up_edge + cfg.tooth_height * w, up_edge, lo_edge, lo_edge - cfg.tooth_height * w


def _gaussianavatars_parts(line: MouthLine, cfg: MouthConfig) -> dict[str, _Part]:
    """Frontal teeth only: 4 rings x 15 columns per part, "back" along -z."""
    w = line.width
    back = np.array([0.0, -1.0])  # -z
    front = line.points + cfg.setback * w * back  # [15, 2]
    up_root, up_edge, lo_edge, lo_root = _teeth_heights(line, cfg)
    source = np.arange(15)

    def shell(xz, root_y, edge_y):
        xz_back = xz + cfg.tooth_thickness * w * back
        return [_xz_to_3d(xz, root_y), _xz_to_3d(xz, edge_y), _xz_to_3d(xz_back, edge_y), _xz_to_3d(xz_back, root_y)]

    return {
        "upper": _Part(shell(front, up_root, up_edge), None, source, (0.0, 0.0, 1.0)),
        "lower": _Part(shell(front + cfg.lower_teeth_back * w * back, lo_root, lo_edge), None, source, (0.0, 0.0, 1.0)),
    }


def _geoavatar_parts(line: MouthLine, cfg: MouthConfig) -> tuple[dict[str, _Part], dict]:
    """Teeth on the molar-extended trajectory (4 rings x 25 columns) + palate / floor rings + apex."""
    w = line.width
    front15 = line.points + cfg.setback * w * np.array([0.0, -1.0])  # [15, 2] front teeth, as GaussianAvatars
    centre, centre_method = trajectory_centre(front15, cfg.max_centre_distance * w)
    if centre_method == "least_squares_circle":
        # The ring's ends do not follow an arc; put the teeth on the fitted circle (same angles around C),
        # so that the reflected molars continue a smooth arch instead of copying the corners' kinks.
        rel = front15 - centre
        radius = np.linalg.norm(rel, axis=1, keepdims=True)
        front15 = centre + rel / radius * radius.mean()
    trajectory, centre, source = molar_trajectory(front15, centre)  # [25, 2]
    apex = _apex(front15, centre, cfg.max_depth * w)  # [2]
    _check_star_shaped(trajectory, apex)
    to_apex = apex - trajectory  # [25, 2]
    dist = np.linalg.norm(to_apex, axis=1, keepdims=True)  # [25, 1]
    inward = to_apex / dist  # [25, 2] "backward": toward the pseudo-centre
    reach = (cfg.lower_teeth_back + cfg.tooth_thickness) * w
    if dist.min() <= 1.5 * reach:
        raise ValueError(f"the lip ring is too curved for the mouth structure: its pseudo-centre is "
                         f"{dist.min():.4f} from the teeth trajectory, the teeth need {1.5 * reach:.4f}")
    up_root, up_edge, lo_edge, lo_root = _teeth_heights(line, cfg)

    def part(xz, root_y, edge_y, rise):
        xz_back = xz + cfg.tooth_thickness * w * inward
        rings = [_xz_to_3d(xz, root_y), _xz_to_3d(xz, edge_y), _xz_to_3d(xz_back, edge_y), _xz_to_3d(xz_back, root_y)]
        rows = cfg.palate_rows
        for k in range(1, rows + 1):  # each ring: the previous one shifted backward, toward the apex
            t = k / (rows + 1)
            rings.append(_xz_to_3d(xz_back + t * (apex - xz_back), root_y + rise * np.sin(0.5 * np.pi * t)))
        apex3 = np.array([apex[0], root_y + rise, apex[1]])
        return rings, apex3

    upper_rings, upper_apex = part(trajectory, up_root, up_edge, cfg.palate_vault * w)
    lower_xz = trajectory + cfg.lower_teeth_back * w * inward
    lower_rings, lower_apex = part(lower_xz, lo_root, lo_edge, -cfg.floor_drop * w)
    parts = {
        "upper": _Part(upper_rings, upper_apex, source, (0.0, 0.0, 1.0)),
        "lower": _Part(lower_rings, lower_apex, source, (0.0, 0.0, 1.0)),
    }
    info = {"pseudo_centre_xz": [float(v) for v in centre], "centre_method": centre_method,
            "apex_xz": [float(v) for v in apex],
            "trajectory_xz": trajectory.tolist()}
    return parts, info


def _apex(front: np.ndarray, centre: np.ndarray, max_depth: float) -> np.ndarray:
    """The point the palate and floor converge to: the pseudo-centre, at most max_depth behind the front."""
    mid = front[len(front) // 2]
    if centre[1] >= mid[1]:
        raise ValueError("the lip ring curves the wrong way: its pseudo-centre lies in front of the mouth")
    depth = float(np.linalg.norm(centre - mid))
    if depth <= max_depth:
        return centre
    return mid + (centre - mid) * (max_depth / depth)


def _check_star_shaped(trajectory: np.ndarray, apex: np.ndarray) -> None:
    rel = trajectory - apex
    angle = np.unwrap(np.arctan2(rel[:, 1], rel[:, 0]))  # [25]
    steps = np.diff(angle)
    if not (np.all(steps > 1e-6) or np.all(steps < -1e-6)) or abs(angle[-1] - angle[0]) >= 2 * np.pi:
        raise ValueError("the extended teeth trajectory does not turn steadily around its pseudo-centre "
                         "(the lip ring is not a convex arc); cannot build the palate and floor")


# --- assembling ------------------------------------------------------------------------------------


def _part_faces(num_rings: int, columns: int, with_apex: bool) -> np.ndarray:
    """Faces [P, 3] (local ids: ring r column i -> r * columns + i, apex last) of a ring-strip surface."""
    r, i = np.meshgrid(np.arange(num_rings - 1), np.arange(columns - 1), indexing="ij")
    a = (r * columns + i).ravel()
    b, d = a + 1, a + columns
    c = d + 1
    quads = np.concatenate([np.stack([a, d, c], 1), np.stack([a, c, b], 1)])  # [2Q, 3]
    if not with_apex:
        return quads
    apex = num_rings * columns
    last = (num_rings - 1) * columns + np.arange(columns - 1)
    fan = np.stack([last, np.full_like(last, apex), last + 1], 1)  # same winding as the quads
    return np.concatenate([quads, fan])


def _append(data: HeadModelData, kind: str, line: MouthLine, parts: dict[str, _Part], cfg: MouthConfig,
            info: dict) -> HeadModelData:
    num_v, num_f = data.num_vertices, data.faces.shape[0]
    new_vertices, new_faces, new_shapedirs, groups_v, groups_f = [], [], [], {}, {}
    weights = []
    offset_v, offset_f = num_v, num_f
    col_mean = line.shapedirs.mean(axis=0, keepdims=True)  # [1, 3, S]
    for name, joint in (("upper", NECK_JOINT), ("lower", JAW_JOINT)):
        part: _Part = parts[name]
        columns = len(part.source)
        verts = np.concatenate(part.rings + ([part.apex[None]] if part.apex is not None else []))  # [n, 3]
        faces = _part_faces(len(part.rings), columns, part.apex is not None)
        faces = _orient(faces, verts, part, columns)
        dirs = np.concatenate([line.shapedirs[part.source]] * len(part.rings)
                              + ([col_mean] if part.apex is not None else []))  # [n, 3, S]
        ids = np.arange(offset_v, offset_v + len(verts))
        teeth = ids[: part.teeth_rings * columns]
        groups_v[f"mouth_{name}"] = ids
        groups_v[f"teeth_{name}"] = teeth
        if part.apex is not None:
            groups_v["palate" if name == "upper" else "floor"] = ids[part.teeth_rings * columns - columns:]
        groups_f[f"mouth_{name}"] = np.arange(offset_f, offset_f + len(faces))
        w = np.zeros((len(verts), data.lbs_weights.shape[1]), np.float32)
        w[:, joint] = 1.0
        new_vertices.append(verts)
        new_faces.append(faces + offset_v)
        new_shapedirs.append(dirs)
        weights.append(w)
        offset_v += len(verts)
        offset_f += len(faces)
    groups_f["mouth"] = np.arange(num_f, offset_f)
    added = offset_v - num_v

    posedirs = data.posedirs
    if posedirs is not None:
        posedirs = np.concatenate([posedirs, np.zeros((added, 3, posedirs.shape[2]), posedirs.dtype)])
    info = {"kind": kind, "num_vertices": int(added), "num_faces": int(offset_f - num_f),
            "mouth_width": line.width, "config": asdict(cfg), **info}
    out = data.copy_with(
        v_template=np.concatenate([data.v_template, *new_vertices]).astype(np.float32),
        faces=np.concatenate([data.faces, *new_faces]).astype(np.int64),
        shapedirs=np.concatenate([data.shapedirs, *new_shapedirs]).astype(np.float32),
        exprdirs=np.concatenate([data.exprdirs, np.zeros((added, 3, data.exprdirs.shape[2]), np.float32)]),
        j_regressor=np.concatenate([data.j_regressor, np.zeros((data.j_regressor.shape[0], added), np.float32)], 1),
        lbs_weights=np.concatenate([data.lbs_weights, *weights]).astype(np.float32),
        posedirs=posedirs,
        vertex_groups={**data.vertex_groups, **groups_v},
        face_groups={**data.face_groups, **groups_f},
        metadata={**data.metadata, "mouth": info},
    )
    return out.validate()


def _orient(faces: np.ndarray, verts: np.ndarray, part: _Part, columns: int) -> np.ndarray:
    """Flip the winding of the whole part if its front strip does not face `front_normal`."""
    mid = columns // 2 - 1
    probe = faces[mid]  # first triangle of the front strip at the middle column
    v0, v1, v2 = verts[probe]
    if np.cross(v1 - v0, v2 - v0) @ np.asarray(part.front_normal) < 0:
        return faces[:, ::-1].copy()
    return faces
