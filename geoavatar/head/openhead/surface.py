"""OpenHead surface: an implicit head sculpted from smooth primitives, sampled on a ray grid.

The head skin is a star-shaped surface seen from one centre point O (on the midline at the height
of the mouth line); the neck below the jaw is sampled by horizontal rays from the neck axis. It is the zero set of a signed distance-like function built from ellipsoids,
capsules and round cones joined with smooth unions (`head_sdf`). Every vertex is the outermost
crossing of that function along one ray from O; the rays form a latitude/longitude grid whose
spacing is dense on the face and sparse on the back of the head. Because the grid has a row exactly
at the mouth line (a horizontal ray plane through O), the mouth opening is a slit along that row:
its 13 inner vertices are duplicated into an upper-lip and a lower-lip copy, the two corners are
shared. The grid is open at the (horizontal) neck base and closed at the crown by one pole vertex.

Coordinates: metres, +x subject's left, +y up, +z out of the face (FLAME axes). The origin is on the
midline at the height of the ear canals, about 1 cm in front of them (see `OpenHeadShape`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class OpenHeadShape:
    """Generator parameters of the neutral OpenHead (metres). Hashed into the cache key."""

    ray_origin: tuple[float, float, float] = (0.0, -0.048, 0.0)  # O; its height is the mouth line
    eye_centre: tuple[float, float, float] = (0.032, 0.020, 0.066)  # left eyeball centre (right mirrored)
    eyeball_radius: float = 0.0120
    lid_radius: float = 0.0133  # eyelid skin lies on this sphere around the eyeball centre
    fissure_floor_radius: float = 0.0103  # skin inside the eye opening, behind the eyeball
    fissure_half_width: float = 0.0145
    fissure_upper: float = 0.0054  # opening above the eye centre line
    fissure_lower: float = 0.0040
    fissure_tilt: float = 0.08  # outer corner higher than the inner one (dy/dx)
    mouth_half_width: float = 0.0250
    lip_gap: float = 0.0012  # neutral opening at the mid-line, each lip (the mouth is almost closed)
    lip_roll_in: float = 0.0028  # inner lip edge sits this much behind the surface
    lowest_ray_elevation_deg: float = -46.0  # last row of rays from O (under the jaw)
    neck_rows: int = 7  # rows below it, cast horizontally from the neck axis down to the neck base
    neck_base_height: float = -0.19  # the open, horizontal neck ring
    neck_axis_z: float = -0.018
    columns_mouth: int = 14  # intervals between the mouth corners (15 vertices on each lip edge)
    column_step_face_deg: float = 1.7
    column_step_back_deg: float = 8.0
    row_step_face_deg: float = 1.9
    row_step_eyes_deg: float = 1.3
    row_step_skull_deg: float = 5.5
    eyeball_segments: tuple[int, int] = (24, 12)  # around, front-to-back


# --------------------------------------------------------------------------- implicit primitives
def _ellipsoid(p: np.ndarray, c, r) -> np.ndarray:
    """Approximate signed distance to an axis-aligned ellipsoid (negative inside). p [..., 3]."""
    r = np.asarray(r, np.float64)
    q = (p - np.asarray(c, np.float64)) / r
    k0 = np.linalg.norm(q, axis=-1)
    k1 = np.linalg.norm(q / r, axis=-1)
    return k0 * (k0 - 1.0) / np.maximum(k1, 1e-12)


def _round_cone(p: np.ndarray, a, b, ra: float, rb: float) -> np.ndarray:
    """Distance to a capsule whose radius goes linearly from ra (at a) to rb (at b)."""
    a = np.asarray(a, np.float64)
    ab = np.asarray(b, np.float64) - a
    t = np.clip(((p - a) @ ab) / (ab @ ab), 0.0, 1.0)
    closest = a + t[..., None] * ab
    return np.linalg.norm(p - closest, axis=-1) - (ra + (rb - ra) * t)


def _smin(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Smooth union (polynomial smooth minimum, blend width k)."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


def _smax(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    return -_smin(-a, -b, k)


def fissure_outline(s: np.ndarray, shape: OpenHeadShape, openness: float = 1.0):
    """Upper and lower eyelid margins (y offsets from the eye centre) at s = dx / half-width in [-1, 1].

    s is measured towards the outer (lateral) corner. Returns (upper [...], lower [...]).
    """
    s = np.clip(s, -1.0, 1.0)
    bulge = np.maximum(1.0 - s * s, 0.0)
    tilt = shape.fissure_tilt * shape.fissure_half_width * s
    # The upper lid peaks a little medially of the pupil, the lower lid laterally (as in real eyes).
    upper = tilt + openness * shape.fissure_upper * bulge**0.75 * (1.0 - 0.15 * s)
    lower = tilt - openness * shape.fissure_lower * bulge**0.9 * (1.0 + 0.1 * s)
    return upper, lower


def head_sdf(p: np.ndarray, shape: OpenHeadShape) -> np.ndarray:
    """Signed distance-like function of the head skin (negative inside). p [..., 3] -> [...].

    Mirror-symmetric in x. The eyelids are closed here; `open_eyes` cuts the openings on the grid.
    """
    q = np.concatenate([np.abs(p[..., :1]), p[..., 1:]], axis=-1)  # fold onto the left half
    x, y, z = q[..., 0], q[..., 1], q[..., 2]
    d = _ellipsoid(q, (0.0, 0.046, -0.004), (0.075, 0.094, 0.097))  # cranium
    d = _smin(d, _ellipsoid(q, (0.0, 0.010, 0.028), (0.062, 0.072, 0.068)), 0.02)  # upper face / forehead
    d = _smin(d, _ellipsoid(q, (0.0, -0.040, 0.022), (0.058, 0.052, 0.062)), 0.02)  # midface
    d = _smin(d, _ellipsoid(q, (0.0, -0.062, 0.026), (0.050, 0.032, 0.052)), 0.02)  # lower face
    d = _smin(d, _round_cone(q, (0.047, -0.030, -0.008), (0.016, -0.082, 0.058), 0.012, 0.010), 0.018)  # mandible
    d = _smin(d, _ellipsoid(q, (0.0, -0.076, 0.060), (0.020, 0.016, 0.016)), 0.012)  # chin
    # Neck: an elliptic cylinder below the skull, ending in the open base (rays stop above its end).
    neck = (np.sqrt((x / 0.054) ** 2 + ((z + 0.018) / 0.050) ** 2) - 1.0) * 0.05
    d = _smin(d, _smax(neck, y + 0.01, 0.03), 0.03)
    d = _smin(d, _ellipsoid(q, (0.047, 0.002, 0.054), (0.020, 0.014, 0.018)), 0.015)  # cheekbone
    d = _smin(d, _ellipsoid(q, (0.030, -0.030, 0.066), (0.020, 0.018, 0.016)), 0.015)  # cheek
    d = _smin(d, _ellipsoid(q, (0.024, 0.037, 0.080), (0.024, 0.0085, 0.012)), 0.014)  # brow ridge
    # Nose: bridge as a round cone, tip ball, alae (nostril wings), columella.
    d = _smin(d, _round_cone(q, (0.0, 0.024, 0.090), (0.0, -0.018, 0.104), 0.0045, 0.0075), 0.006)
    d = _smin(d, _ellipsoid(q, (0.0, -0.021, 0.1055), (0.0085, 0.0085, 0.0080)), 0.004)  # tip
    d = _smin(d, _ellipsoid(q, (0.0125, -0.026, 0.092), (0.0075, 0.0065, 0.0085)), 0.006)  # ala
    d = _smin(d, _ellipsoid(q, (0.0, -0.028, 0.098), (0.0045, 0.0045, 0.0070)), 0.006)  # columella
    # Lips: upper and lower vermilion, philtrum ridge of the upper lip.
    d = _smin(d, _ellipsoid(q, (0.0, -0.0435, 0.056), (0.0265, 0.0065, 0.0355)), 0.004)
    d = _smin(d, _ellipsoid(q, (0.0, -0.0550, 0.054), (0.0235, 0.0078, 0.0350)), 0.004)
    # Ears: a tilted flat ellipsoid with a rim; the concha is a dent on its outer face.
    ear_c = np.array([0.074, 0.003, -0.010])
    e = q - ear_c
    tilt = np.deg2rad(15.0)
    e = np.stack([e[..., 0], np.cos(tilt) * e[..., 1] + np.sin(tilt) * e[..., 2],
                  -np.sin(tilt) * e[..., 1] + np.cos(tilt) * e[..., 2]], axis=-1)
    ear = _ellipsoid(e, (0.0, 0.0, 0.0), (0.013, 0.031, 0.017))
    d = _smin(d, ear, 0.006)
    d = _smax(d, -_ellipsoid(e, (0.012, -0.004, 0.003), (0.006, 0.011, 0.0085)), 0.003)  # concha
    # Eyes: a shallow socket and the closed lids on a sphere around the eyeball.
    ec = np.asarray(shape.eye_centre)
    d = _smax(d, -_ellipsoid(q, (ec[0], ec[1] + 0.002, ec[2] + 0.028), (0.019, 0.013, 0.0105)), 0.010)
    d = _smin(d, np.linalg.norm(q - ec, axis=-1) - shape.lid_radius, 0.005)
    return d


# --------------------------------------------------------------------------- ray grid
def _symmetric_steps(first_steps: np.ndarray, step_fn, end: float) -> np.ndarray:
    """Angles from 0 to `end` (inclusive): fixed first steps, then steps from step_fn, scaled to land on end."""
    angles = [0.0]
    for s in first_steps:
        angles.append(angles[-1] + s)
    fixed_end = angles[-1]
    free = []
    a = fixed_end
    while a < end - 1e-9:
        s = step_fn(a)
        free.append(s)
        a += s
    free = np.array(free) * (end - fixed_end) / np.sum(free)
    return np.concatenate([angles, fixed_end + np.cumsum(free)])


def column_angles(shape: OpenHeadShape) -> tuple[np.ndarray, int]:
    """Longitudes (radians, 0 = straight ahead, + towards the subject's left) and the index of 0.

    The first `columns_mouth / 2` steps on each side end exactly on the mouth corners.
    """
    o = np.asarray(shape.ray_origin)
    corner_depth = 0.080 - o[2]  # the mouth corner sits about this far in front of O
    theta_corner = np.arctan2(shape.mouth_half_width, corner_depth)
    half = shape.columns_mouth // 2
    mouth_steps = np.full(half, theta_corner / half)
    face, back = np.deg2rad(shape.column_step_face_deg), np.deg2rad(shape.column_step_back_deg)

    def step(a):
        t = np.clip((a - np.deg2rad(40.0)) / np.deg2rad(50.0), 0.0, 1.0)
        return face + (back - face) * t * t * (3 - 2 * t)

    right_half = _symmetric_steps(mouth_steps, step, np.pi)  # 0 .. pi
    # Full circle: -pi (exclusive) .. pi; pi and -pi are the same column (back of the head).
    angles = np.concatenate([-right_half[:0:-1], right_half])[1:]
    zero = int(np.argmin(np.abs(angles)))
    return angles, zero


def row_angles(shape: OpenHeadShape) -> tuple[np.ndarray, int]:
    """Elevations (radians) of the rays from O, bottom up, excluding the crown pole, and the mouth row."""
    face, eyes, skull = (np.deg2rad(a) for a in (shape.row_step_face_deg, shape.row_step_eyes_deg, shape.row_step_skull_deg))

    def step_up(a):  # above the mouth line: face, then the eye band (28..52 deg), then the skull
        if a < np.deg2rad(26.0):
            return face
        if a < np.deg2rad(54.0):
            return eyes
        return skull

    def step_down(a):  # below the mouth line: chin and jaw
        return face

    up = _symmetric_steps(np.array([]), step_up, np.deg2rad(86.0))
    down = _symmetric_steps(np.array([]), step_down, -np.deg2rad(shape.lowest_ray_elevation_deg))
    rows = np.concatenate([-down[::-1], up[1:]])
    return rows, len(down) - 1


def _ray_dirs(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(phi), np.cos(theta) * np.cos(phi)], axis=-1)


def cast_rays(origin: np.ndarray, dirs: np.ndarray, sdf, t_max: float = 0.22, step: float = 0.0025) -> np.ndarray:
    """Distance along each ray to the outermost crossing of sdf (outside > 0 -> inside < 0).

    origin [3] or [N, 3], dirs [N, 3] -> [N]. March inwards from t_max, then bisect.
    """
    n = dirs.shape[0]
    origin = np.broadcast_to(np.asarray(origin, np.float64), (n, 3))
    t_hi = np.full(n, t_max)
    t_lo = np.zeros(n)
    todo = np.arange(n)  # rays whose crossing is not bracketed yet
    t = t_max
    if (sdf(origin + t * dirs) <= 0).any():
        raise RuntimeError("OpenHead generator: t_max does not reach outside the head")
    while t > 0 and len(todo):
        t_next = max(t - step, 0.0)
        inside = sdf(origin[todo] + t_next * dirs[todo]) <= 0
        hit = todo[inside]
        t_hi[hit], t_lo[hit] = t, t_next
        todo = todo[~inside]
        t = t_next
    if len(todo):
        raise RuntimeError(f"OpenHead generator: {len(todo)} rays miss the head surface")
    for _ in range(16):  # bisection: outside at t_hi, inside at t_lo (0.04 micrometre at the end)
        mid = 0.5 * (t_hi + t_lo)
        outside = sdf(origin + mid[:, None] * dirs) > 0
        t_hi = np.where(outside, mid, t_hi)
        t_lo = np.where(outside, t_lo, mid)
    return 0.5 * (t_hi + t_lo)


def open_eyes(grid: np.ndarray, shape: OpenHeadShape) -> np.ndarray:
    """Cut the eye openings into the closed lids of a ray grid [R, C, 3] (returns a new grid).

    Per grid column over an eye, the vertex nearest to the upper and to the lower lid margin
    (`fissure_outline`) is moved onto it (on the lid sphere), and the vertices between them sink to a
    sphere behind the eyeball's front, so the eyeball shows between two clean lid margins.
    """
    grid = grid.copy()
    for side in (1.0, -1.0):
        e = np.asarray(shape.eye_centre) * np.array([side, 1.0, 1.0])
        rel = grid - e  # [R, C, 3]
        s = (side * rel[..., 0] - 0.0015) / shape.fissure_half_width
        upper, lower = fissure_outline(s, shape)
        near = (np.linalg.norm(rel, axis=-1) < 0.02) & (rel[..., 2] > 0)
        for c in np.nonzero((near & (np.abs(s) < 1.0)).any(0))[0]:
            rows = np.nonzero(near[:, c] & (np.abs(s[:, c]) < 1.0))[0]
            y = rel[rows, c, 1]
            top = rows[np.argmin(np.abs(y - upper[rows, c]))]
            bottom = rows[np.argmin(np.abs(y - lower[rows, c]))]
            if top - bottom < 2:  # too close to the corner for an opening in this column
                continue
            for r, margin in ((top, upper[top, c]), (bottom, lower[bottom, c])):
                x = rel[r, c, 0]
                z = np.sqrt(max(shape.lid_radius**2 - x * x - margin * margin, 0.0))
                grid[r, c] = e + np.array([x, margin, z])
            for r in range(bottom + 1, top):
                grid[r, c] = e + rel[r, c] * (shape.fissure_floor_radius / np.linalg.norm(rel[r, c]))
    return grid


@dataclass
class SkinGrid:
    """The skin mesh and its grid bookkeeping (used by rigging, regions and modes)."""

    vertices: np.ndarray  # [V, 3]
    faces: np.ndarray  # [F, 3]
    theta: np.ndarray  # [V] ray longitude of each vertex
    phi: np.ndarray  # [V] ray elevation
    row: np.ndarray  # [V] grid row (-1 for the crown pole)
    col: np.ndarray  # [V] grid column
    lower_lip_copy: np.ndarray  # [V] bool: the duplicated lower-lip edge vertices
    lip_ring_upper: np.ndarray  # [15]
    lip_ring_lower: np.ndarray  # [15]
    mouth_row: int
    num_rows: int
    num_cols: int


def build_skin(shape: OpenHeadShape) -> SkinGrid:
    """Cast the ray grid, split the mouth slit, triangulate (outward-facing, mirror-symmetric diagonals)."""
    thetas, zero_col = column_angles(shape)
    ray_phis, ray_mouth_row = row_angles(shape)
    nc = len(thetas)
    th, ph = np.meshgrid(thetas, ray_phis)  # [R, C]
    origin = np.asarray(shape.ray_origin, np.float64)
    dirs = _ray_dirs(th.ravel(), ph.ravel())
    sdf = lambda p: head_sdf(p, shape)  # noqa: E731
    upper_grid = (origin + cast_rays(origin, dirs, sdf)[:, None] * dirs).reshape(len(ray_phis), nc, 3)
    upper_grid = open_eyes(upper_grid, shape)
    # Neck: horizontal rays from the neck axis, at heights from the lowest ray row down to the base.
    k = np.arange(shape.neck_rows, 0, -1)[:, None] / shape.neck_rows  # bottom (1) .. top (1/N)
    heights = upper_grid[0, :, 1][None] + k * (shape.neck_base_height - upper_grid[0, :, 1][None])  # [N, C]
    neck_dirs = np.broadcast_to(_ray_dirs(thetas, np.zeros(nc))[None], (shape.neck_rows, nc, 3)).reshape(-1, 3)
    neck_origins = np.stack([np.zeros(heights.size), heights.ravel(), np.full(heights.size, shape.neck_axis_z)], -1)
    neck_t = cast_rays(neck_origins, neck_dirs, sdf, t_max=0.12)
    neck_grid = (neck_origins + neck_t[:, None] * neck_dirs).reshape(shape.neck_rows, nc, 3)
    grid = np.concatenate([neck_grid, upper_grid]).reshape(-1, 3)
    phis = np.concatenate([np.full(shape.neck_rows, ray_phis[0]), ray_phis])  # neck rows: bookkeeping only
    th, ph = np.meshgrid(thetas, phis)
    mouth_row = ray_mouth_row + shape.neck_rows
    nr = len(phis)
    pole = origin + cast_rays(origin, np.array([[0.0, 1.0, 0.0]]), sdf)[:, None] * np.array([[0.0, 1.0, 0.0]])

    half = shape.columns_mouth // 2
    mouth_cols = np.arange(zero_col - half, zero_col + half + 1)  # 15 columns, corners at both ends
    inner_cols = mouth_cols[1:-1]
    grid_id = np.arange(nr * nc).reshape(nr, nc)
    pole_id = nr * nc
    lower_ids = pole_id + 1 + np.arange(len(inner_cols))  # lower-lip copies of the slit's inner vertices
    vertices = np.concatenate([grid, pole, grid[grid_id[mouth_row, inner_cols]]], axis=0)
    row = np.concatenate([np.repeat(np.arange(nr), nc), [-1], np.full(len(inner_cols), mouth_row)])
    col = np.concatenate([np.tile(np.arange(nc), nr), [0], inner_cols])
    theta = np.concatenate([th.ravel(), [0.0], thetas[inner_cols]])
    phi = np.concatenate([ph.ravel(), [np.pi / 2], np.zeros(len(inner_cols))])
    lower_copy = np.zeros(len(vertices), bool)
    lower_copy[lower_ids] = True

    # Quads between rows r (below) and r+1 (above); columns wrap around.
    below_lookup = grid_id.copy()  # ids seen by quads *below* the mouth row (their top edge)
    below_lookup[mouth_row, inner_cols] = lower_ids
    faces = []
    for r in range(nr - 1):
        lo = below_lookup[r] if r != mouth_row else grid_id[r]
        hi = below_lookup[r + 1] if r + 1 == mouth_row else grid_id[r + 1]
        for c in range(nc):
            c2 = (c + 1) % nc
            a, b, cc, dd = lo[c], lo[c2], hi[c2], hi[c]  # counter-clockwise seen from outside
            if thetas[c] >= 0:  # mirror the diagonal across the mid-line (symmetric mesh)
                faces += [(a, b, cc), (a, cc, dd)]
            else:
                faces += [(a, b, dd), (b, cc, dd)]
    top = grid_id[nr - 1]
    for c in range(nc):
        faces.append((top[c], top[(c + 1) % nc], pole_id))
    faces = np.asarray(faces, np.int64)

    # Open the mouth a little and roll the inner lip edge into the mouth.
    s = np.linspace(0.0, 1.0, len(mouth_cols))[1:-1]
    profile = np.sin(np.pi * s)  # 0 at the corners
    upper_ids = grid_id[mouth_row, inner_cols]
    vertices[upper_ids, 1] += shape.lip_gap * profile
    vertices[lower_ids, 1] -= shape.lip_gap * profile
    roll = shape.lip_roll_in * profile**0.5
    for ids in (upper_ids, lower_ids):
        radial = vertices[ids] - origin
        radial /= np.linalg.norm(radial, axis=-1, keepdims=True)
        vertices[ids] -= roll[:, None] * radial

    corners = grid_id[mouth_row, mouth_cols[[0, -1]]]
    ring_upper = np.concatenate([[corners[0]], upper_ids, [corners[1]]])
    ring_lower = np.concatenate([[corners[0]], lower_ids, [corners[1]]])
    # Columns with theta < 0 are on the subject's right (x < 0): the rings already run right -> left.
    return SkinGrid(vertices, faces, theta, phi, row, col, lower_copy, ring_upper, ring_lower, mouth_row, nr, nc)


def eyeball_mesh(centre: np.ndarray, radius: float, segments: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A UV sphere with its poles on the gaze axis (+z front pole = pupil centre).

    Returns vertices [N, 3], faces [M, 3] (outward), and polar angle of each vertex from the gaze axis [N].
    """
    n_around, n_polar = segments
    polar = np.linspace(0.0, np.pi, n_polar + 1)[1:-1]
    az = np.arange(n_around) * 2 * np.pi / n_around
    pa, aa = np.meshgrid(polar, az, indexing="ij")  # [P, A]
    dirs = np.stack([np.sin(pa) * np.cos(aa), np.sin(pa) * np.sin(aa), np.cos(pa)], axis=-1).reshape(-1, 3)
    dirs = np.concatenate([[[0, 0, 1.0]], dirs, [[0, 0, -1.0]]])
    angle = np.concatenate([[0.0], pa.ravel(), [np.pi]])
    # The cornea bulges about 0.8 mm in front of the sphere.
    bulge = 0.0008 * np.clip((np.cos(angle) - np.cos(0.6)) / (1 - np.cos(0.6)), 0, 1) ** 0.5
    verts = np.asarray(centre) + dirs * (radius + bulge)[:, None]
    front, back = 0, len(dirs) - 1
    ring = lambda i: 1 + i * n_around + np.arange(n_around)  # noqa: E731
    faces = []
    r0 = ring(0)
    for a in range(n_around):
        faces.append((front, r0[(a + 1) % n_around], r0[a]))
    for i in range(n_polar - 2):
        r, s_ = ring(i), ring(i + 1)
        for a in range(n_around):
            a2 = (a + 1) % n_around
            faces += [(r[a], r[a2], s_[a2]), (r[a], s_[a2], s_[a])]
    rl = ring(n_polar - 2)
    for a in range(n_around):
        faces.append((back, rl[a], rl[(a + 1) % n_around]))
    faces = np.asarray(faces, np.int64)
    # Orient every face outward (the sphere is convex around its centre).
    tri = verts[faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    inward = (normal * (tri.mean(1) - centre)).sum(-1) < 0
    faces[inward] = faces[inward][:, ::-1]
    return verts, faces, angle
