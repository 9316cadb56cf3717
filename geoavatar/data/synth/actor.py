"""The ground-truth actor: the head model with a subject's identity plus geometry it cannot express.

    actor = build_actor(get_subject(0))
    out = actor.model.forward_params(params)        # all actor vertices, posed like the head
    out.vertices[:, :actor.num_head_vertices]       # exactly what the head model gives (same params)

What is added to the head model (with its GeoAvatar mouth structure), all rigged to it so it
animates with the same parameters:

- hair: a shell over the scalp region (extended a little below it by the subject's hairline)
  standing `min_cm..max_cm` off the skin along the vertex normals, higher on the crown, lumpy for
  curly hair, grooved along a side parting; it tapers to 2 mm at its border (no gap, no z-fight).
  Each shell vertex copies the skinning weights, identity/expression bases and pose correctives
  of the scalp vertex it was built from, so the hair follows the head, its shape and the brows.
- ears: the ear regions are scaled and turned about their root (smoothly blended into the head):
  a static change of the template, NOT written to the dataset's static_offset.
- glasses (optional): a rigid frame (two rims, bridge, temple arms) 1.5 cm in front of the eyes,
  skinned entirely to the joint that carries the nose bridge.
- beard (optional): a shell 4-6 mm off the chin, jaw line and upper lip that follows the jaw.

None of this is in the written parameters: the avatar must learn it as offsets of its Gaussians,
which is what GeoAvatar's flexible parts are for (hair, ears, glasses, beard), while the face skin
needs none (rigid).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from geoavatar.data.synth.appearance import MATERIAL_INDEX, MATERIALS, FaceLandmarks
from geoavatar.data.synth.noise import SolidNoise
from geoavatar.data.synth.subjects import Subject, identity_coefficients
from geoavatar.head import load_head_data
from geoavatar.head.base import JOINT_NAMES, HeadModel, HeadModelData

HEAD_MODEL = "openhead"
MOUTH_KIND = "geoavatar"


@dataclass
class Actor:
    subject: Subject
    head: HeadModelData  # the head model the dataset is written for (with its mouth structure)
    data: HeadModelData  # head + ear change + hair/beard/glasses
    model: HeadModel  # LBS over `data`
    shape: np.ndarray  # [S] the subject's identity coefficients
    num_head_vertices: int  # vertices of the head model with its mouth (they come first)
    num_model_vertices: int  # vertices of the head model without the mouth (the static_offset size)
    canonical: np.ndarray  # [V, 3] rest positions with the subject's identity (texture coordinates)
    materials: np.ndarray  # [V, M] material weights per vertex (rows sum to 1)
    landmarks: FaceLandmarks
    part_of_vertex: np.ndarray  # [V] index into PARTS; -1 hidden (joint compensation)
    shell_edge: np.ndarray  # [V] distance to the border of the hair/beard shell (metres), 1.0 elsewhere
    cavity_faces: np.ndarray  # [F] bool: faces whose back side is the inside of the head (mouth cavity)
    mouth_faces: np.ndarray  # [F] bool: mouth-structure faces
    info: dict = field(default_factory=dict)

    PARTS = ("head", "hair", "beard", "glasses", "tongue")

    @property
    def faces(self) -> np.ndarray:
        return self.data.faces


# --- mesh helpers (numpy) ---------------------------------------------------------------------


def _faces_within(faces: np.ndarray, vertex_mask: np.ndarray) -> np.ndarray:
    return np.flatnonzero(vertex_mask[faces].all(axis=1))


def _vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    tri = vertices[faces]
    face_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(normals, faces[:, k], face_n)
    return normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)


def _edge_graph(vertices: np.ndarray, faces: np.ndarray):
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    lengths = np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)
    n = len(vertices)
    graph = coo_matrix((np.concatenate([lengths, lengths]), (np.concatenate([edges[:, 0], edges[:, 1]]),
                                                              np.concatenate([edges[:, 1], edges[:, 0]]))), shape=(n, n))
    return graph.tocsr()


def _boundary_vertices(faces: np.ndarray) -> np.ndarray:
    """Vertices on edges used by exactly one face."""
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    return np.unique(unique[counts == 1])


def _distance_from(vertices: np.ndarray, faces: np.ndarray, sources: np.ndarray) -> np.ndarray:
    """Geodesic (edge-path) distance [V] of every vertex to the nearest source vertex (inf if unreachable)."""
    if len(sources) == 0:
        return np.full(len(vertices), np.inf)
    graph = _edge_graph(vertices, faces)
    return dijkstra(graph, directed=False, indices=np.asarray(sources), min_only=True)


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _region(data: HeadModelData, *names: str) -> np.ndarray:
    mask = np.zeros(data.num_vertices, bool)
    for name in names:
        if name not in data.regions:
            raise ValueError(f"head model '{data.name}' has no region '{name}' (the synthetic actor needs it)")
        mask[np.asarray(data.regions[name])] = True
    return mask


# --- the pieces ---------------------------------------------------------------------------------


def _landmarks(data: HeadModelData, rest: np.ndarray) -> FaceLandmarks:
    centres, radii = [], []
    for name in ("left_eyeball", "right_eyeball"):
        ids = np.asarray(data.regions[name])
        pts = rest[ids]
        lo, hi = pts.min(0), pts.max(0)
        centre = 0.5 * (lo + hi)
        centres.append(centre)
        radii.append(float(np.linalg.norm(pts - centre, axis=1).mean()))
    upper, lower = np.asarray(data.lip_ring_upper), np.asarray(data.lip_ring_lower)
    mouth = 0.5 * (rest[upper].mean(0) + rest[lower].mean(0))
    arch = mouth.copy()
    if "mouth" in data.metadata and "pseudo_centre_xz" in data.metadata["mouth"]:
        cx, cz = data.metadata["mouth"]["pseudo_centre_xz"]
        arch = np.array([cx, mouth[1], cz])
    else:
        arch[2] -= 0.03
    face = _region(data, "face") if "face" in data.regions else np.ones(len(rest), bool)
    nose_ids = np.asarray(data.regions["nose"]) if "nose" in data.regions else np.flatnonzero(face)
    nose_tip = rest[nose_ids[np.argmax(rest[nose_ids, 2])]]
    head_ids = np.flatnonzero(_region(data, "scalp"))
    top = rest[head_ids]
    head_centre = np.array([0.0, 0.5 * (top[:, 1].max() + np.mean([c[1] for c in centres])),
                            0.5 * (top[:, 2].max() + top[:, 2].min())])
    return FaceLandmarks(
        eye_centres=np.stack(centres).astype(np.float32), eye_radius=float(np.mean(radii)),
        mouth_centre=mouth.astype(np.float32), mouth_arch_centre=arch.astype(np.float32),
        head_centre=head_centre.astype(np.float32), nose_tip=nose_tip.astype(np.float32),
    )


def _ear_offsets(data: HeadModelData, rest: np.ndarray, subject: Subject) -> np.ndarray:
    """Static per-vertex change [V, 3] of both ears: scale + turn about the ear root, blended in."""
    change = subject.ears
    offsets = np.zeros_like(rest)
    skin_faces = data.faces[: _num_skin_faces(data)]
    for name, sign in (("left_ear", 1.0), ("right_ear", -1.0)):
        mask = _region(data, name)
        ids = np.flatnonzero(mask)
        region_faces = skin_faces[_faces_within(skin_faces, mask)]
        border = _boundary_vertices(region_faces)
        # How far inside the ear each vertex is (0 at the join with the head -> 1 beyond 1 cm).
        dist = _distance_from(rest, region_faces, border)
        weight = _smoothstep(dist[ids] / 0.01)
        root = rest[border].mean(0)
        angle = math.radians(change.turn_out_deg) * -sign  # turns the back of the ear away from the head
        c, s = math.cos(angle), math.sin(angle)
        rot = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
        rel = rest[ids] - root
        moved = root + change.scale * rel @ rot.T
        shift = np.array(change.shift_cm) * 0.01 * np.array([sign, 1.0, 1.0])
        offsets[ids] = weight[:, None] * (moved + shift - rest[ids])
    return offsets


def _num_skin_faces(data: HeadModelData) -> int:
    """Faces before the mouth structure (the mouth faces are appended last)."""
    mouth = data.face_groups.get("mouth")
    return int(np.min(mouth)) if mouth is not None and len(mouth) else len(data.faces)


@dataclass
class _Shell:
    source: np.ndarray  # [n] head vertex each shell vertex copies
    positions: np.ndarray  # [n, 3] rest positions (subject identity applied)
    faces: np.ndarray  # [f, 3] local ids
    edge: np.ndarray  # [n] distance to the shell's border (metres, along the surface)


def _shell(rest: np.ndarray, faces: np.ndarray, vertex_mask: np.ndarray, thickness_fn) -> _Shell:
    """Offset surface over the faces inside vertex_mask; thickness_fn(points, dist_to_border) -> [n] metres."""
    face_ids = _faces_within(faces, vertex_mask)
    if len(face_ids) == 0:
        raise ValueError("the shell region has no faces")
    sub = faces[face_ids]
    used = np.unique(sub)
    local = np.full(len(rest), -1, np.int64)
    local[used] = np.arange(len(used))
    normals = _vertex_normals(rest, faces)[used]
    border = _boundary_vertices(sub)
    dist = _distance_from(rest, sub, border)[used]
    dist = np.where(np.isfinite(dist), dist, 1.0)
    thickness = thickness_fn(rest[used], dist)
    positions = rest[used] + normals * thickness[:, None]
    return _Shell(source=used, positions=positions, faces=local[sub], edge=dist)


def _hair_shell(data: HeadModelData, rest: np.ndarray, subject: Subject, marks: FaceLandmarks) -> _Shell:
    style = subject.hair
    skin_faces = data.faces[: _num_skin_faces(data)]
    scalp = _region(data, "scalp")
    # Over the temples, sides and back the hair reaches hairline_drop below the scalp region (the
    # forehead keeps the region's hairline); never onto eyes, ears, nose or lips.
    dist = _distance_from(rest, skin_faces, np.flatnonzero(scalp))
    sides = (np.abs(rest[:, 0]) > 0.045) | (rest[:, 2] < 0.04)
    mask = scalp | ((dist < style.hairline_drop_cm * 0.01) & sides)
    # The ear regions are generous (skin around the ear too): the ear proper is the region's
    # interior (> 8 mm inside its border). Hair covers the sides above and behind it, not the ear.
    proper = []
    for name in ("left_ear", "right_ear"):
        region = _region(data, name)
        region_faces = skin_faces[_faces_within(skin_faces, region)]
        inside = _distance_from(rest, region_faces, _boundary_vertices(region_faces))
        proper.append(np.flatnonzero(region & (inside > 0.008)))
    proper = np.concatenate(proper)
    ear_top, ear_back = float(rest[proper, 1].max()), float(rest[proper, 2].min())
    eye_outer = float(np.abs(marks.eye_centres[:, 0]).max()) + 0.022
    mouth_y = float(marks.mouth_centre[1])
    eye_y, eye_z = float(marks.eye_centres[:, 1].mean()), float(marks.eye_centres[:, 2].mean())
    temples = (np.abs(rest[:, 0]) > eye_outer) & (rest[:, 2] < eye_z - 0.015) & (rest[:, 1] > eye_y + 0.004)
    mask |= temples | ((np.abs(rest[:, 0]) > eye_outer) & (rest[:, 1] > ear_top - 0.004))
    mask |= (np.abs(rest[:, 0]) > 0.05) & (rest[:, 2] < ear_back + 0.01) & (rest[:, 1] > mouth_y)  # behind the ears
    mask &= ~(_distance_from(rest, skin_faces, proper) < 0.006)
    for name in ("left_eyeball", "right_eyeball", "left_eye_region", "right_eye_region", "nose", "lips"):
        if name in data.regions:
            mask[np.asarray(data.regions[name])] = False
    eye_y = float(marks.eye_centres[:, 1].mean())
    noise = SolidNoise(subject.texture_seed * 13 + 7, smoothing=1.5)
    top_y = float(rest[scalp, 1].max())

    def thickness(points: np.ndarray, border_dist: np.ndarray) -> np.ndarray:
        height = _smoothstep((points[:, 1] - eye_y) / max(top_y - eye_y, 1e-3))  # 0 at eye level, 1 on top
        t = style.min_cm + (style.max_cm - style.min_cm) * height
        lumps = noise(torch.from_numpy(points.astype(np.float32)), 30.0 if style.curl > 0.5 else 15.0).numpy()
        t = t * (1.0 + style.lumpiness * np.clip(lumps, -2.0, 2.0) * 0.5)
        if style.part_x is not None:
            groove = np.exp(-0.5 * ((points[:, 0] - style.part_x) / 0.005) ** 2)
            on_top = _smoothstep((points[:, 1] - (top_y - 0.06)) / 0.03) * (points[:, 2] > marks.head_centre[2] - 0.02)
            t = t * (1.0 - 0.45 * groove * on_top)
        t = np.clip(t, style.min_cm * 0.5, style.max_cm * 1.2) * 0.01
        taper = _smoothstep(border_dist / 0.025)
        return np.maximum(0.002, t * taper)

    return _shell(rest, skin_faces, mask, thickness)


def _beard_shell(data: HeadModelData, rest: np.ndarray, subject: Subject, marks: FaceLandmarks) -> _Shell:
    skin_faces = data.faces[: _num_skin_faces(data)]
    mouth = marks.mouth_centre
    upper, lower = np.asarray(data.lip_ring_upper), np.asarray(data.lip_ring_lower)
    half_width = 0.5 * float(rest[upper, 0].max() - rest[upper, 0].min())
    p = rest
    ear_z = float(np.mean([rest[np.asarray(data.regions[n]), 2].mean() for n in ("left_ear", "right_ear")]))
    below = (p[:, 1] < mouth[1] - 0.007) & (p[:, 1] > mouth[1] - 0.085)
    cheeks = (p[:, 1] < mouth[1] + 0.012) & (np.abs(p[:, 0]) > half_width + 0.01)
    moustache = (p[:, 1] > mouth[1] + 0.005) & (p[:, 1] < mouth[1] + 0.017) & (np.abs(p[:, 0]) < half_width + 0.006)
    mask = (below | cheeks | moustache) & (p[:, 2] > ear_z + 0.015) & (p[:, 1] > mouth[1] - 0.085)
    for name in ("lips", "left_ear", "right_ear", "nose", "left_eyeball", "right_eyeball"):
        if name in data.regions:
            mask[np.asarray(data.regions[name])] = False
    # Keep the beard off the lip rings themselves (the mouth opening).
    mask[upper] = False
    mask[lower] = False
    noise = SolidNoise(subject.texture_seed * 13 + 9, smoothing=1.5)

    def thickness(points: np.ndarray, border_dist: np.ndarray) -> np.ndarray:
        lumps = noise(torch.from_numpy(points.astype(np.float32)), 40.0).numpy()
        t = (0.005 + 0.0012 * np.clip(lumps, -2, 2)) * _smoothstep(border_dist / 0.012)
        return np.maximum(0.0015, t)

    return _shell(rest, skin_faces, mask, thickness)


def _tube(path: np.ndarray, radius: float, sides: int = 6, closed: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """A tube [n*sides, 3] with faces around a polyline path [n, 3] (parallel-transport frames)."""
    n = len(path)
    tangents = np.gradient(path, axis=0) if not closed else (np.roll(path, -1, 0) - np.roll(path, 1, 0))
    tangents /= np.linalg.norm(tangents, axis=1, keepdims=True)
    ref = np.array([0.0, 0.0, 1.0]) if abs(tangents[0, 2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    normal = np.cross(tangents[0], ref)
    normal /= np.linalg.norm(normal)
    rings = []
    for i in range(n):
        normal = normal - tangents[i] * (normal @ tangents[i])
        normal /= np.linalg.norm(normal)
        binormal = np.cross(tangents[i], normal)
        angles = 2 * np.pi * np.arange(sides) / sides
        rings.append(path[i] + radius * (np.cos(angles)[:, None] * normal + np.sin(angles)[:, None] * binormal))
    vertices = np.concatenate(rings)
    segments = n if closed else n - 1
    faces = []
    for i in range(segments):
        j = (i + 1) % n
        for k in range(sides):
            a, b = i * sides + k, i * sides + (k + 1) % sides
            c, d = j * sides + (k + 1) % sides, j * sides + k
            faces += [[a, b, c], [a, c, d]]
    return vertices, np.asarray(faces, np.int64)


def _glasses(data: HeadModelData, rest: np.ndarray, marks: FaceLandmarks) -> tuple[np.ndarray, np.ndarray, int]:
    """Rigid frame vertices [n, 3], faces [f, 3] (local) and the head vertex it is anchored to."""
    eyes = marks.eye_centres.astype(np.float64)
    r = marks.eye_radius
    lens_z = float(eyes[:, 2].mean()) + r + 0.013
    half_w, half_h = 0.025, 0.018
    parts_v, parts_f, count = [], [], 0

    def add(vertices, faces):
        nonlocal count
        parts_v.append(vertices)
        parts_f.append(faces + count)
        count += len(vertices)

    t = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    # A rounded rectangle (superellipse) per eye, slightly wrapped around the face.
    rim_points = {}
    for side in (0, 1):
        c = eyes[side]
        x = np.sign(np.cos(t)) * np.abs(np.cos(t)) ** 0.6 * half_w
        y = np.sign(np.sin(t)) * np.abs(np.sin(t)) ** 0.6 * half_h
        sx = np.sign(c[0])
        z = lens_z - 0.08 * (sx * x) ** 2 / half_w - 0.004 * (sx * x > 0) * (sx * x / half_w) ** 2
        path = np.stack([c[0] + x, c[1] + 0.002 + y, z], axis=1)
        rim_points[side] = path
        add(*_tube(path, 0.0016, closed=True))
    # Bridge between the inner rim points.
    inner = [rim_points[s][np.argmin(np.abs(rim_points[s][:, 0]))] for s in (0, 1)]
    bridge = np.stack([inner[0] + (inner[1] - inner[0]) * u + np.array([0, 0.004 * math.sin(math.pi * u), 0.002])
                       for u in np.linspace(0, 1, 8)])
    add(*_tube(bridge, 0.0014))
    # Temple arms from the outer rim points back to above the ears, just outside the head.
    skin = rest[: data.num_vertices]
    for side in (0, 1):
        outer = rim_points[side][np.argmax(np.abs(rim_points[side][:, 0]))]
        ear = np.asarray(data.regions["left_ear" if side == 0 else "right_ear"])
        ear_top = rest[ear][np.argmax(rest[ear, 1])]
        sx = np.sign(outer[0])
        band = np.abs(skin[:, 1] - outer[1]) < 0.015
        band &= skin[:, 2] > ear_top[2] - 0.005
        for name in ("left_ear", "right_ear"):
            band[np.asarray(data.regions[name])] = False
        head_half = float(np.abs(skin[band, 0]).max()) if band.any() else abs(outer[0])
        arm_x = sx * (head_half + 0.004)
        hinge = np.array([arm_x, outer[1], outer[2] - 0.006])
        end = np.array([arm_x, ear_top[1] + 0.002, ear_top[2] - 0.01])
        path = np.concatenate([np.linspace(outer, hinge, 4)[:-1], np.linspace(hinge, end, 10)])
        path = np.concatenate([path, [end + np.array([0.0, -0.015, -0.012])]])
        add(*_tube(path, 0.0015))
    vertices = np.concatenate(parts_v)
    faces = np.concatenate(parts_f)
    # The anchor: the head vertex closest to the bridge (on the nose).
    bridge_mid = bridge[len(bridge) // 2]
    anchor = int(np.argmin(np.linalg.norm(skin - bridge_mid, axis=1)))
    return vertices, faces, anchor


def _tongue(head: HeadModelData, rest: np.ndarray, shape: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A tongue lying on the mouth floor (flattened ellipsoid inside the lower teeth arch), rigid on the jaw.

    Returns rest vertices [n, 3], faces [f, 3] (local) and the identity basis [n, 3, S] (the floor's mean).
    """
    floor = np.asarray(head.vertex_groups["floor"])
    teeth = np.asarray(head.vertex_groups["teeth_lower"])
    pts = rest[floor]
    x_half = 0.5 * (pts[:, 0].max() - pts[:, 0].min())
    z_front, z_back = float(rest[teeth, 2].max()), float(pts[:, 2].min())
    floor_y = float(pts[:, 1].mean())
    top_y = float(rest[teeth, 1].max())  # the lower teeth's biting edge
    half = np.array([0.62 * x_half, 0.45 * (top_y - floor_y) + 0.002, 0.5 * (z_front - z_back) * 0.8])
    centre = np.array([0.0, floor_y + half[1] * 0.7, z_front - 0.012 - half[2]])
    rings, around = 9, 16
    theta = np.linspace(0.0, np.pi, rings + 2)[1:-1]  # without the poles
    phi = np.linspace(0.0, 2 * np.pi, around, endpoint=False)
    # The long axis along z: poles at the tip (front) and the root (back).
    t, p = np.meshgrid(theta, phi, indexing="ij")
    unit = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1).reshape(-1, 3)
    vertices = np.concatenate([unit, [[0, 0, 1.0]], [[0, 0, -1.0]]]) * half + centre
    faces = []
    for r in range(rings - 1):
        for k in range(around):
            a, b = r * around + k, r * around + (k + 1) % around
            c, d = b + around, a + around
            faces += [[a, c, b], [a, d, c]]
    tip, root = rings * around, rings * around + 1
    last = (rings - 1) * around
    for k in range(around):
        faces.append([tip, k, (k + 1) % around])
        faces.append([root, last + (k + 1) % around, last + k])
    faces = np.asarray(faces, np.int64)
    # Outward winding (checked on the whole mesh: the signed volume must be positive).
    tri = vertices[faces] - centre
    if np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() < 0:
        faces = faces[:, ::-1].copy()
    dirs = np.repeat(head.shapedirs[floor].mean(0, keepdims=True), len(vertices), 0)
    return vertices, faces, dirs


