"""`geoavatar demo`: the main job on the embedded default, end to end, with a report to open.

The steps a user's own video takes after `prepare` (#31): generate a subject → train GeoAvatar (preset E) → fit the
held-out test frames against the trained avatar (`train`'s last stage, train/held_out_fit.py) → evaluate them
(`geoavatar eval RUN`; with the generated subject's written parameters beside it, `--test-params dataset`) → render
the self re-enactment of the test frames, a novel-view orbit and a cross re-enactment driven by a second generated
subject, at 256 px (larger than the training images) → the browser player of the avatar (demo_output/web/, `export
--format web`) → the voice: learned, scored, speaking → demo_output/report.md (and report.json) led by the test
score, with the time of every stage and pictures.

Each stage writes into its own folder and is skipped when its output is already complete, so an
interrupted demo continues where it stopped (training itself resumes from its last checkpoint).
"""

from __future__ import annotations

import functools
import json
import platform
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Literal

from geoavatar.eval.speech import speech_dir
from geoavatar.io.atomic import atomic_write_png, atomic_write_text
from geoavatar.train.held_out_fit import HELD_OUT_REPORT

DRIVER_SUBJECT = 1


@dataclass
class DemoSettings:
    """The demo's schedule: the paper's method on a CPU-sized budget (all milestones scale with steps)."""

    frames: int = 160  # generated video length (25 fps); the last 25 % are the test split
    size: int = 256  # generated image size
    resolution: int = 128  # training / evaluation resolution (longer side)
    picture_resolution: int = 256  # the videos' and stills' longer side (at most `size`: images are never enlarged)
    steps: int = 1500  # training steps (the paper: 200k on a GPU)
    driver_frames: int = 60  # length of the cross re-enactment driver
    orbit_frames: int = 48
    seed: int = 0
    voice_steps: int = 400  # the voice model's steps (a 4.8 s training part: the default 1000 gain nothing here)
    speech_seconds: float = 4.0  # the clip the avatar says
    speech_pictures: int = 10  # held-out frames rendered for eval --speech's picture scores (its face scores: all)


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
    driver_frames: int = DemoSettings.driver_frames,
    voice_steps: int = DemoSettings.voice_steps,
    seed: int = DemoSettings.seed,
    device: str = "auto",
    backend: Literal["auto", "cpu", "torch", "gsplat"] = "auto",
    progress: bool = True,
) -> int:
    """Run the whole pipeline on a generated subject and write OUT/report.md.

    Generates subject 0 with its voice (and subject 1 as a driver), trains GeoAvatar (preset E) on the first 75 %
    of the video, fits the held-out last 25 % against the trained avatar as `geoavatar train` does at its end,
    evaluates MSE/PSNR/SSIM/LPIPS on them (`geoavatar eval RUN`) and, beside it, on the generated subject's written
    parameters (`--test-params dataset`: their simulated tracker error, which the avatar never saw), renders the
    test re-enactment (ground truth | render | error), a novel-view orbit and a cross re-enactment at
    --picture-resolution, learns the subject's voice from its training frames, scores it on the held-out frames'
    sound (`geoavatar eval RUN --speech`) and makes the avatar say a clip it never heard (`geoavatar speak`), and
    writes report.md (led by the test score) and report.json with timings and pictures. Re-running continues an
    interrupted demo. The defaults take 2-6 minutes on 2 CPU cores (docs/demo.md).

    Args:
        out: Output folder (data/, run/, videos, stills and report.md go here).
        steps: Training steps (every milestone of the paper's 200k-step schedule scales with it).
        frames: Length of the generated training video (the last 25 % are the test split).
        size: Size of the generated images.
        resolution: Training and evaluation resolution (longer side, pixels).
        picture_resolution: Longer side of the videos and stills (pixels; at most --size).
        driver_frames: Length of the second subject's video that drives the cross re-enactment.
        voice_steps: Training steps of the voice model (`geoavatar voice --steps`).
        seed: Seed of the generated motion and of training.
        device: auto (CUDA when available, else CPU), cpu or cuda.
        backend: Rasterizer of every stage: auto (gsplat on CUDA, the native cpu kernel on CPU when it
            builds, else torch), cpu, torch or gsplat; `--backend torch` times the demo without the
            native kernel.
        progress: Show progress bars.
    """
    if (steps <= 0 or frames < 8 or size < 32 or resolution < 32 or picture_resolution < 32 or driver_frames < 2
            or voice_steps <= 0):
        raise SystemExit("geoavatar demo: need --steps > 0, --frames >= 8, --size >= 32, --resolution >= 32, "
                         "--picture-resolution >= 32, --driver-frames >= 2, --voice-steps > 0")
    plan = DemoPlan(Path(out), DemoSettings(frames, size, resolution, min(picture_resolution, size), steps,
                                            driver_frames, seed=seed, voice_steps=voice_steps),
                    device, backend, progress)
    plan.out.mkdir(parents=True, exist_ok=True)
    timer = StageTimer(plan.out / "timings.json")
    for name, done, action in plan.stages():
        timer.run(name, done, action)
    stills = {name: plan.out / f"{name}.png" for name in plan.videos}
    for name, video in plan.videos.items():
        if video.is_file():  # no speech video when the subject was too short to learn a voice
            save_still(video, stills[name])
    report = write_report(plan, stills, timer.seconds)
    print()
    print(f"Demo finished: {sum(timer.seconds.values()) / 60:.1f} min of stage time in all.")
    print(f"Open {report} (metrics, timings, pictures); videos: {', '.join(str(v) for v in plan.videos.values())}")
    print(f"The avatar in your browser: python3 -m http.server 8000 --bind 127.0.0.1 --directory {plan.player}\n"
          f"  then open http://127.0.0.1:8000/ (or: geoavatar view {plan.run}, with expression and jaw sliders)")
    return 0


