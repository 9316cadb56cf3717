"""`geoavatar demo`: the main job on the embedded default, end to end, with a report to open.

The steps a user's own video takes after `prepare` (#31): generate a subject → train GeoAvatar (preset E) → track
the held-out test frames against the trained avatar (`geoavatar track DATA --avatar RUN --out COPY`, the README's
advice) → evaluate them (`geoavatar eval RUN --data COPY`; the plain `geoavatar eval RUN` on the generated subject's
written parameters beside it) → render the self re-enactment of the tracked test frames, a novel-view orbit and a
cross re-enactment driven by a second generated subject, at 256 px (larger than the training images) → the browser
player of the avatar (demo_output/web/, `export --format web`) → demo_output/report.md (and report.json) led by the
tracked test score, with the time of every stage and pictures.

Each stage writes into its own folder and is skipped when its output is already complete, so an
interrupted demo continues where it stopped (training itself resumes from its last checkpoint).
"""

from __future__ import annotations

import json
import platform
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Literal

from geoavatar.io.atomic import atomic_write_png, atomic_write_text

DRIVER_SUBJECT = 1


@dataclass
class DemoSettings:
    """The demo's schedule: the paper's method on a CPU-sized budget (all milestones scale with steps)."""

    frames: int = 160  # generated video length (25 fps); the last 25 % are the test split
    size: int = 256  # generated image size
    resolution: int = 128  # training / evaluation resolution (longer side)
    picture_resolution: int = 256  # the videos' and stills' longer side (at most `size`: images are never enlarged)
    steps: int = 1500  # training steps (the paper: 200k on a GPU)
    track_steps: int = 30  # Adam steps per test frame against the avatar (track --avatar's default; 10 lose 3.4 dB)
    driver_frames: int = 60  # length of the cross re-enactment driver
    orbit_frames: int = 48
    seed: int = 0


@dataclass
class StageTimer:
    """Times each stage and keeps the times in a JSON file, so a re-run that skips finished stages
    still reports what they cost when they ran."""

    path: Path
    seconds: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.path.is_file():
            try:
                self.seconds = {str(k): float(v) for k, v in json.loads(self.path.read_text()).items()}
            except (ValueError, AttributeError):
                self.seconds = {}  # unreadable timings are only a report detail: start afresh

    def run(self, name: str, done: Callable[[], bool], action: Callable[[], object]) -> None:
        if done():
            print(f"[demo] {name}: already done, skipped")
            return
        print(f"[demo] {name} ...", flush=True)
        start = time.perf_counter()
        action()
        self.seconds[name] = time.perf_counter() - start
        atomic_write_text(self.path, json.dumps(self.seconds, indent=1))
        print(f"[demo] {name}: {self.seconds[name]:.0f} s", flush=True)


TRACKED_NAME = "subject0_tracked"  # the copy of the subject with its test frames tracked against the avatar
REPORT_KEYS = ("psnr", "ssim", "lpips", "mse", "mouth_psnr", "mouth_lpips")  # report.json's per-path figures


def _checked(code: object, stage: str) -> None:
    if isinstance(code, int) and code != 0:
        raise SystemExit(f"geoavatar demo: stage '{stage}' failed (exit code {code})")


