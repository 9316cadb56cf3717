"""Applications on a trained run, end to end: train -> render -> export -> reenact -> orbit -> bench.

One tiny generated subject (48 px, 8 frames, the last 2 held out) trained for 2 steps serves every
test; a second tiny subject is the re-enactment driver. Videos are decoded back with PyAV, PLYs read
back with plyfile.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import av
import numpy as np
import pytest
import torch
import tyro
from plyfile import PlyData

from apps_fixtures import SIZE, make_run, make_subject, make_untrained_run
from geoavatar import cli
from geoavatar.animation.expression_transfer import TRANSFER_MODES
from geoavatar.animation.posing import pose_gaussians, record_camera, render_params
from geoavatar.animation.sinks import mp4 as mp4_sink
from geoavatar.animation.transfer import driven_params, reference_frame
from geoavatar.apps import bench as bench_app
from geoavatar.apps import export as export_app
from geoavatar.apps import orbit as orbit_app
from geoavatar.apps import reenact as reenact_app
from geoavatar.apps import render_video
from geoavatar.apps import view as view_app
from geoavatar.apps.common import colormap_lut, error_map, torch_threads
from geoavatar.apps.track import write_tracked_copy
from geoavatar.data import open_subject
from geoavatar.errors import OptionError
from geoavatar.head.params import HeadParams
from geoavatar.io.ply import PLY_PROPERTIES, read_gaussian_ply
from geoavatar.io.video import Mp4Writer
from geoavatar.render import composite_target
from geoavatar.render.camera import Camera, project, rigid_inverse
from geoavatar.train.checkpoint import RunError, open_run, open_run_dataset
from geoavatar.train.run_frames import RunFrames


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    return make_subject(tmp_path_factory.mktemp("apps-data") / "avatar", subject=0, frames=8)


@pytest.fixture(scope="module")
def driver(tmp_path_factory) -> Path:
    return make_subject(tmp_path_factory.mktemp("apps-driver") / "driver", subject=1, frames=4, size=40, seed=5)


@pytest.fixture(scope="module")
def run_dir(data, tmp_path_factory) -> Path:
    return make_run(data, tmp_path_factory.mktemp("apps-run") / "run")


@pytest.fixture(scope="module")
def run(run_dir):
    return open_run(run_dir, "cpu")


def decode(path: Path) -> list[np.ndarray]:
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        assert stream.codec_context.name == "h264" and stream.codec_context.pix_fmt == "yuv420p"
        assert abs(float(stream.average_rate) - 25.0) < 1e-6
        return [frame.to_ndarray(format="rgb24") for frame in container.decode(stream)]


# --- render -------------------------------------------------------------------------------------


def test_render_writes_ground_truth_render_error_video(run, run_dir, tmp_path):
    out = tmp_path / "render.mp4"
    assert render_video.render(run_dir, split="test", out=out, device="cpu", progress=False) == 0
    frames = decode(out)
    dataset = open_run_dataset(run, "test")
    assert len(frames) == len(dataset) == 2
    assert frames[0].shape == (SIZE, 3 * SIZE, 3)
    # Left: the composited ground truth; middle: the render (T = 0 for test frames). H.264 at crf 18 is
    # close but not exact.
    item = dataset[0]
    target = composite_target(item["image"], item["mask"], item["background"]).numpy() * 255.0
    frames_t = RunFrames(run)
    params, timestep = frames_t.params(item["timestep"])
    assert timestep is None  # a test frame: novel, T = 0
    pred = render_params(run, params, Camera(item["viewmat"], item["K"], SIZE, SIZE)).numpy() * 255.0
    assert np.abs(frames[0][:, :SIZE] - target).mean() < 6.0
    assert np.abs(frames[0][:, SIZE:2 * SIZE] - pred).mean() < 6.0
    assert np.abs(frames[0][:, :SIZE] - pred).mean() > np.abs(frames[0][:, SIZE:2 * SIZE] - pred).mean()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["render.mp4"]  # no temporary file left



def test_render_with_a_dataset_copy_shows_the_copys_parameters_on_held_out_frames(run, run_dir, data, tmp_path):
    """`render --data COPY` (a `track --avatar` copy) renders the test frames with the copy's parameters, as
    `eval --data COPY` scores them, not with those the run recorded."""
    subject = open_subject(data)
    params = HeadParams.from_npz({k: v.float() for k, v in subject.params.items()})
    copy = write_tracked_copy(subject, params.replace(translation=params.translation + torch.tensor([0.03, 0.0, 0.0])),
                              tmp_path / "copy", {})
    out = tmp_path / "render.mp4"
    assert render_video.render(run_dir, split="test", out=out, data=copy, device="cpu", progress=False) == 0
    item = open_run_dataset(run, "test", copy)[0]
    camera = Camera(item["viewmat"], item["K"], SIZE, SIZE)
    shown = decode(out)[0][:, SIZE:2 * SIZE].astype(np.float64)
    copys = render_params(run, HeadParams.from_npz(item["params"]), camera).numpy() * 255.0
    recorded = render_params(run, RunFrames(run).params(item["timestep"])[0], camera).numpy() * 255.0
    assert np.abs(shown - copys).mean() < 6.0 < np.abs(shown - recorded).mean()



def test_render_reenact_and_orbit_at_another_resolution(run_dir, driver, tmp_path):
    """--resolution sets the renders' longer side (the demo's pictures are larger than its training images); a bad
    value is a one-line OptionError naming it, before any work."""
    out = tmp_path / "render.mp4"
    assert render_video.render(run_dir, out=out, resolution=32, device="cpu", progress=False) == 0
    assert decode(out)[0].shape == (32, 3 * 32, 3)  # ground truth | render | error, all at 32 px
    out = tmp_path / "reenact.mp4"
    assert reenact_app.reenact(run_dir, driver, out=out, max_frames=1, resolution=32, device="cpu", progress=False) == 0
    assert decode(out)[0].shape == (32, 2 * 32, 3)  # driver (scaled to the height) | avatar
    bad = {"render": lambda: render_video.render(run_dir, out=tmp_path / "x.mp4", resolution=0, progress=False),
           "reenact": lambda: reenact_app.reenact(run_dir, driver, out=tmp_path / "x.mp4", resolution=-5, progress=False),
           "orbit": lambda: orbit_app.orbit(run_dir, out=tmp_path / "x.mp4", resolution=0, progress=False)}
    for name, command in bad.items():
        with pytest.raises(OptionError, match="--resolution"):
            command()
    assert not (tmp_path / "x.mp4").exists()


def test_error_map_scale_and_colours():
    pred = torch.zeros(2, 2, 3)
    target = torch.tensor([[0.0, 0.1], [0.25, 1.0]])[..., None].expand(2, 2, 3)
    colours = error_map(pred, target, error_max=0.25)
    lut = colormap_lut("inferno")
    assert torch.allclose(colours[0, 0], lut[0]) and torch.allclose(colours[1, 0], lut[255])
    assert torch.allclose(colours[1, 1], lut[255]) and torch.allclose(colours[0, 1], lut[102])
    with pytest.raises(ValueError, match="--error-max"):
        error_map(pred, target, error_max=0.0)


def test_mp4_writer_is_atomic_and_pads_odd_sizes(tmp_path):
    out = tmp_path / "odd.mp4"
    with Mp4Writer(out, fps=25) as video:
        for value in (0, 128, 255):
            video.write(np.full((15, 21, 3), value, np.uint8))
    frames = decode(out)
    assert len(frames) == 3 and frames[0].shape == (16, 22, 3)
    assert abs(int(frames[1][5, 5, 0]) - 128) <= 3
    with pytest.raises(RuntimeError, match="boom"):
        with Mp4Writer(out) as video:
            video.write(np.zeros((8, 8, 3), np.uint8))
            raise RuntimeError("boom")
    assert len(decode(out)) == 3  # the old file is untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["odd.mp4"]
    with pytest.raises(ValueError, match="size"):
        with Mp4Writer(tmp_path / "mixed.mp4") as video:
            video.write(np.zeros((8, 8, 3), np.uint8))
            video.write(np.zeros((8, 10, 3), np.uint8))
    assert not (tmp_path / "mixed.mp4").exists()


# --- export --------------------------------------------------------------------------------------


def test_export_ply_has_the_standard_layout_and_the_posed_gaussians(run, run_dir, tmp_path):
    timestep = run.info.timesteps["train"][1]
    out = tmp_path / "avatar.ply"
    assert export_app.export(run_dir, out=out, frame=timestep, progress=False) == 0
    ply = PlyData.read(str(out))
    vertex = ply["vertex"]
    assert ply.byte_order == "<" and not ply.text
    assert tuple(p.name for p in vertex.properties) == PLY_PROPERTIES
    assert all(p.val_dtype in ("f4", "float32") for p in vertex.properties)
    assert vertex.count == run.avatar.num_gaussians
    # The values are the global Gaussians of that frame (its refined parameters, its own T).
    params, t = RunFrames(run).params(timestep)
    assert t == timestep
    g = pose_gaussians(run, params, t)
    loaded = read_gaussian_ply(out)
    assert np.allclose(loaded.means, g.means.detach().numpy(), atol=1e-6)
    assert np.allclose(np.exp(loaded.log_scales), g.scales.detach().numpy(), rtol=1e-5)
    assert np.allclose(1 / (1 + np.exp(-loaded.opacity_logits)), g.opacities.detach().numpy(), atol=1e-6)
    assert np.allclose(0.5 + 0.28209479177387814 * loaded.f_dc, g.colors.detach().numpy(), atol=1e-6)
    assert np.allclose(np.linalg.norm(loaded.quats, axis=1), 1.0, atol=1e-6)
    assert np.allclose(np.abs((loaded.quats * g.quats.detach().numpy()).sum(1)), 1.0, atol=1e-5)
    assert np.allclose(np.c_[vertex["nx"], vertex["ny"], vertex["nz"]], 0.0)


def test_export_sequence_folder_and_npz(run, run_dir, tmp_path):
    folder = tmp_path / "seq"
    assert export_app.export(run_dir, out=folder, sequence=True, split="test", progress=False) == 0
    test_steps = run.info.timesteps["test"]
    assert sorted(p.name for p in folder.iterdir()) == [f"frame_{t:05d}.ply" for t in test_steps]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["seq"]  # the temporary folder is gone
    with pytest.raises(OptionError, match="--out .*already exists; pass --overwrite"):
        export_app.export(run_dir, out=folder, sequence=True, split="test", progress=False)
    assert export_app.export(run_dir, out=folder, sequence=True, split="test", overwrite=True, progress=False) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["seq"]
    with pytest.raises(OptionError, match="would delete the run"):  # --overwrite never replaces its inputs
        export_app.export(run_dir, out=Path(run_dir).parent, sequence=True, overwrite=True, progress=False)
    assert (Path(run_dir) / "checkpoints").is_dir()
    with pytest.raises(OptionError, match="--split and --format npz go with --sequence"):  # said, not dropped
        export_app.export(run_dir, out=tmp_path / "one.ply", split="test", progress=False)
    with pytest.raises(OptionError, match="is a folder"):  # before posing every frame
        export_app.export(run_dir, out=folder, sequence=True, format="npz", split="test", progress=False)

    npz_path = tmp_path / "seq.npz"
    assert export_app.export(run_dir, out=npz_path, sequence=True, format="npz", split="test", progress=False) == 0
    with np.load(npz_path) as arrays:
        n, count = run.avatar.num_gaussians, len(test_steps)
        assert arrays["timesteps"].tolist() == test_steps
        assert arrays["means"].shape == (count, n, 3) and arrays["quats"].shape == (count, n, 4)
        assert arrays["log_scales"].shape == (count, n, 3)
        assert run.avatar.normal_shading  # the default: the colour is shaded per frame, so stored per frame
        assert arrays["opacity_logits"].shape == (n,) and arrays["f_dc"].shape == (count, n, 3)
        assert arrays["binding"].shape == (n,)
        first = read_gaussian_ply(folder / f"frame_{test_steps[0]:05d}.ply")
        assert np.array_equal(arrays["means"][0], first.means) and np.array_equal(arrays["f_dc"][0], first.f_dc)
        assert not np.allclose(arrays["means"][0], arrays["means"][1])  # the head moves between frames
    # Without normal shading the colour does not change over time: stored once.
    plain = make_untrained_run(run.info.data_root, tmp_path / "plain", normal_shading=False)
    assert export_app.export(plain, out=tmp_path / "plain.npz", sequence=True, format="npz", split="test",
                             progress=False) == 0
    with np.load(tmp_path / "plain.npz") as arrays:
        n = arrays["binding"].shape[0]
        assert arrays["f_dc"].shape == (n, 3) and arrays["means"].shape == (len(test_steps), n, 3)
    with pytest.raises(OptionError, match="--frame and --sequence"):
        export_app.export(run_dir, frame=0, sequence=True)
    with pytest.raises(OptionError, match="not a timestep"):
        export_app.export(run_dir, out=tmp_path / "x.ply", frame=999)


# --- reenact -------------------------------------------------------------------------------------


def test_reenact_videos_in_every_transfer_mode(run_dir, driver, tmp_path, capsys):
    for mode in TRANSFER_MODES:
        out = tmp_path / f"reenact_{mode}.mp4"
        code = reenact_app.reenact(run_dir, driver, out=out, transfer=mode, max_frames=2, device="cpu", progress=False)
        assert code == 0 and f"{mode} transfer" in capsys.readouterr().out
        frames = decode(out)
        # driver (40 px, scaled to the avatar's 48 px height) | avatar (48 px)
        assert len(frames) == 2 and frames[0].shape == (SIZE, 2 * SIZE, 3)
    with pytest.raises(RunError, match="--driver .*not found"):
        reenact_app.reenact(run_dir, tmp_path / "missing", out=tmp_path / "x.mp4")


def test_driven_params_absolute_and_relative_rules(run, driver):
    frames = RunFrames(run)
    subject = open_subject(driver)
    values = subject.params
    timesteps = list(subject.timesteps)
    driver_ref = reference_frame(values, timesteps, "first")
    avatar_ref = reference_frame(frames.values.to_npz(), frames.timesteps, "first")
    identity = frames.identity()

    absolute = driven_params(identity, avatar_ref, values, driver_ref, "absolute")
    assert torch.equal(absolute["expr"], values["expr"]) and torch.equal(absolute["jaw_pose"], values["jaw_pose"])
    assert torch.equal(absolute["shape"], frames.values.shape)  # the avatar's identity
    assert torch.allclose(absolute["translation"][0], avatar_ref["translation"][0])  # neutral frame: avatar's place
    moved = values["translation"][2] - values["translation"][0]
    assert torch.allclose(absolute["translation"][2] - absolute["translation"][0], moved, atol=1e-6)

    relative = driven_params(identity, avatar_ref, values, driver_ref, "relative")
    assert all(torch.equal(relative[k], v) for k, v in driven_params(identity, avatar_ref, values,
                                                                     driver_ref, True).items())
    for key in ("expr", "rotation", "neck_pose", "jaw_pose", "eyes_pose"):  # the driver's neutral -> the avatar's
        assert torch.allclose(relative[key][0], avatar_ref[key][0], atol=1e-5), key
    delta = values["expr"][2] - values["expr"][0]
    assert torch.allclose(relative["expr"][2] - relative["expr"][0], delta, atol=1e-5)
    # Driving the avatar with its own sequence, relative to its own first frame, gives that sequence back.
    own = {k: v for k, v in frames.values.to_npz().items()}
    same = driven_params(identity, avatar_ref, own, avatar_ref, "relative")
    for key in ("expr", "rotation", "jaw_pose", "translation"):
        assert torch.allclose(same[key], own[key], atol=1e-5), key
    mean = reference_frame(values, timesteps, "mean")
    assert torch.allclose(mean["expr"][0], values["expr"].mean(0))
    assert torch.equal(reference_frame(values, timesteps, str(timesteps[1]))["expr"], values["expr"][1:2])
    with pytest.raises(ValueError, match="--driver-neutral"):
        reference_frame(values, timesteps, "middle")


# --- orbit ---------------------------------------------------------------------------------------


def test_orbit_cameras_circle_the_head_centre(run, data):
    base = record_camera(open_subject(data), 0, None)
    centre = torch.tensor([0.01, 0.02, -0.03])
    angles = orbit_app.sweep_angles(8, 60.0, 20.0)
    assert angles[0] == (0.0, 0.0) and max(a[0] for a in angles) == pytest.approx(60.0)
    assert min(a[1] for a in angles) == pytest.approx(-20.0)
    cameras = orbit_app.orbit_cameras(base, centre, angles)
    eyes = torch.stack([rigid_inverse(c.viewmat)[:3, 3] for c in cameras])  # [8, 3]
    distance = (rigid_inverse(base.viewmat)[:3, 3] - centre).norm()
    assert torch.allclose((eyes - centre).norm(dim=-1), distance.expand(8), atol=1e-5)
    assert torch.allclose(eyes[0], rigid_inverse(base.viewmat)[:3, 3], atol=1e-5)
    for camera in cameras:  # every camera looks at the centre
        pixel, depth = project(centre[None], camera.viewmat, camera.K)
        assert torch.allclose(pixel[0], camera.K[:2, 2], atol=1e-3) and float(depth[0]) > 0
    # The largest yaw turns the camera by 60 degrees about the camera's up axis.
    up = -rigid_inverse(base.viewmat)[:3, 1]
    flat = lambda v: v - (v @ up) * up  # noqa: E731 - the component perpendicular to the up axis
    yaw_eye = eyes[[a[0] for a in angles].index(max(a[0] for a in angles))]
    turned = torch.nn.functional.cosine_similarity(flat(yaw_eye - centre), flat(eyes[0] - centre), dim=0)
    assert float(turned) == pytest.approx(math.cos(math.radians(60.0)), abs=1e-4)


def test_orbit_cameras_put_the_head_centre_mid_image_whatever_the_principal_point(run, data):
    """prepare's face crops leave the principal point anywhere (duda.mp4: below the image); an orbit camera aimed at
    the head centre must still show it in the middle of the frame, not at the dataset's principal point."""
    base = record_camera(open_subject(data), 0, None)
    K = base.K.clone()
    K[0, 2], K[1, 2] = 0.3 * base.width, 1.1 * base.height  # off-centre, the second outside the image
    centre = torch.tensor([0.01, 0.02, -0.03])
    for camera in orbit_app.orbit_cameras(Camera(base.viewmat, K, base.width, base.height), centre,
                                          orbit_app.sweep_angles(6, 60.0, 20.0)):
        pixel, depth = project(centre[None], camera.viewmat, camera.K)
        assert torch.allclose(pixel[0], torch.tensor([base.width / 2, base.height / 2]), atol=1e-3)
        assert torch.equal(camera.K[[0, 1], [0, 1]], K[[0, 1], [0, 1]]) and float(depth[0]) > 0  # focal kept