@dataclass
class DemoPlan:
    """Where the demo's stages write, and the stages themselves (each: a name, whether it is done, what it does)."""

    out: Path
    settings: DemoSettings
    device: str = "auto"
    backend: str = "auto"
    progress: bool = True

    def __post_init__(self) -> None:
        out = self.out
        self.data, self.driver, self.run = out / "data" / "subject0", out / "data" / "driver", out / "run"
        self.new_speech = out / "data" / "new_speech.wav"  # a clip of the subject's voice it never said
        self.videos = {"render": out / "render_test.mp4", "orbit": out / "orbit.mp4", "reenact": out / "reenact.mp4",
                       "speak": out / "speak.mp4"}
        self.metrics = {"fitted": self.run / "eval" / "test" / "metrics.json",  # the held-out fit's parameters
                        "written": self.run / "eval" / "test@dataset_params" / "metrics.json"}  # the generator's
        self.speech_metrics = speech_dir(self.run) / "metrics.json"
        self.player = out / "web"

    def stages(self) -> list[tuple[str, Callable[[], bool], Callable[[], object]]]:
        return [*self._subject_stages(), *self._evaluation_stages(), *self._picture_stages(), *self._speech_stages()]

    def _subject_stages(self):
        from geoavatar.apps.synth import synth
        from geoavatar.apps.train import TrainArgs, train
        from geoavatar.data.layout import is_layout
        from geoavatar.train.options import RunOptions

        s, run = self.settings, self.run
        resume = (run / "checkpoints" / "last.pt").is_file()
        return [
            ("generate subject", lambda: is_layout(self.data),
             lambda: synth(out=self.data, subject=0, frames=s.frames, size=s.size, seed=s.seed, preview=True,
                           sound=True, progress=self.progress)),
            ("generate driver", lambda: is_layout(self.driver),
             lambda: synth(out=self.driver, subject=DRIVER_SUBJECT, frames=s.driver_frames, size=s.size,
                           seed=s.seed + 1, progress=self.progress)),
            ("train GeoAvatar (preset E)", (run / "checkpoints" / "final.pt").is_file,
             lambda: _checked(train(TrainArgs(
                 RunOptions(out=run, data=self.data, preset=None if resume else "E", resolution=s.resolution,
                            seed=s.seed, device=self.device, backend=self.backend, progress=self.progress),
                 steps=None if resume else s.steps, resume=resume, held_out_fit=False, voice=False)), "train")),
        ]

    def _evaluation_stages(self):
        from geoavatar.apps.eval import eval_runs
        from geoavatar.train.held_out_fit import fit_held_out

        common = {"device": self.device, "progress": self.progress}
        # the user's path: train ends by fitting the held-out frames against the avatar (a stage of its own here, to
        # time it), then they are scored; beside them the eval on the generator's written parameters
        return [
            ("fit the test frames against the avatar", (self.run / HELD_OUT_REPORT).is_file,
             lambda: fit_held_out(self.run, progress=self.progress)),
            ("evaluate (test split)", self.metrics["fitted"].is_file,
             lambda: _checked(eval_runs([self.run], split="test", backend=self.backend, **common), "eval")),
            ("evaluate (test split, written parameters)", self.metrics["written"].is_file,
             lambda: _checked(eval_runs([self.run], split="test", faces=False, floaters=False, backend=self.backend,
                                        test_params="dataset", **common), "eval")),
        ]

    def _picture_stages(self):
        from geoavatar.apps.export import export
        from geoavatar.apps.orbit import orbit
        from geoavatar.apps.reenact import reenact
        from geoavatar.apps.render_video import render

        px, videos = self.settings.picture_resolution, self.videos
        common = {"device": self.device, "backend": self.backend, "progress": self.progress}
        return [
            ("render test re-enactment", videos["render"].is_file,
             lambda: _checked(render(self.run, split="test", out=videos["render"], resolution=px, **common),
                              "render")),
            ("render novel-view orbit", videos["orbit"].is_file,
             lambda: _checked(orbit(self.run, out=videos["orbit"], frames=DemoSettings.orbit_frames, resolution=px,
                                    **common), "orbit")),
            ("render cross re-enactment", videos["reenact"].is_file,
             lambda: _checked(reenact(self.run, driver=self.driver, out=videos["reenact"], relative=True,
                                      resolution=px, **common), "reenact")),
            ("write the web player", (self.player / "avatar.json").is_file,
             lambda: _checked(export(self.run, out=self.player, format="web", overwrite=True, device=self.device,
                                     progress=self.progress), "export")),
        ]

    def _speech_stages(self):
        from geoavatar.apps.eval import eval_runs
        from geoavatar.apps.speak import speak
        from geoavatar.apps.voice import learn_voice
        from geoavatar.train.checkpoint import open_run
        from geoavatar.voice import VoiceConfig, VoiceModel
        from geoavatar.voice.model import INFO_FILE, VOICE_DIR

        px, s = self.settings.picture_resolution, self.settings
        learned = Path(self.run) / VOICE_DIR / INFO_FILE

        def after_the_voice(path: Path) -> bool:  # made from the voice there now (not one learned before it)
            return path.is_file() and path.stat().st_mtime >= learned.stat().st_mtime

        # a subject too short to learn a voice from: these stages are skipped (the report says so)
        return [
            ("learn the voice", lambda: VoiceModel.readable(self.run) or self.mute,  # an older one: learned again
             # the generated sound is a known function of the mouth: a few seconds teach it, no advice to film more
             lambda: learn_voice(open_run(self.run, "cpu"), config=VoiceConfig(steps=s.voice_steps, seed=s.seed),
                                 advise=False)),
            ("evaluate the voice (held-out sound)", lambda: self.mute or after_the_voice(self.speech_metrics),
             lambda: _checked(eval_runs([self.run], speech=True, max_frames=s.speech_pictures,
                                        device=self.device, backend=self.backend, progress=self.progress),
                              "eval --speech")),
            ("speak a clip it never heard", lambda: self.mute or after_the_voice(self.videos["speak"]),
             lambda: _checked(speak(self.run, audio=self._new_speech(), out=self.videos["speak"], resolution=px,
                                    seed=s.seed, device=self.device, backend=self.backend, progress=self.progress),
                              "speak")),
        ]

    @functools.cached_property
    def mute(self) -> bool:
        """Whether the generated subject holds too little speech to learn a voice from (a very short --frames); read
        once, after the subject is generated."""
        from geoavatar.data.sound import read_dataset_sound

        sound = read_dataset_sound(self.data)
        return sound is None or not sound.activity.has_speech

    def _new_speech(self) -> Path:
        from geoavatar.data.synth.sound import new_speech
        from geoavatar.sound import write_wav

        return write_wav(self.new_speech, new_speech(DemoSettings.speech_seconds, seed=self.settings.seed + 11))