# --- assembling the actor -----------------------------------------------------------------------


def _materials_of_head(data: HeadModelData) -> np.ndarray:
    m = np.zeros((data.num_vertices, len(MATERIALS)), np.float32)
    m[:, MATERIAL_INDEX["skin"]] = 1.0

    def assign(ids, name):
        ids = np.asarray(ids, np.int64)
        m[ids] = 0.0
        m[ids, MATERIAL_INDEX[name]] = 1.0

    assign(data.regions["lips"], "lips")
    assign(data.regions["left_eyeball"], "eyeball")
    assign(data.regions["right_eyeball"], "eyeball")
    groups = data.vertex_groups
    for name in ("teeth_upper", "teeth_lower"):
        if name in groups:
            assign(groups[name], "teeth")
    if "palate" in groups:
        assign(groups["palate"], "gums")
    if "floor" in groups:
        assign(groups["floor"], "tongue")
    return m


@lru_cache(maxsize=1)
def default_head() -> HeadModelData:
    """OpenHead with the GeoAvatar mouth structure (loaded once per process; treat as read-only)."""
    return load_head_data(HEAD_MODEL, mouth=MOUTH_KIND)


@lru_cache(maxsize=4)
def actor_for_subject(index: int) -> "Actor":
    """build_actor of subject `index` on the default head, built once per process (read-only)."""
    from geoavatar.data.synth.subjects import get_subject

    return build_actor(get_subject(index))