def demo(
    out: Path = Path("demo_output"),
    steps: int = DemoSettings.steps,
    frames: int = DemoSettings.frames,
    size: int = DemoSettings.size,
    resolution: int = DemoSettings.resolution,
    picture_resolution: int = DemoSettings.picture_resolution,
    track_steps: int = DemoSettings.track_steps,
    driver_frames: int = DemoSettings.driver_frames,
    seed: int = DemoSettings.seed,
    device: str = "auto",
    backend: Literal["auto", "cpu", "torch", "gsplat"] = "auto",
    progress: bool = True,
) -> int:
    """Run the whole pipeline on a generated subject and write OUT/report.md.

    Generates subject 0 (and subject 1 as a driver), trains GeoAvatar (preset E) on the first 75 %
    of the video, tracks the held-out last 25 % against the trained avatar as the README advises for a user's
    own video (`geoavatar track DATA --avatar RUN --out COPY`), evaluates MSE/PSNR/SSIM/LPIPS on them
    (`geoavatar eval RUN --data COPY`) and, beside it, on the generated subject's written parameters (the plain
    `geoavatar eval RUN`: their simulated tracker error, which the avatar never saw), renders the tracked test
    re-enactment (ground truth | render | error), a novel-view orbit and a cross re-enactment at
    --picture-resolution, and writes report.md (led by the tracked test score) and report.json with timings and
    pictures. Re-running continues an interrupted demo. The defaults take an estimated 4-5 minutes on 2 quiet CPU
    cores (native cpu rasterizer; docs/demo.md).

    Args:
        out: Output folder (data/, run/, videos, stills and report.md go here).
        steps: Training steps (every milestone of the paper's 200k-step schedule scales with it).
        frames: Length of the generated training video (the last 25 % are the test split).
        size: Size of the generated images.
        resolution: Training and evaluation resolution (longer side, pixels).
        picture_resolution: Longer side of the videos and stills (pixels; at most --size).
        track_steps: Adam steps per test frame when tracking them against the avatar (`track --steps`).
        driver_frames: Length of the second subject's video that drives the cross re-enactment.
        seed: Seed of the generated motion and of training.
        device: auto (CUDA when available, else CPU), cpu or cuda.
        backend: Rasterizer of every stage: auto (gsplat on CUDA, the native cpu kernel on CPU when it
            builds, else torch), cpu, torch or gsplat; `--backend torch` times the demo without the
            native kernel.
        progress: Show progress bars.
    """
    from geoavatar.apps.eval import eval_runs
    from geoavatar.apps.export import export
    from geoavatar.apps.orbit import orbit
    from geoavatar.apps.reenact import reenact
    from geoavatar.apps.render_video import render
    from geoavatar.apps.synth import synth
    from geoavatar.apps.track import REPORT_FILE as TRACK_REPORT
    from geoavatar.apps.track import track
    from geoavatar.apps.train import TrainArgs, train
    from geoavatar.data.layout import is_layout
    from geoavatar.train.options import RunOptions

    if (steps <= 0 or frames < 8 or size < 32 or resolution < 32 or picture_resolution < 32 or track_steps <= 0
            or driver_frames < 2):
        raise SystemExit("geoavatar demo: need --steps > 0, --frames >= 8, --size >= 32, --resolution >= 32, "
                         "--picture-resolution >= 32, --track-steps > 0, --driver-frames >= 2")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    data, driver, run = out / "data" / "subject0", out / "data" / "driver", out / "run"
    tracked = out / "data" / TRACKED_NAME
    pictures = min(picture_resolution, size)  # the generated images are never enlarged
    videos = {"render": out / "render_test.mp4", "orbit": out / "orbit.mp4", "reenact": out / "reenact.mp4"}
    metrics = {"tracked": run / "eval" / f"test@{TRACKED_NAME}" / "metrics.json",  # eval's folder for --data COPY
               "written": run / "eval" / "test" / "metrics.json"}
    timer = StageTimer(out / "timings.json")

    timer.run("generate subject", lambda: is_layout(data),
              lambda: synth(out=data, subject=0, frames=frames, size=size, seed=seed, preview=True,
                            progress=progress))
    timer.run("generate driver", lambda: is_layout(driver),
              lambda: synth(out=driver, subject=DRIVER_SUBJECT, frames=driver_frames, size=size, seed=seed + 1,
                            progress=progress))
    final_ckpt = run / "checkpoints" / "final.pt"
    resume = (run / "checkpoints" / "last.pt").is_file()
    timer.run("train GeoAvatar (preset E)", final_ckpt.is_file,
              lambda: _checked(train(TrainArgs(
                  RunOptions(out=run, data=data, preset=None if resume else "E", resolution=resolution, seed=seed,
                             device=device, backend=backend, progress=progress),
                  steps=None if resume else steps, resume=resume)), "train"))
    # the user's path: the held-out frames tracked against the avatar (only they: the training frames keep the
    # parameters training refined), then scored on that copy
    timer.run("track the test frames against the avatar", (tracked / TRACK_REPORT).is_file,
              lambda: _checked(track(data, out=tracked, avatar=run, steps=track_steps, device=device, overwrite=True,
                                     progress=progress), "track"))
    timer.run("evaluate (test split, tracked)", metrics["tracked"].is_file,
              lambda: _checked(eval_runs([run], split="test", data=tracked, device=device, backend=backend,
                                         progress=progress), "eval"))
    # beside it, the plain eval on the written parameters (the generator's tracker error); its three figures only
    timer.run("evaluate (test split, written parameters)", metrics["written"].is_file,
              lambda: _checked(eval_runs([run], split="test", faces=False, floaters=False, device=device,
                                         backend=backend, progress=progress), "eval"))
    timer.run("render test re-enactment", videos["render"].is_file,
              lambda: _checked(render(run, split="test", out=videos["render"], data=tracked, resolution=pictures,
                                      device=device, backend=backend, progress=progress),
                               "render"))
    timer.run("render novel-view orbit", videos["orbit"].is_file,
              lambda: _checked(orbit(run, out=videos["orbit"], frames=DemoSettings.orbit_frames, resolution=pictures,
                                     device=device, backend=backend, progress=progress), "orbit"))
    timer.run("render cross re-enactment", videos["reenact"].is_file,
              lambda: _checked(reenact(run, driver=driver, out=videos["reenact"], relative=True, resolution=pictures,
                                       device=device, backend=backend, progress=progress),
                               "reenact"))

    player = out / "web"
    timer.run("write the web player", (player / "avatar.json").is_file,
              lambda: _checked(export(run, out=player, format="web", overwrite=True, device=device,
                                      progress=progress), "export"))

    stills = {name: out / f"{name}.png" for name in videos}
    for name, video in videos.items():
        save_still(video, stills[name])
    report = write_report(out, data, tracked, run, metrics, videos, stills, timer.seconds,
                          steps=steps, resolution=resolution, frames=frames, backend=backend,
                          picture_resolution=pictures, track_steps=track_steps, size=size, seed=seed)
    print()
    print(f"Demo finished: {sum(timer.seconds.values()) / 60:.1f} min of stage time in all.")
    print(f"Open {report} (metrics, timings, pictures); videos: {', '.join(str(v) for v in videos.values())}")
    print(f"The avatar in your browser: python3 -m http.server 8000 --bind 127.0.0.1 --directory {player}\n"
          f"  then open http://127.0.0.1:8000/ (or: geoavatar view {run}, with expression and jaw sliders)")
    return 0


