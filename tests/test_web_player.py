"""The web player: `export --format web` writes a folder that a real browser (Debian's chromium, software WebGL,
driven by Playwright) plays; the page's frame from the dataset camera scores like the CPU renderer's against the
same ground truth; deep links, counters and controls; bad input and interrupted exports.

The avatar is a run's step-0 state (colours from the images) thinned to 4000 Gaussians with varied local means,
rotations, scales, opacities, normal shading and pose offsets (hair that follows the head), so every part of the GPU
placement is exercised on 64 px frames."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from apps_fixtures import make_subject, make_untrained_run
from web_fixtures import cpu_and_truth, psnr, varied_avatar
from geoavatar import cli
from geoavatar.apps.web_export import export_web
from geoavatar.train.checkpoint import open_run
from geoavatar.web import pack
from geoavatar.web.browser import browser_missing, canvas_rgb, chromium_page, static_server, wait_drawn

SPLATS = 4000


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("web")
    data = make_subject(root / "data", subject=1, frames=8, size=64)
    return make_untrained_run(data, root / "run")


@pytest.fixture(scope="module")
def run(run_dir):
    loaded = open_run(run_dir, "cpu")
    assert loaded.avatar.normal_shading and loaded.avatar.follows_head  # the defaults: the page must shade and
    # move the hair with the head's turn
    varied_avatar(loaded.avatar, SPLATS)
    return loaded


@pytest.fixture(scope="module")
def player(run, tmp_path_factory):
    return export_web(run, tmp_path_factory.mktemp("player") / "web", "test", show_progress=False)


def test_export_writes_the_player_folder(run, player):
    manifest = json.loads((player / pack.MANIFEST).read_text())
    names = sorted(f.name for f in player.iterdir())
    assert names == sorted([*pack.PLAYER_FILES, pack.MANIFEST, pack.AVATAR_FILE, pack.CLIP_FILE])
    test_steps = run.info.timesteps["test"]
    assert manifest["clip"]["timesteps"] == test_steps and manifest["clip"]["frames"] == len(test_steps)
    avatar = manifest["avatar"]
    assert (avatar["splats"], avatar["faces"], avatar["vertices"]) == (SPLATS, run.avatar.num_faces, run.head.num_vertices)
    assert avatar["followsHead"] and len(manifest["clip"]["pose"]) == len(test_steps)  # the default: the hair follows
    posed = int(run.avatar.moving[run.avatar.binding].sum())  # the splats that carry pose rows
    assert avatar["posed"] == posed and manifest["format"] == pack.FORMAT_VERSION
    assert (player / pack.AVATAR_FILE).stat().st_size == SPLATS * (16 + 40) + run.avatar.num_faces * 12 + posed * 72
    assert (player / pack.CLIP_FILE).stat().st_size == len(test_steps) * run.head.num_vertices * 6
    yaw, pitch = manifest["orbit"]["yaw"], manifest["orbit"]["pitch"]
    assert yaw[0] <= 0 <= yaw[1] and pitch[0] <= 0 <= pitch[1] and yaw[1] - yaw[0] < 180
    assert "flame" not in json.dumps(manifest).lower()  # posed vertices and triangles only
    assert "viewmats" not in manifest  # one camera for the whole clip (the subject's camera does not move)


pytestmark_browser = pytest.mark.skipif(browser_missing() is not None, reason=f"browser tests: {browser_missing()}")


@pytestmark_browser
def test_browser_frame_matches_the_cpu_renderer_from_the_dataset_camera(run, player):
    manifest = json.loads((player / pack.MANIFEST).read_text())
    console: list[str] = []
    with static_server(player) as url, chromium_page(console=console) as page:
        for index in (0, 1):
            page.goto(url + f"index.html?frame={index}&paused=1&view=dataset")
            wait_drawn(page, index)
            browser = canvas_rgb(page)
            cpu, truth = cpu_and_truth(run, manifest["clip"]["timesteps"][index])
            assert browser.shape == cpu.shape == (manifest["camera"]["height"], manifest["camera"]["width"], 3)
            assert psnr(browser, cpu) > 30.0, console
            assert abs(psnr(browser, truth) - psnr(cpu, truth)) < 1.0
        stats = page.evaluate("window.geoavatar.stats")
        assert stats["ready"] and stats["drawn"] >= 1 and stats["frameCostMs"] > 0
    assert not [line for line in console if line.startswith(("error", "pageerror"))], console


@pytestmark_browser
def test_player_plays_scrubs_and_limits_the_orbit(player):
    with static_server(player) as url, chromium_page(320, 240) as page:
        page.goto(url + "index.html")
        page.wait_for_function("window.geoavatar && window.geoavatar.stats.ready", timeout=120_000)
        page.wait_for_function("window.geoavatar.player.frame === 1", timeout=60_000)  # it plays by itself
        page.click("#play")  # pause
        page.evaluate("delete document.body.dataset.drawnFrame")  # announced again once the scrubbed frame is sorted
        page.fill("#scrub", "0")
        page.dispatch_event("#scrub", "input")
        wait_drawn(page, 0)
        assert page.inner_text("#frame-label").startswith("1 / 2")
        page.evaluate("p => { p.orbit.yaw = 170; p.placeOrbit(); }", page.evaluate_handle("window.geoavatar.player"))
        limited = page.evaluate("window.geoavatar.player.orbit.yaw")
        page.check("#free-orbit")
        page.evaluate("p => { p.orbit.yaw = 170; p.placeOrbit(); }", page.evaluate_handle("window.geoavatar.player"))
        free = page.evaluate("window.geoavatar.player.orbit.yaw")
        limits = json.loads((player / pack.MANIFEST).read_text())["orbit"]["yaw"]
        assert limited == pytest.approx(limits[1]) and free == pytest.approx(170.0)
        page.fill("#background", "#ff0000")
        page.dispatch_event("#background", "input")
        assert page.evaluate("window.geoavatar.player.background") == [1.0, 0.0, 0.0]


@pytestmark_browser
def test_a_folder_of_another_format_version_is_refused_in_one_line(player, tmp_path):
    """An older export (format 1: float32 rows, pose rows for every splat) must not be read with the new layout."""
    old = tmp_path / "old"
    shutil.copytree(player, old)
    manifest = json.loads((old / pack.MANIFEST).read_text())
    (old / pack.MANIFEST).write_text(json.dumps({**manifest, "format": pack.FORMAT_VERSION - 1}))
    with static_server(old) as url, chromium_page(320, 240) as page:
        page.goto(url + "index.html")
        page.wait_for_function("document.body.dataset.error !== undefined", timeout=60_000)
        error = page.evaluate("document.body.dataset.error")
        assert f"format {pack.FORMAT_VERSION - 1}" in error and "export the avatar again" in error
        assert error in page.inner_text("#status")


def test_bad_input_is_one_line(run_dir, tmp_path, capsys):
    cases = [
        (["export", str(tmp_path), "--format", "web"], "not a GeoAvatar run"),
        (["export", str(run_dir), "--format", "web", "--split", "nope", "--out", str(tmp_path / "w")], "--split"),
        (["export", str(run_dir), "--format", "web", "--frame", "0"], "--frame"),
        (["export", str(run_dir), "--format", "web", "--relative"], "--relative"),
    ]
    for argv, words in cases:
        assert cli.main(argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and words in err, (argv, err)
    (tmp_path / "taken").mkdir()
    assert cli.main(["export", str(run_dir), "--format", "web", "--out", str(tmp_path / "taken")]) == 2
    assert "--overwrite" in capsys.readouterr().err


def test_interrupted_export_leaves_nothing_that_looks_complete(run, tmp_path, monkeypatch):
    out = tmp_path / "web"

    def broken_copy(source, target):
        raise KeyboardInterrupt  # Ctrl-C while the folder is written

    monkeypatch.setattr(pack.shutil, "copyfile", broken_copy)
    with pytest.raises(KeyboardInterrupt):
        export_web(run, out, "test", show_progress=False)
    assert list(tmp_path.iterdir()) == []  # no folder, no leftover temporary one


def test_a_driver_clip_is_reenacts_motion_posed_once(run, tmp_path):
    from geoavatar.animation.posing import posed_head_vertices
    from geoavatar.animation.sources.driver import driven_clip, frame_of
    from geoavatar.train.run_frames import RunFrames

    driver = make_subject(tmp_path / "driver", subject=2, frames=5, size=32, seed=3)
    folder = export_web(run, tmp_path / "web", driver=driver, transfer="subspace", fps=12.5, show_progress=False)
    manifest = json.loads((folder / pack.MANIFEST).read_text())
    assert manifest["clip"]["frames"] == 5 and manifest["clip"]["fps"] == 12.5
    assert manifest["clip"]["source"] == "driver driver (subspace transfer)"
    codes = np.frombuffer((folder / pack.CLIP_FILE).read_bytes(), dtype="<u2").reshape(5, -1, 3)
    decoded = manifest["clip"]["offset"] + codes[4] * np.asarray(manifest["clip"]["step"])
    _, params = driven_clip(run, RunFrames(run), driver, "subspace")
    expected = posed_head_vertices(run, frame_of(params, 4), None).detach().numpy()
    assert np.abs(decoded - expected).max() < 1e-5  # reenact's parameters, posed as every command poses


def test_a_clip_whose_camera_moves_lists_each_frames_camera(run, tmp_path, monkeypatch):
    """INSTA-like data moves the camera instead of the head: the dataset view must follow each frame's camera."""
    from geoavatar.animation.sinks import web as web_export

    still = web_export.record_camera

    def moving(subject, timestep, resolution):
        camera = still(subject, timestep, resolution)
        viewmat = camera.viewmat.clone()
        viewmat[0, 3] += 0.01 * timestep  # the camera slides sideways frame by frame
        return camera.__class__(viewmat, camera.K, camera.width, camera.height)

    monkeypatch.setattr(web_export, "record_camera", moving)
    folder = export_web(run, tmp_path / "web", "all", show_progress=False)
    manifest = json.loads((folder / pack.MANIFEST).read_text())
    viewmats = np.asarray(manifest["viewmats"])
    assert viewmats.shape == (manifest["clip"]["frames"], 4, 4)
    np.testing.assert_allclose(viewmats[:, 0, 3] - viewmats[0, 0, 3], 0.01 * np.asarray(manifest["clip"]["timesteps"]),
                               atol=1e-6)
    assert manifest["camera"]["viewmat"] == manifest["viewmats"][0]


