"""Novel views (issue #18): the synth's novel-view split (written, read, evaluated per view), the floater
measure (zero for the mesh itself, positive with a planted floater), orbit cameras and stills, and the
training background option. Small: 48 px subjects of 8 frames (2 test frames), untrained runs."""

from __future__ import annotations

import json
import math
import warnings

import numpy as np
import pytest
import torch
from PIL import Image

from apps_fixtures import make_untrained_run
from geoavatar.apps import orbit as orbit_app
from geoavatar.apps.eval import eval_runs
from geoavatar.config import preset
from geoavatar.data import HeadAvatarDataset, open_subject
from geoavatar.data.errors import DatasetError
from geoavatar.data.splits import ShortVideoWarning
from geoavatar.data.synth.actor import actor_for_subject
from geoavatar.data.synth.generate import FRONT_VIEW, NOVEL_VIEWS, SynthConfig, generate_dataset
from geoavatar.data.synth.render import ActorRenderer, frontal_camera, orbit_camera
from geoavatar.eval.floaters import FloaterConfig, head_silhouette, outside_share
from geoavatar.head.regions import skull_centre
from geoavatar.render import Camera, rasterize
from geoavatar.render.camera import intrinsics_from_fov, look_at, orbit_viewmat, project, rigid_inverse
from geoavatar.train.randomness import step_background
from head_fakes import procedural_head

SIZE = 48
FRAMES = 8  # the last 2 are test frames


def _synth(out, **changes):
    config = dict(subject=0, frames=FRAMES, size=SIZE, seed=0, workers=1)
    config.update(changes)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ShortVideoWarning)
        return generate_dataset(out, SynthConfig(**config), progress=False)


@pytest.fixture(scope="module")
def novel_data(tmp_path_factory):
    return _synth(tmp_path_factory.mktemp("novel") / "s0", novel_views=True, novel_every=1)


@pytest.fixture(scope="module")
def novel_run(novel_data, tmp_path_factory):
    return make_untrained_run(novel_data, tmp_path_factory.mktemp("novel-run") / "E")


# --- the split -------------------------------------------------------------------------------------


def test_novel_split_is_written_beside_an_unchanged_dataset(novel_data, tmp_path):
    plain = _synth(tmp_path / "plain")
    for name in ("transforms.json", "transforms_train.json", "transforms_test.json", "images/00006_00.png",
                 "fg_masks/00007_00.png", "flame_param/00007.npz"):
        assert (plain / name).read_bytes() == (novel_data / name).read_bytes(), name
    assert not (plain / "transforms_novel.json").exists()

    subject = open_subject(novel_data)
    test = HeadAvatarDataset(subject, "test", check_head=False)
    assert test.timesteps == (6, 7) and {f.camera for f in test.frames} == {0}  # novel views stay out of test
    novel = HeadAvatarDataset(subject, "novel", check_head=False)
    views = [(f.timestep, f.camera, f.view) for f in novel.frames]
    expected = [(t, 0, FRONT_VIEW) for t in (6, 7)] + [(t, i, name) for t in (6, 7) for i, name, _, _ in NOVEL_VIEWS]
    assert sorted(views) == sorted(expected)
    # The front view is the test frame itself; a novel view's image differs and its mask is not empty.
    front = next(i for i, f in enumerate(novel.frames) if f.view == FRONT_VIEW and f.timestep == 6)
    assert torch.equal(novel[front]["image"], test[0]["image"])
    side = next(i for i, f in enumerate(novel.frames) if f.view == "yaw+60" and f.timestep == 6)
    assert (novel[side]["image"] - test[0]["image"]).abs().mean() > 0.01 and novel[side]["mask"].mean() > 0.02
    # The same parameters as the test frame (one npz per timestep).
    assert all(torch.equal(novel[side]["params"][k], test[0]["params"][k]) for k in test[0]["params"])

    meta = json.loads((novel_data / "synth.json").read_text())["novel_views"]
    assert meta["timesteps"] == [6, 7] and len(meta["views"]) == len(NOVEL_VIEWS)