def save_still(video: Path, png: Path, position: float = 0.5) -> Path:
    """The frame at `position` (0..1) of an mp4 as a PNG (written atomically)."""
    import av

    with av.open(str(video)) as container:
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    if not frames:
        raise SystemExit(f"geoavatar demo: {video} holds no frames")
    image = frames[min(len(frames) - 1, int(position * len(frames)))]
    return atomic_write_png(png, image)


def write_report(out: Path, data: Path, tracked: Path, run: Path, metrics: dict[str, Path], videos: dict[str, Path],
                 stills: dict[str, Path], seconds: dict[str, float], **settings) -> Path:
    """OUT/report.md, led by the test score of the tracked test frames with the written parameters' beside it, and
    OUT/report.json with the same figures (per path: mean and std of PSNR, SSIM, LPIPS, MSE and the mouth's)."""
    scores = {path: json.loads(file.read_text()) for path, file in metrics.items()}
    figures = {path: _figures(score["summary"]) for path, score in scores.items()}
    tracking = _tracking_summary(tracked)
    # the tracked eval's report without its own title, its sections one level down, so it nests under this heading
    table = "\n".join("##" + line if line.startswith("## ") else line
                      for line in (metrics["tracked"].parent / "metrics.md").read_text().strip().splitlines()
                      if not line.startswith("# "))
    aps = run / "aps.json"
    aps_text = ""
    if aps.is_file():
        aps_text = "\n## Adaptive Pre-allocation Stage\n\n```\n" + _aps_summary(json.loads(aps.read_text())) + "\n```\n"
    rel = lambda p: Path(p).relative_to(out).as_posix()  # noqa: E731
    timing_rows = "\n".join(f"| {name} | {sec / 60:.1f} min |" for name, sec in seconds.items())
    frames_evaluated = len(scores["tracked"]["frames"])
    lead = figures["tracked"]
    px = settings["picture_resolution"]
    lines = [
        "# GeoAvatar demo",
        "",
        f"A generated subject ({settings['frames']} frames), GeoAvatar (preset E) trained for {settings['steps']} steps "
        f"at {settings['resolution']} px on {platform.processor() or platform.machine()} (rasterizer backend "
        f"'{settings.get('backend', 'auto')}') on the first 75 % of the video, and tested on the held-out last 25 % "
        f"(poses and expressions not seen in training) the way your own video is: its frames tracked against the "
        f"trained avatar, then scored.",
        "",
        "## Test-split score",
        "",
        f"**{_headline(lead)}** on the {frames_evaluated} held-out frames tracked against the avatar "
        f"(`geoavatar track DATA --avatar RUN --out COPY`, then `geoavatar eval RUN --data COPY`).",
        "",
        "| test frames' parameters | PSNR ↑ | SSIM ↑ | LPIPS ↓ | mouth PSNR ↑ |",
        "|---|---:|---:|---:|---:|",
        f"| **tracked against the avatar** (`{rel(tracked)}`) | {_row(lead, bold=True)} |",
        f"| written by the generator (the plain `geoavatar eval RUN`) | {_row(figures['written'])} |",
        "",
        "The written parameters carry the generator's simulated tracker error, which the avatar never saw (on the test "
        "frames mostly a drift in depth); tracking against the avatar fits it away as it would a real tracker's, so the "
        "plain score measures that error more than the avatar.",
        "",
        _tracking_line(tracking, rel(tracked / "track.json")),
        "",
        f"### The tracked test frames in full (`geoavatar eval RUN --data {rel(tracked)}`)",
        "",
        table,
        "",
        f"Frames evaluated: {frames_evaluated}. Per-frame values: `{rel(metrics['tracked'])}`; with the written "
        f"parameters: `{rel(metrics['written'])}`.",
        "",
        "## Pictures",
        "",
        f"At {px} px (the avatar was trained at {settings['resolution']} px).",
        "",
        f"Self re-enactment of the tracked test frames (ground truth | render | error): `{rel(videos['render'])}`",
        "",
        f"![test re-enactment]({rel(stills['render'])})",
        "",
        f"Novel views (yaw/pitch orbit): `{rel(videos['orbit'])}`",
        "",
        f"![orbit]({rel(stills['orbit'])})",
        "",
        f"Cross re-enactment driven by a second generated subject (relative expressions): `{rel(videos['reenact'])}`",
        "",
        f"![cross re-enactment]({rel(stills['reenact'])})",
        "",
        f"The generated subject across its sequence: `{rel(data / 'preview.png')}`",
        "",
        f"The animated avatar in a browser (test split, posed on the GPU): `python3 -m http.server 8000 --bind "
        f"127.0.0.1 --directory {out / 'web'}`, then open http://127.0.0.1:8000/ (docs/web_player.md).",
        aps_text,
        "## Time",
        "",
        "| stage | time |",
        "|---|---|",
        timing_rows,
        f"| **total** | **{sum(seconds.values()) / 60:.1f} min** |",
        "",
        "## Reproduce",
        "",
        "```bash",
        f"geoavatar demo --out {out} --steps {settings['steps']} --frames {settings['frames']} --size {settings['size']} "
        f"--resolution {settings['resolution']} --picture-resolution {px} --track-steps {settings['track_steps']}",
        "```",
        "",
        "or the same steps one by one, as for your own video after `geoavatar prepare`:",
        "",
        "```bash",
        *_user_path(out, data, tracked, run, videos["render"], **settings),
        "```",
        "",
        f"Training log: `{rel(run / 'train.log')}`; validation images: `{rel(run / 'val')}`.",
        "",
    ]
    atomic_write_text(out / "report.json", json.dumps({
        "format": "geoavatar-demo", "version": 1,
        "test": {"lead": "tracked", **figures},  # per path: the test frames' parameters
        "frames_evaluated": frames_evaluated,
        "tracking": tracking,
        "metrics": {path: rel(file) for path, file in metrics.items()},
        "pictures": {"resolution": px, "stills": {name: rel(png) for name, png in stills.items()},
                     "videos": {name: rel(video) for name, video in videos.items()}},
        "settings": {key: settings[key] for key in ("frames", "size", "steps", "resolution", "track_steps", "seed",
                                                    "backend") if key in settings},
        "seconds": {name: round(sec, 1) for name, sec in seconds.items()},
        "total_seconds": round(sum(seconds.values()), 1),
    }, indent=1) + "\n")
    return atomic_write_text(out / "report.md", "\n".join(lines))