def save_still(video: Path, png: Path, position: float = 0.5) -> Path:
    """The frame at `position` (0..1) of an mp4 as a PNG (written atomically)."""
    import av

    with av.open(str(video)) as container:
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    if not frames:
        raise SystemExit(f"geoavatar demo: {video} holds no frames")
    image = frames[min(len(frames) - 1, int(position * len(frames)))]
    return atomic_write_png(png, image)


def write_report(plan: DemoPlan, stills: dict[str, Path], seconds: dict[str, float]) -> Path:
    """OUT/report.md, led by the test score of the test frames fitted against the avatar with the written parameters'
    beside it, and OUT/report.json with the same figures (per path: mean and std of PSNR, SSIM, LPIPS, MSE and the mouth's)."""
    out, settings = plan.out, plan.settings
    scores = {path: json.loads(file.read_text()) for path, file in plan.metrics.items()}
    figures = {path: _figures(score["summary"]) for path, score in scores.items()}
    speech = json.loads(plan.speech_metrics.read_text()) if plan.speech_metrics.is_file() else None
    fit = json.loads((plan.run / HELD_OUT_REPORT).read_text())
    rel = lambda p: Path(p).relative_to(out).as_posix()  # noqa: E731
    lines = [*_score_lines(plan, figures, fit, len(scores["fitted"]["frames"]), rel),
             *_speech_lines(plan, speech, rel), *_picture_lines(plan, stills, rel), _aps_text(plan.run),
             *_time_lines(seconds), *_reproduce_lines(plan, rel)]
    atomic_write_text(out / "report.json", json.dumps({
        "format": "geoavatar-demo", "version": 1,
        "test": {"lead": "fitted", **figures},  # per path: the test frames' parameters
        "frames_evaluated": len(scores["fitted"]["frames"]),
        "held_out_fit": fit,
        "speech": None if speech is None else ({key: speech.get(key) for key in SPEECH_KEYS}
                                               | {"baselines": speech.get("baselines", {})}),
        "metrics": {path: rel(file) for path, file in plan.metrics.items()}
        | ({"speech": rel(plan.speech_metrics)} if speech is not None else {}),
        "pictures": {"resolution": settings.picture_resolution,
                     "stills": {n: rel(png) for n, png in stills.items() if png.is_file()},
                     "videos": {name: rel(video) for name, video in plan.videos.items() if video.is_file()}},
        "settings": {key: getattr(settings, key) for key in ("frames", "size", "steps", "resolution", "voice_steps",
                                                             "seed")} | {"backend": plan.backend},
        "seconds": {name: round(sec, 1) for name, sec in seconds.items()},
        "total_seconds": round(sum(seconds.values()), 1),
    }, indent=1) + "\n")
    return atomic_write_text(out / "report.md", "\n".join(lines))