def test_orbit_video(run_dir, tmp_path):
    out = tmp_path / "orbit.mp4"
    assert orbit_app.orbit(run_dir, out=out, frames=4, pitch=0.0, device="cpu", progress=False) == 0
    frames = decode(out)  # yaw 0, +60, 0, -60
    assert len(frames) == 4 and frames[0].shape == (SIZE, SIZE, 3)
    assert np.abs(frames[0].astype(float) - frames[1]).mean() > 0.1  # the view changes
    with pytest.raises(OptionError, match="--stills .*png"):  # before the sweep: PNG bytes in a .jpg before
        orbit_app.orbit(run_dir, out=out, frames=4, stills=tmp_path / "st.jpg", device="cpu", progress=False)


def test_reenact_checks_its_video_options_before_tracking_a_driver(run_dir, tmp_path):
    talk = tmp_path / "talk.mp4"
    talk.write_bytes(b"the user's video")  # never read: every check comes first
    for options, expected in (({"out": tmp_path / "x.avi"}, "must end in .mp4"), ({"out": talk}, "the input video"),
                              ({"fps": 0.0}, "--fps must be positive"), ({"crf": 99}, "--crf"),
                              ({"max_frames": 0}, "--max-frames must be positive")):
        with pytest.raises(OptionError, match=expected):
            reenact_app.reenact(run_dir, driver_video=talk, device="cpu", progress=False, **options)
    assert talk.read_bytes() == b"the user's video"