@dataclass
class _Piece:
    """Vertices appended to the head model's: a hair or beard shell, the glasses, the tongue, or the joint
    compensators (in no face). Bases a piece leaves out (None) are zero: no expression, no pose correctives."""

    template: np.ndarray  # [n, 3] template space: rest minus the identity part
    rest: np.ndarray  # [n, 3] rest positions with the subject's identity (the appearance's canonical space)
    shapedirs: np.ndarray  # [n, 3, S]
    lbs_weights: np.ndarray  # [n, J]
    materials: np.ndarray  # [n, M]
    part: int  # index into Actor.PARTS; -1 hidden
    faces: np.ndarray | None = None  # [f, 3] ids within the piece; None: in no face
    exprdirs: np.ndarray | None = None  # [n, 3, E]
    posedirs: np.ndarray | None = None  # [n, 3, P]
    edge: np.ndarray | None = None  # [n] distance to a shell's border (metres); None: 1.0

    def __len__(self) -> int:
        return len(self.rest)


def _material_rows(n: int, material: int) -> np.ndarray:
    """[n, M] one-hot rows of material index `material`."""
    rows = np.zeros((n, len(MATERIALS)), np.float32)
    rows[:, material] = 1.0
    return rows


def _rigid_weights(n: int, joint: int) -> np.ndarray:
    """[n, J] skinning weights moving n vertices rigidly with one joint."""
    weights = np.zeros((n, len(JOINT_NAMES)), np.float32)
    weights[:, joint] = 1.0
    return weights