def test_novel_cameras_turn_about_the_head(novel_data):
    subject = open_subject(novel_data)
    frames = {(f.timestep, f.view): f for f in subject.extra_frames["novel"]}
    front = torch.from_numpy(frames[(6, FRONT_VIEW)].viewmat)
    eye0 = rigid_inverse(front)[:3, 3]
    for _, name, yaw, pitch in NOVEL_VIEWS:
        viewmat = torch.from_numpy(frames[(6, name)].viewmat)
        eye = rigid_inverse(viewmat)[:3, 3]
        # The pivot lies on the optical axis, as far from this eye as from the front camera's:
        # |s axis| = |eye + s axis - eye0|  ->  s = -|d|^2 / (2 axis.d), d = eye - eye0.
        axis, d = rigid_inverse(viewmat)[:3, 2], eye - eye0
        pivot = eye - axis * float(d @ d) / (2 * float(axis @ d))
        turned = torch.nn.functional.cosine_similarity(eye - pivot, eye0 - pivot, dim=0)
        assert float(turned) == pytest.approx(math.cos(math.radians(abs(yaw or pitch))), abs=0.02), name
        if pitch > 0:
            assert float(eye[1]) > float(eye0[1])  # from above
        if yaw > 0:
            assert float(eye[0]) > float(eye0[0])  # toward the camera's right (+x: the subject's left)


def test_novel_views_keep_the_lights_in_the_room():
    """A novel camera sees the actor lit by the dataset camera's lights, as a second camera of a capture rig
    would, not by lights that turn with it: seen from behind, the back of the head gets the ambient only."""
    actor = actor_for_subject(0)
    camera = frontal_camera(actor, 32)
    renderer = ActorRenderer(actor, camera, (0.0, 0.0, 0.0), ssaa=1)
    params = actor.model.zero_params(1)
    params["shape"] = torch.from_numpy(actor.shape)
    with torch.no_grad():
        vertices = actor.model.forward_params(params).vertices[0]  # [V, 3]
    behind = orbit_camera(camera, 180.0, 0.0, skull_centre(vertices, actor.head))
    room, mask = renderer.render(vertices, behind)
    lamp, lamp_mask = renderer.render(vertices, behind, lights_on_camera=True)
    assert torch.equal(mask, lamp_mask) and float(mask.mean()) > 0.1
    assert float(room.sum()) < 0.5 * float(lamp.sum())
    # The dataset camera itself is lit as before either way.
    assert torch.equal(renderer.render(vertices)[0], renderer.render(vertices, camera, lights_on_camera=True)[0])


def test_dataset_without_novel_split_says_how_to_make_one(tmp_path):
    subject = open_subject(_synth(tmp_path / "plain", frames=4, size=16))
    with pytest.raises(DatasetError, match="--novel-views"):
        HeadAvatarDataset(subject, "novel", check_head=False)


def test_eval_novel_split_reports_every_view(novel_run, capsys):
    assert eval_runs([novel_run], split="novel", progress=False, device="cpu", mouth=False) == 0
    printed = capsys.readouterr().out
    assert "Per view" in printed and "yaw+60" in printed
    report = json.loads((novel_run / "eval" / "novel" / "metrics.json").read_text())
    assert list(report["by_view"]) == [FRONT_VIEW] + [name for _, name, _, _ in NOVEL_VIEWS]
    for view, summary in report["by_view"].items():
        assert summary["psnr"]["count"] == 2 and math.isfinite(summary["psnr"]["mean"]), view
        assert 0.0 <= summary["outside"]["mean"] <= 1.0 and 0.0 <= summary["gt_outside"]["mean"] <= 1.0
    assert report["side_views"] == {}  # the novel split's frames are side views already
    assert "Per view" in (novel_run / "eval" / "novel" / "metrics.md").read_text()
    # every frame says where its camera saw the face from; a view turned by yaw (about the head's centre, the
    # head barely pitched) sees it from that many degrees further round than the front camera of the same frame
    frames = {(f["timestep"], f["view"]): f for f in report["frames"]}
    for (timestep, view), frame in frames.items():
        turn = dict((name, yaw) for _, name, yaw, _ in NOVEL_VIEWS).get(view, 0.0)
        front = frames[(timestep, FRONT_VIEW)]
        if "yaw" in view:
            assert abs(frame["view_yaw"] - front["view_yaw"] - turn) < 6.0, (timestep, view)
        assert isinstance(frame["trained_view"], bool)
    assert all(not f["trained_view"] for (_, view), f in frames.items() if view in ("yaw+60", "yaw-60"))
    assert sum(f["trained_view"] for (_, view), f in frames.items() if view == FRONT_VIEW) >= 1
    ranges = report["by_view_range"]
    assert "beyond" in ranges["yaw+60"] and "trained" not in ranges["yaw+60"]
    assert sum(part["psnr"]["count"] for part in ranges[FRONT_VIEW].values()) == 2


