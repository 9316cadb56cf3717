"""Faces -> the 10 APS parts: coverage, priority of overlapping regions, the mouth set."""

from typing import get_args

import numpy as np
import pytest

from geoavatar.config import APSPart
from geoavatar.head.mouth import add_mouth_structure
from geoavatar.head.regions import PART_NAMES, PART_REGIONS, face_parts
from head_fakes import head_by_name, procedural_head

HEADS = ["procedural", "flame5023", "openhead"]


def _first_covering_part(data, face):
    """Per-face reference: the first part (priority order) whose regions hold all 3 vertices."""
    for k, name in enumerate(PART_NAMES):
        ids = set()
        for region in PART_REGIONS[name]:
            ids.update(np.asarray(data.regions.get(region, [])).tolist())
        if all(int(v) in ids for v in face):
            return k
    return None


@pytest.fixture(scope="module", params=HEADS)
def head(request):
    return head_by_name(request.param)


def test_ten_parts_cover_every_face_once(head):
    parts = face_parts(head)
    assert parts.part_names == PART_NAMES and parts.num_parts == 10
    assert parts.part_of_face.shape == (len(head.faces),)
    assert parts.part_of_face.min() >= 0 and parts.part_of_face.max() < 10  # no mouth yet: no -1
    counts = parts.counts()
    assert sum(counts.values()) == len(head.faces)
    assert all(n > 0 for n in counts.values()), counts


def test_overlaps_go_to_the_specific_part_and_gaps_to_a_neighbour(head):
    parts = face_parts(head)
    rng = np.random.default_rng(0)
    sample = rng.choice(len(head.faces), size=min(400, len(head.faces)), replace=False)
    uncovered = []
    for f in sample:
        expected = _first_covering_part(head, head.faces[f])
        if expected is None:
            uncovered.append(f)
        else:
            assert parts.part_of_face[f] == expected, (f, PART_NAMES[parts.part_of_face[f]], PART_NAMES[expected])
    # Faces no region covers share their part with an edge-neighbour (or are in a piece with no region).
    edges = {}
    for f, tri in enumerate(head.faces):
        for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])):
            edges.setdefault((min(a, b), max(a, b)), []).append(f)
    for f in uncovered:
        tri = head.faces[f]
        neighbours = {g for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0]))
                      for g in edges[(min(a, b), max(a, b))] if g != f}
        assert parts.part_of_face[f] in parts.part_of_face[list(neighbours)]


def test_procedural_head_has_gaps_and_overlaps_resolved():
    head = procedural_head()
    parts = face_parts(head)
    assert parts.filled_by_neighbours > 0  # the fake leaves a band between neck and scalp uncovered
    lips = parts.faces_of("lips")
    face_ids = set(head.regions["face"].tolist())
    assert all(set(head.faces[f].tolist()) <= face_ids for f in lips)  # lips faces are also in 'face'
    eyeballs = parts.faces_of("eyeballs")
    centres_x = head.v_template[head.faces[eyeballs]].mean(1)[:, 0]
    assert (centres_x > 0).any() and (centres_x < 0).any()  # left and right merged


def test_region_less_pieces_take_the_nearest_part():
    head = procedural_head()
    no_eyes = {k: v for k, v in head.regions.items() if not k.endswith("eyeball")}
    parts = face_parts(head.copy_with(regions=no_eyes))
    assert parts.part_of_face.min() >= 0
    assert len(parts.faces_of("eyeballs")) == 0


@pytest.mark.parametrize("kind", ["geoavatar", "gaussianavatars"])
def test_mouth_faces_are_minus_one_and_the_rest_unchanged(head, kind):
    with_mouth = add_mouth_structure(head, kind)
    before, after = face_parts(head), face_parts(with_mouth)
    mouth = with_mouth.face_groups["mouth"]
    np.testing.assert_array_equal(after.mouth_faces, mouth)
    assert (after.part_of_face[mouth] == -1).all()
    np.testing.assert_array_equal(after.part_of_face[: len(head.faces)], before.part_of_face)
    assert len(after.part_of_face) == len(with_mouth.faces)


def test_head_without_regions_is_refused():
    with pytest.raises(ValueError, match="region"):
        face_parts(procedural_head().copy_with(regions={}))


def test_the_configuration_names_the_same_parts_as_the_head_layer():
    """config.APSPart lists the part names so that a configuration is checked without the head layer."""
    assert get_args(APSPart) == PART_NAMES