class _Assembly:
    """The actor's vertex arrays: the head model's (with the ear change) first, then each piece added in turn."""

    def __init__(self, head: HeadModelData, ear_offset: np.ndarray, rest_head: np.ndarray):
        self.head = head
        num_head = head.num_vertices
        self.template, self.rest, self.faces = [head.v_template + ear_offset], [rest_head], [head.faces]
        self.shapedirs, self.exprdirs, self.lbs = [head.shapedirs], [head.exprdirs], [head.lbs_weights]
        self.posedirs = [head.posedirs] if head.posedirs is not None else None
        self.materials, self.part, self.edges = [_materials_of_head(head)], [np.zeros(num_head, np.int64)], \
            [np.ones(num_head)]
        self.count = num_head  # vertices so far

    def add(self, piece: _Piece) -> None:
        n, head = len(piece), self.head
        self.template.append(piece.template)
        self.rest.append(piece.rest)
        if piece.faces is not None:
            self.faces.append(piece.faces + self.count)
        self.shapedirs.append(piece.shapedirs)
        self.exprdirs.append(piece.exprdirs if piece.exprdirs is not None else
                             np.zeros((n, 3, head.exprdirs.shape[-1]), np.float32))
        self.lbs.append(piece.lbs_weights)
        if self.posedirs is not None:
            self.posedirs.append(piece.posedirs if piece.posedirs is not None else
                                 np.zeros((n, 3, head.posedirs.shape[-1]), np.float32))
        self.materials.append(piece.materials)
        self.part.append(np.full(n, piece.part, np.int64))
        self.edges.append(piece.edge if piece.edge is not None else np.ones(n))
        self.count += n

    def head_model_data(self, name: str, regressor_extra: np.ndarray, info: dict) -> HeadModelData:
        """The head model's data grown by the pieces; regressor_extra [J, added vertices] (the compensators')."""
        head = self.head
        return head.copy_with(
            name=name,
            v_template=np.concatenate(self.template).astype(np.float32),
            faces=np.concatenate(self.faces).astype(np.int64),
            shapedirs=np.concatenate(self.shapedirs).astype(np.float32),
            exprdirs=np.concatenate(self.exprdirs).astype(np.float32),
            j_regressor=np.concatenate([head.j_regressor, regressor_extra], 1),
            lbs_weights=np.concatenate(self.lbs).astype(np.float32),
            posedirs=None if self.posedirs is None else np.concatenate(self.posedirs).astype(np.float32),
            metadata={**head.metadata, "synth_actor": info},
        )