SPEECH_KEYS = ("lip_vertex_error", "mouth_open_correlation", "lag_ms", "upper_face_dynamics", "psnr", "lpips",
               "mouth_psnr")


def _score_lines(plan: DemoPlan, figures: dict, fit: dict, evaluated: int, rel) -> list[str]:
    s, lead = plan.settings, figures["fitted"]
    # the eval's report without its own title, its sections one level down, so it nests under this heading
    table = "\n".join("##" + line if line.startswith("## ") else line
                      for line in (plan.metrics["fitted"].parent / "metrics.md").read_text().strip().splitlines()
                      if not line.startswith("# "))
    return [
        "# GeoAvatar demo", "",
        f"A generated subject ({s.frames} frames, with its voice), GeoAvatar (preset E) trained for {s.steps} steps at "
        f"{s.resolution} px on {platform.processor() or platform.machine()} (rasterizer backend '{plan.backend}') "
        "on the first 75 % of the video, and tested on the held-out last 25 % (poses and expressions not seen in "
        "training) the way your own video is: their parameters fitted against the trained avatar (`geoavatar "
        "train`'s last stage), then scored.", "",
        "## Test-split score", "",
        f"**{_headline(lead)}** on the {evaluated} held-out frames fitted against the avatar (`geoavatar eval RUN`).",
        "", "| test frames' parameters | PSNR ↑ | SSIM ↑ | LPIPS ↓ | mouth PSNR ↑ |", "|---|---:|---:|---:|---:|",
        f"| **fitted against the avatar** (`{rel(plan.run / HELD_OUT_REPORT)}`) | {_row(lead, bold=True)} |",
        f"| written by the generator (`geoavatar eval RUN --test-params dataset`) | {_row(figures['written'])} |", "",
        "The written parameters carry the generator's simulated tracker error, which the avatar never saw (on the test "
        "frames mostly a drift in depth); the fit against the avatar takes it away as it would a real tracker's, so "
        "the second score measures that error more than the avatar.", "",
        _fit_line(fit, rel(plan.run / HELD_OUT_REPORT)), "",
        "### The test frames in full (`geoavatar eval RUN`)", "",
        table, "",
        f"Frames evaluated: {evaluated}. Per-frame values: `{rel(plan.metrics['fitted'])}`; with the written "
        f"parameters: `{rel(plan.metrics['written'])}`.", "",
    ]