def test_video_loops_run_on_threads_asked_and_restore_the_process_count(run_dir, driver, tmp_path, monkeypatch):
    """--threads (default 1) holds inside the frame loops of render, reenact and orbit, the process's count after;
    the frames do not depend on it."""
    seen: list[int] = []
    real, real_frames = mp4_sink.rasterize_gaussians, render_video.render_run_frames

    def spy(*args, **kwargs):
        seen.append(torch.get_num_threads())
        return real(*args, **kwargs)

    def frames_spy(*args, **kwargs):  # render draws eval's frames: the count while each frame is made
        for frame in real_frames(*args, **kwargs):
            seen.append(torch.get_num_threads())
            yield frame

    monkeypatch.setattr(render_video, "render_run_frames", frames_spy)
    monkeypatch.setattr(mp4_sink, "rasterize_gaussians", spy)
    before = torch.get_num_threads()
    with torch_threads(3):
        assert torch.get_num_threads() == 3
    assert torch.get_num_threads() == before
    videos = {}
    for threads in (1, 2):
        seen.clear()
        out = tmp_path / f"render_{threads}.mp4"
        render_video.render(run_dir, out=out, max_frames=2, device="cpu", progress=False, threads=threads)
        reenact_app.reenact(run_dir, driver, out=tmp_path / f"reenact_{threads}.mp4", max_frames=2, device="cpu",
                            progress=False, threads=threads)
        assert seen == [threads] * 4 and torch.get_num_threads() == before
        videos[threads] = [decode(out), decode(tmp_path / f"reenact_{threads}.mp4")]
    assert all(np.array_equal(a, b) for one, two in zip(videos[1], videos[2]) for a, b in zip(one, two))
    assert orbit_app.orbit(run_dir, out=tmp_path / "orbit.mp4", frames=2, pitch=0.0, device="cpu", progress=False,
                           threads=2) == 0
    assert torch.get_num_threads() == before
    with pytest.raises(OptionError, match="--threads"):
        reenact_app.reenact(run_dir, driver, out=tmp_path / "x.mp4", threads=0)