def test_head_relative_view_undoes_the_head_turn():
    from geoavatar.head.view_angles import view_directions, within_trained_views, yaw_pitch
    from geoavatar.geometry import axis_angle_to_matrix

    g = torch.Generator().manual_seed(0)
    rest = torch.randn(200, 3, generator=g, dtype=torch.float64) * torch.tensor([0.08, 0.1, 0.09], dtype=torch.float64)
    turn = axis_angle_to_matrix(torch.tensor([0.2, -0.5, 0.1], dtype=torch.float64))  # the head's rotation
    posed = rest @ turn.T + torch.tensor([0.01, 0.03, -0.02], dtype=torch.float64)  # [S, 3]
    # a camera 0.9 m away, placed 30 deg to the head's left (+x) and 10 deg above, in the head's axes
    yaw, pitch = math.radians(30.0), math.radians(10.0)
    local = torch.tensor([math.sin(yaw) * math.cos(pitch), math.sin(pitch), math.cos(yaw) * math.cos(pitch)],
                         dtype=torch.float64)
    centre = posed.mean(0) + 0.9 * (turn @ local)
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[:3, :3] = turn.T  # any orientation: only the camera's centre matters
    viewmat[:3, 3] = -(turn.T @ centre)
    direction = view_directions(rest, posed[None], viewmat[None])
    measured_yaw, measured_pitch = yaw_pitch(direction)
    assert float(measured_yaw) == pytest.approx(30.0, abs=1e-6) and float(measured_pitch) == pytest.approx(10.0, abs=1e-6)
    trained = view_directions(rest, posed[None], viewmat[None])
    assert bool(within_trained_views(direction, trained, 5.0)[0])
    assert not bool(within_trained_views(direction, torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64), 5.0)[0])


def test_eval_test_split_measures_floaters_at_side_views(novel_run):
    assert eval_runs([novel_run], split="test", progress=False, device="cpu", mouth=False, floater_frames=1) == 0
    report = json.loads((novel_run / "eval" / "test" / "metrics.json").read_text())
    assert set(report["side_views"]) >= {"yaw+90", "yaw-90", "pitch+20"}
    assert all(0.0 <= v <= 1.0 for v in report["side_views"].values())
    assert report["settings"]["floaters"]["side_view_frames"] == [6]
    assert all(f["outside"] is not None and f["view"] is None for f in report["frames"])


# --- the floater measure ---------------------------------------------------------------------------


def _splats_on_mesh(vertices: torch.Tensor, faces: torch.Tensor, extra: list[tuple[list[float], float]] = ()):
    """One small opaque Gaussian per face centre (a render of the mesh itself), plus planted ones."""
    means = vertices[faces].mean(1)  # [F, 3]
    scales = torch.full_like(means, 0.002)
    for centre, size in extra:
        means = torch.cat([means, torch.tensor([centre])])
        scales = torch.cat([scales, torch.full((1, 3), size)])
    n = means.shape[0]
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).expand(n, 4).contiguous()
    return means, quats, scales, torch.full((n,), 0.9), torch.full((n, 3), 0.5)