def _shell_piece(head: HeadModelData, name: str, shell: _Shell, shape: np.ndarray) -> _Piece:
    """A hair or beard shell: each vertex copies the bases and skinning of the head vertex it was built from."""
    source = shell.source
    identity = np.einsum("vcs,s->vc", head.shapedirs[source], shape)  # [n, 3]
    return _Piece(template=shell.positions - identity, rest=shell.positions, shapedirs=head.shapedirs[source],
                  lbs_weights=head.lbs_weights[source], materials=_material_rows(len(source), MATERIAL_INDEX[name]),
                  part=Actor.PARTS.index(name), faces=shell.faces, exprdirs=head.exprdirs[source],
                  posedirs=head.posedirs[source] if head.posedirs is not None else None, edge=shell.edge)


def _shell_info(name: str, shell: _Shell, rest_head: np.ndarray) -> dict:
    """How far a shell stands off the skin (cm: min, median, max) and its vertex count, for the dataset's notes."""
    offsets = np.linalg.norm(shell.positions - rest_head[shell.source], axis=1)
    return {f"{name}_offset_cm": [float(offsets.min() * 100), float(np.percentile(offsets, 50) * 100),
                                  float(offsets.max() * 100)],
            f"{name}_vertices": int(len(shell.source))}


def _glasses_piece(head: HeadModelData, rest_head: np.ndarray, marks: FaceLandmarks, shape: np.ndarray) -> _Piece:
    """The glasses frame, rigid on the main joint of the vertex it hangs from, with that vertex's identity."""
    vertices, faces, anchor = _glasses(head, rest_head, marks)
    n = len(vertices)
    identity = np.einsum("cs,s->c", head.shapedirs[anchor], shape)  # [3]
    return _Piece(template=vertices - identity, rest=vertices, shapedirs=np.repeat(head.shapedirs[anchor][None], n, 0),
                  lbs_weights=_rigid_weights(n, int(np.argmax(head.lbs_weights[anchor]))),
                  materials=_material_rows(n, MATERIAL_INDEX["glasses"]), part=Actor.PARTS.index("glasses"),
                  faces=faces)