def _descendants(root: int) -> list[int]:
    """Process ids below `root` (Linux /proc)."""
    from pathlib import Path

    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            parent = int(stat.read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        children.setdefault(parent, []).append(int(stat.parent.name))
    found, stack = [], list(children.get(root, []))
    while stack:
        pid = stack.pop()
        found.append(pid)
        stack.extend(children.get(pid, []))
    return found


@pytest.mark.skipif(browser_missing() is not None, reason=f"browser tests: {browser_missing()}")
def test_a_niced_browser_stays_niced():
    """web_player_bench live runs the browser at nice 10 beside drive (#28): Chromium raises its own threads to nice 0
    and -8 when it may (root), and Playwright starts it in a session of its own, whose autogroup the scheduler
    weighs as much as drive's; every browser thread and its session's group must stay at the given nice."""
    import os
    from pathlib import Path

    with chromium_page(64, 64, nice=7) as page:
        page.goto("about:blank")
        threads, groups = {}, set()
        for pid in _descendants(os.getpid()):
            try:
                if b"chromium" not in Path(f"/proc/{pid}/cmdline").read_bytes():
                    continue
                for stat in Path(f"/proc/{pid}/task").glob("*/stat"):
                    nice = int(stat.read_text().rsplit(")", 1)[1].split()[16])
                    threads[nice] = threads.get(nice, 0) + 1
                autogroup = Path(f"/proc/{pid}/autogroup")
                if autogroup.exists():
                    groups.add(autogroup.read_text().split()[-1])
            except OSError:  # a process that ended meanwhile
                continue
    assert threads and set(threads) == {7}, threads
    assert groups <= {"7"}, groups