@pytest.mark.parametrize("yaw", [0.0, 60.0])
def test_floater_share_is_zero_for_the_mesh_and_positive_with_a_floater(yaw):
    data = procedural_head()
    vertices = torch.from_numpy(data.v_template).float()
    faces = torch.from_numpy(data.faces).long()
    size = 96
    front = look_at(torch.tensor([0.0, 0.0, 0.6]), torch.zeros(3))
    camera = Camera(orbit_viewmat(front, torch.zeros(3), yaw), intrinsics_from_fov(40.0, size, size), size, size)
    silhouette = head_silhouette(vertices, faces, camera, FloaterConfig().dilate_px(size, size))
    assert silhouette.float().mean() > 0.05

    clean = rasterize(*_splats_on_mesh(vertices, faces), camera.viewmat, camera.K, size, size).alpha
    assert float(clean.sum()) > 100 and outside_share(clean, silhouette) == 0.0
    # A floater beside the head, where the side view sees it (behind the head for the front view it is hidden).
    floater = [([0.05, 0.14, 0.0], 0.012)]
    planted = rasterize(*_splats_on_mesh(vertices, faces, floater), camera.viewmat, camera.K, size, size).alpha
    assert outside_share(planted, silhouette) > 0.01
    assert outside_share(torch.zeros(size, size), silhouette) == 0.0


# --- cameras, orbit, training background -------------------------------------------------------------


def test_orbit_viewmat_yaw_right_pitch_up():
    front = look_at(torch.tensor([0.0, 0.0, 1.0]), torch.zeros(3))
    centre = torch.tensor([0.0, 0.0, 0.0])
    eye = lambda m: rigid_inverse(m)[:3, 3]  # noqa: E731
    assert float(eye(orbit_viewmat(front, centre, 30.0))[0]) == pytest.approx(math.sin(math.radians(30)), abs=1e-5)
    assert float(eye(orbit_viewmat(front, centre, 0.0, 20.0))[1]) == pytest.approx(math.sin(math.radians(20)), abs=1e-5)
    pixel, depth = project(centre[None], orbit_viewmat(front, centre, 45.0, -15.0), intrinsics_from_fov(40, 32, 32))
    assert torch.allclose(pixel[0], torch.tensor([16.0, 16.0]), atol=1e-4) and float(depth[0]) > 0


def test_orbit_writes_stills_and_reports_floaters(novel_run, tmp_path, capsys):
    stills = tmp_path / "stills.png"
    assert orbit_app.orbit(novel_run, out=tmp_path / "o.mp4", frames=8, stills=stills, device="cpu",
                           progress=False) == 0
    assert "outside the head silhouette" in capsys.readouterr().out
    angles = orbit_app.sweep_angles(8, 60.0, 20.0)
    picks = orbit_app.still_indices(angles)
    assert picks[0] == 0 and len(picks) == 5  # front, yaw +-60, pitch +-20
    assert Image.open(stills).size == (len(picks) * SIZE, SIZE)


def test_random_background_is_a_pure_function_of_seed_and_step():
    dataset = torch.tensor([0.2, 0.3, 0.4])
    assert step_background(dataset, "dataset", 0, 5) is dataset
    a, b = step_background(dataset, "random", 0, 5), step_background(dataset, "random", 0, 6)
    assert torch.equal(a, step_background(dataset, "random", 0, 5)) and not torch.equal(a, b)
    assert not torch.equal(a, step_background(dataset, "random", 1, 5))
    colours = torch.stack([step_background(dataset, "random", 0, s) for s in range(1, 201)])  # [200, 3]
    assert colours.min() >= 0 and colours.max() <= 1 and float(colours.std(0).min()) > 0.2  # spread over [0, 1]
    with pytest.raises(ValueError, match="background"):
        preset("E", steps=2).__class__(background="noise").validate()
