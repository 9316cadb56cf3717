"""Faces -> the 10 parts of the Adaptive Pre-allocation Stage (APS), plus the mouth set F_m.

GeoAvatar splits the head-model faces into n parts using FLAME's vertex masks, and decides per part
whether it is rigid or flexible (paper §3.1). FLAME_masks.pkl has 14 overlapping regions (OpenHead
provides the same names). We form 10 parts by merging the left/right pairs, which should behave
alike under APS and would otherwise only add noise to the per-part mean distance:

    part          regions merged into it                           priority
    eyeballs      left_eyeball, right_eyeball                      1
    lips          lips                                             2
    nose          nose                                             3
    eye_region    eye_region, left_eye_region, right_eye_region    4
    ears          left_ear, right_ear                              5
    forehead      forehead                                         6
    face          face                                             7
    boundary      boundary                                         8
    neck          neck                                             9
    scalp         scalp                                            10

14 regions - 1 (eyeballs) - 1 (ears) - 2 (eye regions) = 10 parts; `boundary` (the rim at the
bottom of the neck, where clothing and shoulders start) stays its own part because it behaves
differently from the neck skin above it.

Rules:
- a face is in a region when all 3 of its vertices are (a part's vertex set is the union of its
  regions);
- regions overlap (e.g. `face` contains nose, lips and the eye regions; `forehead` overlaps face
  and scalp), so a face covered by several parts takes the first in the priority column: specific,
  small parts before broad ones;
- a face covered by no part (it straddles two regions) takes the most common part among its
  edge-neighbours, repeated until every face reached this way has a part; faces in a connected
  piece with no part at all take the part of the nearest assigned face centre;
- mouth-structure faces (`data.face_groups["mouth"]`, the set F_m appended by
  `geoavatar.head.mouth`) get part -1: they are never rigid/flexible, they have their own τ_mouth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from geoavatar.head.base import HeadModelData

# Part name -> the mask regions it is made of. The order is the priority order and the part index.
PART_REGIONS: dict[str, tuple[str, ...]] = {
    "eyeballs": ("left_eyeball", "right_eyeball"),
    "lips": ("lips",),
    "nose": ("nose",),
    "eye_region": ("eye_region", "left_eye_region", "right_eye_region"),
    "ears": ("left_ear", "right_ear"),
    "forehead": ("forehead",),
    "face": ("face",),
    "boundary": ("boundary",),
    "neck": ("neck",),
    "scalp": ("scalp",),
}
PART_NAMES: tuple[str, ...] = tuple(PART_REGIONS)
MOUTH_PART = -1


@dataclass(frozen=True)
class FaceParts:
    part_of_face: np.ndarray  # [F] int64: index into part_names, or -1 for mouth-structure faces
    part_names: tuple[str, ...]  # the 10 part names
    mouth_faces: np.ndarray  # [Fm] int64 face ids of F_m
    filled_by_neighbours: int = 0  # faces that no region covered (assigned from adjacent faces)

    @property
    def num_parts(self) -> int:
        return len(self.part_names)

    def faces_of(self, part: str) -> np.ndarray:
        """Face ids of one part, by name."""
        return np.flatnonzero(self.part_of_face == self.part_names.index(part))

    def counts(self) -> dict[str, int]:
        return {name: int((self.part_of_face == k).sum()) for k, name in enumerate(self.part_names)}


def face_parts(data: HeadModelData) -> FaceParts:
    """Assign every face of `data` to one of the 10 APS parts (-1 for the mouth structure)."""
    faces = np.asarray(data.faces, dtype=np.int64)  # [F, 3]
    num_faces, num_vertices = faces.shape[0], data.num_vertices
    if not data.regions:
        raise ValueError(f"head model '{data.name}' has no region masks; the APS parts are built from them")
    known = {r for regions in PART_REGIONS.values() for r in regions}
    if not known & set(data.regions):
        raise ValueError(f"head model '{data.name}': none of its regions {sorted(data.regions)} is a FLAME mask region")

    mouth_faces = np.asarray(data.face_groups.get("mouth", np.zeros(0, np.int64)), dtype=np.int64)
    is_mouth = np.zeros(num_faces, dtype=bool)
    is_mouth[mouth_faces] = True

    part_of_face = np.full(num_faces, -2, dtype=np.int64)  # -2: not yet assigned
    for k in reversed(range(len(PART_NAMES))):  # lowest priority first, so higher priority overwrites
        in_part = np.zeros(num_vertices, dtype=bool)
        for region in PART_REGIONS[PART_NAMES[k]]:
            ids = data.regions.get(region)
            if ids is not None and len(ids):
                in_part[np.asarray(ids, dtype=np.int64)] = True
        part_of_face[in_part[faces].all(axis=1)] = k
    part_of_face[is_mouth] = MOUTH_PART

    unassigned = int((part_of_face == -2).sum())
    if unassigned:
        part_of_face = _fill_from_neighbours(part_of_face, faces, data.v_template, is_mouth)
    return FaceParts(part_of_face=part_of_face, part_names=PART_NAMES, mouth_faces=mouth_faces,
                     filled_by_neighbours=unassigned)


def _fill_from_neighbours(part_of_face: np.ndarray, faces: np.ndarray, vertices: np.ndarray,
                          is_mouth: np.ndarray) -> np.ndarray:
    """Give unassigned faces (-2) the majority part of their assigned edge-neighbours, repeatedly."""
    part = part_of_face.copy()
    num_parts = len(PART_NAMES)
    pairs = _edge_adjacent_face_pairs(faces)  # [P, 2]
    pairs = pairs[~(is_mouth[pairs[:, 0]] | is_mouth[pairs[:, 1]])]  # the mouth does not spread into the head
    both = np.concatenate([pairs, pairs[:, ::-1]])  # [2P, 2] directed (face, neighbour)
    while True:
        todo = part == -2
        if not todo.any():
            break
        usable = todo[both[:, 0]] & (part[both[:, 1]] >= 0)
        if not usable.any():
            break
        votes = np.zeros((len(part), num_parts), dtype=np.int64)
        np.add.at(votes, (both[usable, 0], part[both[usable, 1]]), 1)
        voted = todo & (votes.sum(axis=1) > 0)
        part[voted] = votes[voted].argmax(axis=1)  # ties: the higher-priority part
    rest = np.flatnonzero(part == -2)
    if rest.size:  # pieces no region touches: nearest assigned face centre
        centres = vertices[faces].mean(axis=1)  # [F, 3]
        assigned = np.flatnonzero(part >= 0)
        if assigned.size == 0:
            raise ValueError("no face of the head model lies inside any region mask")
        d2 = ((centres[rest, None, :] - centres[None, assigned, :]) ** 2).sum(-1)  # [R, A]
        part[rest] = part[assigned[d2.argmin(axis=1)]]
    return part


def _edge_adjacent_face_pairs(faces: np.ndarray) -> np.ndarray:
    """Pairs of faces [P, 2] that share an edge."""
    num_faces = faces.shape[0]
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])  # [3F, 2]
    edges.sort(axis=1)
    owner = np.tile(np.arange(num_faces), 3)
    order = np.lexsort((edges[:, 1], edges[:, 0]))
    edges, owner = edges[order], owner[order]
    same = (edges[1:] == edges[:-1]).all(axis=1)
    # Consecutive equal edges: manifold edges give one pair; non-manifold ones give a chain, enough for adjacency.
    return np.stack([owner[:-1][same], owner[1:][same]], axis=1)


def skull_vertex_ids(head) -> "torch.Tensor":
    """[S] ids of the head's skin without the neck and the mouth structure (every vertex if that left none);
    head: HeadModel or HeadModelData."""
    import torch

    count = int(head.num_vertices)
    keep = torch.ones(count, dtype=torch.bool)
    groups = [head.regions.get("neck")] + [head.vertex_groups.get(g) for g in ("mouth_upper", "mouth_lower")]
    for ids in groups:
        if ids is not None:
            keep[torch.as_tensor(np.asarray(ids), dtype=torch.long)] = False
    if not bool(keep.any()):
        keep[:] = True
    return torch.nonzero(keep).flatten()


def skull_centre(vertices: "torch.Tensor", head) -> "torch.Tensor":
    """[3] centre of a posed head: the bounding-box centre of its skin without the neck and the mouth
    structure, so that a camera turned about it turns about the middle of the skull and face, not
    about a point pulled down toward the shoulders. vertices [V, 3] (the head's vertices first; any
    further ones, e.g. a generated actor's hair, are left out); head: HeadModel or HeadModelData."""
    points = vertices[skull_vertex_ids(head).to(vertices.device)]  # [S, 3]
    return 0.5 * (points.min(dim=0).values + points.max(dim=0).values)