def _speech_lines(plan: DemoPlan, speech: dict | None, rel) -> list[str]:
    if speech is None:
        return ["## The avatar speaks", "", f"Not in this demo: its {plan.settings.frames}-frame subject holds too "
                "little speech to learn a voice from (the default 160 frames hold 4.5 s).", ""]
    table = (plan.speech_metrics.parent / "metrics.md").read_text().strip().splitlines()
    table = [line for line in table if line.startswith("|")]
    r, lag = speech.get("mouth_open_correlation"), speech.get("lag_ms")
    headline = (f"mouth-open r {'–' if r is None else f'{r:.2f}'}, LVE {speech['lip_vertex_error']:.2e} m², "
                f"lag {'–' if lag is None else f'{lag:+.0f}'} ms")
    return [
        "## The avatar speaks", "",
        f"The subject's voice model, learned from its training frames' sound, drives the {speech['frames']} held-out "
        f"frames by their own sound (never heard in training; `geoavatar eval RUN --speech`, the head pose and the "
        f"reference parameters from the held-out fit; pictures on {plan.settings.speech_pictures} of the "
        f"frames): **{headline}** "
        f"(`{rel(plan.speech_metrics)}`).", "",
        *table, "",
        f"The avatar saying a clip of the same voice it never heard (`geoavatar speak RUN --audio "
        f"{rel(plan.new_speech)}`, an mp4 with its sound): `{rel(plan.videos['speak'])}`", "",
    ]