def _figures(summary: dict) -> dict[str, dict[str, float]]:
    """The report's figures of an eval summary: {metric: {mean, std}}."""
    return {key: {"mean": summary[key]["mean"], "std": summary[key]["std"]} for key in REPORT_KEYS if key in summary}


def _headline(figures: dict) -> str:
    return (f"PSNR {figures['psnr']['mean']:.2f} dB · SSIM {figures['ssim']['mean']:.3f} · "
            f"LPIPS {figures['lpips']['mean']:.3f}")


def _row(figures: dict, bold: bool = False) -> str:
    mark = "**" if bold else ""
    mouth = f"{figures['mouth_psnr']['mean']:.2f}" if "mouth_psnr" in figures else "–"
    return (f"{mark}{figures['psnr']['mean']:.2f}{mark} ± {figures['psnr']['std']:.2f} | "
            f"{mark}{figures['ssim']['mean']:.3f}{mark} | {mark}{figures['lpips']['mean']:.3f}{mark} | {mouth}")


def _tracking_summary(tracked: Path) -> dict:
    """What `track --avatar` did, from COPY/track.json: frames fitted, steps, L1 before and after, seconds."""
    from geoavatar.apps.track import REPORT_FILE

    report = json.loads((tracked / REPORT_FILE).read_text())
    fitted = report["avatar_tracking"]
    return {"frames_fitted": len(fitted["fitted"]), "frames_from_run": len(fitted["from_run"]),
            "steps": fitted["steps"], "l1_before": fitted["l1"]["mean_before"], "l1_after": fitted["l1"]["mean"],
            "seconds": report["seconds"]}