def _tongue_piece(head: HeadModelData, rest_head: np.ndarray, shape: np.ndarray) -> _Piece:
    """The tongue on the mouth floor, rigid on the jaw."""
    vertices, faces, dirs = _tongue(head, rest_head, shape)
    n = len(vertices)
    return _Piece(template=vertices - np.einsum("vcs,s->vc", dirs, shape), rest=vertices, shapedirs=dirs,
                  lbs_weights=_rigid_weights(n, JOINT_NAMES.index("jaw")),
                  materials=_material_rows(n, MATERIAL_INDEX["tongue"]), part=Actor.PARTS.index("tongue"), faces=faces)


def _joint_compensators(head: HeadModelData, ear_offset: np.ndarray, appended: int) -> tuple[_Piece | None, np.ndarray]:
    """(hidden vertices, the joint regressor's columns for every vertex appended to the head [J, appended + n]).

    The head model's joint regressor also reads some ear vertices; one hidden vertex per joint (in no face,
    regressor weight 1, rest position = minus the ears' contribution) cancels the ear change there, so the
    actor's joints are exactly the head model's for every identity."""
    ear_shift = head.j_regressor @ ear_offset  # [J, 3]
    compensate = np.flatnonzero(np.abs(ear_shift).max(axis=1) > 0)
    n = len(compensate)
    regressor_extra = np.zeros((head.j_regressor.shape[0], appended + n), np.float32)
    if n == 0:
        return None, regressor_extra
    regressor_extra[compensate, appended + np.arange(n)] = 1.0
    piece = _Piece(template=-ear_shift[compensate], rest=-ear_shift[compensate],
                   shapedirs=np.zeros((n, 3, head.shapedirs.shape[-1]), np.float32), lbs_weights=_rigid_weights(n, 0),
                   materials=_material_rows(n, 0), part=-1)
    return piece, regressor_extra