def _picture_lines(plan: DemoPlan, stills: dict[str, Path], rel) -> list[str]:
    videos = plan.videos
    return [
        "## Pictures", "",
        f"At {plan.settings.picture_resolution} px (the avatar was trained at {plan.settings.resolution} px).", "",
        f"Self re-enactment of the test frames (ground truth | render | error): `{rel(videos['render'])}`", "",
        f"![test re-enactment]({rel(stills['render'])})", "",
        f"Novel views (yaw/pitch orbit): `{rel(videos['orbit'])}`", "",
        f"![orbit]({rel(stills['orbit'])})", "",
        f"Cross re-enactment driven by a second generated subject (relative expressions): `{rel(videos['reenact'])}`",
        "", f"![cross re-enactment]({rel(stills['reenact'])})", "",
        *([f"The avatar speaking: `{rel(videos['speak'])}`", "", f"![speaking]({rel(stills['speak'])})", ""]
          if stills["speak"].is_file() else []),
        f"The generated subject across its sequence: `{rel(plan.data / 'preview.png')}`", "",
        f"The animated avatar in a browser (test split, posed on the GPU): `python3 -m http.server 8000 --bind "
        f"127.0.0.1 --directory {plan.player}`, then open http://127.0.0.1:8000/ (docs/web_player.md).",
    ]


def _aps_text(run: Path) -> str:
    aps = run / "aps.json"
    if not aps.is_file():
        return ""
    return "\n## Adaptive Pre-allocation Stage\n\n```\n" + _aps_summary(json.loads(aps.read_text())) + "\n```\n"


def _time_lines(seconds: dict[str, float]) -> list[str]:
    return ["## Time", "", "| stage | time |", "|---|---|",
            *(f"| {name} | {sec / 60:.1f} min |" for name, sec in seconds.items()),
            f"| **total** | **{sum(seconds.values()) / 60:.1f} min** |", ""]


def _reproduce_lines(plan: DemoPlan, rel) -> list[str]:
    s = plan.settings
    return [
        "## Reproduce", "", "```bash",
        f"geoavatar demo --out {plan.out} --steps {s.steps} --frames {s.frames} --size {s.size} "
        f"--resolution {s.resolution} --picture-resolution {s.picture_resolution} --voice-steps {s.voice_steps}",
        "```", "", "or the same steps one by one, as for your own video after `geoavatar prepare`:", "", "```bash",
        *_user_path(plan), "```", "",
        f"Training log: `{rel(plan.run / 'train.log')}`; validation images: `{rel(plan.run / 'val')}`.", "",
    ]


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


def _fit_line(fit: dict, report: str) -> str:
    return (f"The fit: {fit['frames']} test frames, {fit['steps']} Adam steps each against the frozen avatar, each from "
            f"its neighbour's correction (the training frames keep the parameters training refined); L1 "
            f"{fit['l1_before']:.4f} -> {fit['l1']:.4f} in {fit['seconds']:.0f} s on {fit['workers']} worker(s) "
            f"(`{report}`).")


def _user_path(plan: DemoPlan) -> list[str]:
    """The demo's stages as the commands a user types (the generated subject stands for `prepare`'s dataset)."""
    s, data, run = plan.settings, plan.data, plan.run
    return [
        f"geoavatar synth --out {data} --subject 0 --frames {s.frames} --size {s.size} --seed {s.seed} --preview "
        "--sound",
        f"geoavatar train --data {data} --out {run} --preset E --steps {s.steps} --resolution {s.resolution} "
        f"--seed {s.seed} --no-voice      # ends with the held-out fit",
        f"geoavatar eval {run}",
        f"geoavatar eval {run} --test-params dataset --no-faces --no-floaters      # the written parameters",
        f"geoavatar render {run} --split test --resolution {s.picture_resolution} --out {plan.videos['render']}",
        f"geoavatar voice {run} --steps {s.voice_steps}      # train learns it itself without --no-voice",
        f"geoavatar eval {run} --speech --max-frames {s.speech_pictures}",
        f"geoavatar speak {run} --audio {plan.new_speech} --out {plan.videos['speak']}",
    ]


def _aps_summary(aps: dict) -> str:
    """A short text of which parts went rigid/flexible, whatever the exact JSON layout."""
    report = aps.get("report")
    if isinstance(report, str):
        return report
    return json.dumps(aps, indent=1)[:2000]