def _tracking_line(tracking: dict, report: str) -> str:
    return (f"Tracking: {tracking['frames_fitted']} test frames, {tracking['steps']} Adam steps each against the "
            f"frozen avatar (the {tracking['frames_from_run']} training frames keep the parameters training refined); "
            f"L1 {tracking['l1_before']:.4f} -> {tracking['l1_after']:.4f} in {tracking['seconds']:.0f} s (`{report}`).")


def _user_path(out: Path, data: Path, tracked: Path, run: Path, render_video: Path, **settings) -> list[str]:
    """The demo's stages as the commands a user types (the generated subject stands for `prepare`'s dataset)."""
    px = settings["picture_resolution"]
    return [
        f"geoavatar synth --out {data} --subject 0 --frames {settings['frames']} --size {settings['size']} "
        f"--seed {settings['seed']} --preview",
        f"geoavatar train --data {data} --out {run} --preset E --steps {settings['steps']} "
        f"--resolution {settings['resolution']} --seed {settings['seed']}",
        f"geoavatar track {data} --avatar {run} --out {tracked} --steps {settings['track_steps']}",
        f"geoavatar eval {run} --data {tracked}",
        f"geoavatar eval {run} --no-faces --no-floaters      # the written parameters",
        f"geoavatar render {run} --data {tracked} --resolution {px} --out {render_video}",
    ]


def _aps_summary(aps: dict) -> str:
    """A short text of which parts went rigid/flexible, whatever the exact JSON layout."""
    report = aps.get("report")
    if isinstance(report, str):
        return report
    return json.dumps(aps, indent=1)[:2000]