def _rest_head(head: HeadModelData, subject: Subject, shape: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rest positions [V, 3] with the subject's identity and ears, the ear change [V, 3]): the ears are a static
    change of the template (and so of the rest pose)."""
    rest = head.v_template + np.einsum("vcs,s->vc", head.shapedirs, shape)  # [V, 3]
    ear_offset = _ear_offsets(head, rest, subject)  # [V, 3]
    return rest + ear_offset, ear_offset


def _mouth_and_cavity_faces(head: HeadModelData, num_faces: int) -> tuple[np.ndarray, np.ndarray]:
    """[F] bool masks over the actor's faces: the mouth structure's, and the head's other faces (whose back side
    is the inside of the head)."""
    mouth = np.zeros(num_faces, bool)
    if "mouth" in head.face_groups:
        mouth[np.asarray(head.face_groups["mouth"])] = True
    cavity = np.zeros(num_faces, bool)
    num_faces_head = len(head.faces)
    cavity[:num_faces_head] = ~mouth[:num_faces_head]
    return mouth, cavity


def _model_vertex_count(head: HeadModelData) -> int:
    """Vertices of the head model before its mouth structure (the mouth groups' vertices come last)."""
    groups = [np.asarray(v) for k, v in head.vertex_groups.items() if k.startswith("mouth_")]
    mouth = np.concatenate(groups) if groups else np.zeros(0, np.int64)
    return int(mouth.min()) if len(mouth) else head.num_vertices


def build_actor(subject: Subject, head: HeadModelData | None = None) -> Actor:
    """The rigged ground-truth actor of `subject` (deterministic): the head with the subject's identity and ears,
    then its hair (and beard) shells, glasses, tongue and the hidden joint compensators appended."""
    head = default_head() if head is None else head
    shape = identity_coefficients(subject, head.shapedirs.shape[-1])
    rest_head, ear_offset = _rest_head(head, subject, shape)
    marks = _landmarks(head, rest_head)
    info: dict = {"ear_offset_max_mm": float(np.linalg.norm(ear_offset, axis=1).max() * 1000)}
    assembly = _Assembly(head, ear_offset, rest_head)
    shells = [("hair", _hair_shell(head, rest_head, subject, marks))]
    if subject.beard:
        shells.append(("beard", _beard_shell(head, rest_head, subject, marks)))
    for name, shell in shells:
        assembly.add(_shell_piece(head, name, shell, shape))
        info.update(_shell_info(name, shell, rest_head))
    if subject.glasses:
        glasses = _glasses_piece(head, rest_head, marks, shape)
        assembly.add(glasses)
        info["glasses_vertices"] = len(glasses)
    if "floor" in head.vertex_groups:
        assembly.add(_tongue_piece(head, rest_head, shape))
    compensators, regressor_extra = _joint_compensators(head, ear_offset, assembly.count - head.num_vertices)
    if compensators is not None:
        assembly.add(compensators)
    data = assembly.head_model_data(f"{head.name}+synth{subject.index}", regressor_extra, info)
    mouth_faces, cavity_faces = _mouth_and_cavity_faces(head, len(data.faces))
    return Actor(
        subject=subject, head=head, data=data, model=HeadModel(data), shape=shape, num_head_vertices=head.num_vertices,
        num_model_vertices=_model_vertex_count(head), canonical=np.concatenate(assembly.rest).astype(np.float32),
        materials=np.concatenate(assembly.materials), landmarks=marks, part_of_vertex=np.concatenate(assembly.part),
        shell_edge=np.concatenate(assembly.edges).astype(np.float32),
        cavity_faces=cavity_faces, mouth_faces=mouth_faces, info=info,
    )


__all__ = ["Actor", "build_actor", "actor_for_subject", "default_head", "HEAD_MODEL", "MOUTH_KIND"]