# --- bench, CLI, errors --------------------------------------------------------------------------


def test_bench_reports_every_stage(run, run_dir, tmp_path, capsys):
    out = tmp_path / "bench.json"
    assert bench_app.bench(run_dir, resolution=32, iterations=1, warmup=0, out=out, device="cpu") == 0
    printed = capsys.readouterr().out
    assert "full animation path" in printed and "rasterize" in printed
    report = json.loads(out.read_text())
    assert (report["width"], report["height"]) == (32, 32) and report["gaussians"] == run.avatar.num_gaussians
    assert list(report["stages"]) == list(bench_app.STAGES)
    assert all(row["fps"] > 0 and row["ms"] > 0 for row in report["stages"].values())
    assert report["backend"] in ("cpu", "torch") and report["device"] == "cpu"  # native kernel when it builds


COMMANDS = {
    "render": render_video.render, "reenact": reenact_app.reenact, "orbit": orbit_app.orbit,
    "export": export_app.export, "view": view_app.view, "bench": bench_app.bench,
}


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_commands_build_a_cli_with_documented_options(name, capsys):
    with pytest.raises(SystemExit) as exit_info:
        tyro.cli(COMMANDS[name], args=["--help"], prog=f"geoavatar {name}")
    assert exit_info.value.code == 0
    text = capsys.readouterr().out
    assert "--device" in text
    assert "Run folder written by `geoavatar train`" in text


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_bad_run_folder_gives_a_clear_error(name, tmp_path, capsys):
    args = {"reenact": {"driver": tmp_path}}.get(name, {})
    with pytest.raises(RunError, match="not a GeoAvatar run"):
        COMMANDS[name](tmp_path, **args)
    # through `geoavatar`: one line naming the command, exit status 2
    cli_args = ["--driver", str(tmp_path)] if name == "reenact" else []
    assert cli.main([name, str(tmp_path / "missing"), *cli_args]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"geoavatar {name}: ") and "run folder not found" in err and err.count("\n") == 1


def test_export_through_the_cli_parser(run, run_dir, tmp_path):
    out = tmp_path / "cli.ply"
    tyro.cli(export_app.export, args=[str(run_dir), "--out", str(out), "--frame", "0"])
    assert PlyData.read(str(out))["vertex"].count == run.avatar.num_gaussians
