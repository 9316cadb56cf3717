"""`geoavatar eval RUN [RUN ...]`: MSE, PSNR, SSIM, LPIPS (+ mouth PSNR / LPIPS, face metrics) of trained runs;
`geoavatar eval RUN --driver DATA | --driver-video FILE`: a cross re-enactment scored without ground truth."""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import TYPE_CHECKING, Literal, Optional, Sequence

import tyro

from geoavatar.animation.expression_transfer import TransferMode
from geoavatar.errors import OptionError

if TYPE_CHECKING:
    import torch

    from geoavatar.eval.evaluate import EvalConfig, EvalResult


def _common_parent(paths: list[Path]) -> Path:
    try:
        return Path(os.path.commonpath([str(p.resolve()) for p in paths]))
    except ValueError:  # different drives
        return Path.cwd()


def eval_runs(
    runs: tyro.conf.Positional[list[Path]],
    split: Literal["test", "val", "train", "novel"] = "test",
    lpips_net: Literal["vgg", "alex"] = "vgg",
    out: Optional[Path] = None,
    max_frames: Optional[int] = None,
    device: str = "auto",
    data: Optional[Path] = None,
    test_params: Literal["fitted", "dataset"] = "fitted",
    checkpoint: Literal["last", "final"] = "last",
    save_images: bool = False,
    lpips_unit_inputs: bool = False,
    mouth: bool = True,
    floaters: bool = True,
    floater_frames: int = 4,
    backend: Literal["auto", "cpu", "torch", "gsplat"] = "auto",
    flame_dir: Optional[Path] = None,
    progress: bool = True,
    faces: bool = True,
    driver: Optional[Path] = None,
    driver_video: Optional[Path] = None,
    relative: bool = False,
    transfer: tuple[TransferMode, ...] = (),
    driver_cache: Optional[Path] = None,
    speech: bool = False,
    loudness: Literal["own", "video"] = "own",
) -> int:
    """Evaluate trained runs on a split of their datasets, as the paper's Table 1 does, or score one run's cross
    re-enactment (--driver / --driver-video), as the paper's appendix does.

    Renders every frame of the split, composites the ground truth on the dataset's background as
    GaussianAvatars and INSTA do, and measures MSE, PSNR, SSIM and LPIPS per frame (mean ± std), plus
    PSNR and LPIPS of the mouth region (mouth-structure + lips faces). Test frames are unseen
    timesteps: T = 0 for the mouth deformer, and the parameters `train` fitted for them against the finished avatar
    (its held-out fit; a run without one, or another copy of the dataset: the dataset's tracked parameters);
    metrics.json says which (settings.test_params).
    Writes RUN/eval/SPLIT/metrics.json (per frame, summary, settings) and metrics.md (Table 1 layout)
    for each run (RUN/eval/SPLIT@COPY with --data COPY, another copy of the run's dataset); with several runs
    also one comparison table (Table 1 and ablation layouts). Face metrics (--no-faces skips them): dlib identity
    similarity of each render to the avatar's training frames, FER2013 expression similarity to the ground truth,
    and the landmark agreement of mouth, eyes and brows over the clip (docs/cross_reenactment.md).

    With --driver DATA or --driver-video FILE, one run is driven as `geoavatar reenact` drives it, once per
    --transfer mode, and each render is scored against the driver's frame (identity against the avatar's training
    frames, expression and landmarks against the driver): RUN/eval/cross@<driver>/metrics.json (per frame and
    summary, per mode) and metrics.md (rows = modes). Renders without a detected face are counted, not scored.

    Args:
        runs: One or more RUN folders written by `geoavatar train`.
        split: Frames to evaluate: test (held-out last frames), val, train, or novel (test frames seen from
            other cameras, with metrics per view: datasets from `geoavatar synth --novel-views`).
        lpips_net: LPIPS backbone: vgg (as the 3DGS / GaussianAvatars evaluation) or alex.
        out: Comparison table file (Markdown; a .json beside it), written when several runs are given or this is
            set; never an existing run report (default: eval_SPLIT_comparison.md in the runs' common parent folder).
        max_frames: Evaluate only this many frames, spread evenly over the split (default: all).
        device: auto (CUDA when available, else CPU), cpu, cuda or cuda:N.
        data: Dataset folder, when it moved since training (default: the one the run recorded), or another copy of
            it, e.g. `geoavatar track --avatar`'s: while the recorded folder exists, the report of a copy goes to
            RUN/eval/SPLIT@COPY (COPY: the copy's folder name, or OUT's for prepare's OUT/dataset), so the run's own
            report is kept.
        test_params: The parameters of the held-out frames: fitted (those `train` fitted against the finished
            avatar, its last stage) or dataset (the tracker's, as the dataset holds them: the GaussianAvatars
            protocol, nothing fitted at test time; reported in RUN/eval/SPLIT@dataset_params). A run trained with
            --no-held-out-fit, or another copy of the dataset (--data COPY), always uses the dataset's.
        checkpoint: Which checkpoint of each run: last or final.
        save_images: Also write RUN/eval/SPLIT/frames/*.png (gt | render | error x4 | mouth mask).
        lpips_unit_inputs: Feed [0, 1] images to LPIPS unscaled, as the 3DGS scripts do (only then are
            numbers comparable with theirs); default: [-1, 1], as LPIPS is defined.
        mouth: Measure the mouth region too (--no-mouth skips it).
        floaters: Measure the share of rendered opacity outside the dilated silhouette of the posed head mesh,
            per frame and at side views (yaw +-30/60/90, pitch +-20) of a few frames (--no-floaters skips it).
        floater_frames: Frames of the split rendered at the side views.
        backend: Rasterizer: auto (gsplat on CUDA, the native cpu kernel on CPU when it builds, else torch), cpu, torch or gsplat.
        flame_dir: Folder with your FLAME model files (runs on FLAME-tracked data only).
        progress: Show progress bars.
        faces: Measure the face metrics (dlib identity similarity, FER2013 expression similarity, landmark
            agreement); --no-faces skips them.
        driver: Score a cross re-enactment: the tracked dataset that drives the run (as `reenact --driver`).
        driver_video: Score a cross re-enactment driven by a video, tracked and cached as `reenact --driver-video`
            does (RUN/drivers/, reused by reenact and later calls).
        relative: With a driver: the same as --transfer relative.
        transfer: With a driver: the transfer modes to score, each a row of the report (absolute, relative,
            statistics, subspace; default: reenact's default mode).
        driver_cache: With --driver-video: the folder of its tracking (as `reenact --driver-cache`).
        speech: Score the run's voice model instead: the held-out segment driven by its own sound (never heard in
            training) against its tracked parameters, beside the mean-face, nearest and linear baselines:
            RUN/eval/speech/metrics.json and metrics.md (docs/speech.md). The face scores use every held-out frame,
            the picture scores 40 of them spread evenly (--max-frames N: N of them). With --data COPY (track
            --avatar's), the copy's parameters of the held-out frames are the reference and give the head pose:
            RUN/eval/speech@COPY/.
        loudness: With --speech: how the held-out sound is normalised, as `speak --loudness` does: own (its own
            speech statistics, as a new recording is) or video (the training sound's, the same recording's loudness,
            the mean mouth following the segment's level): RUN/eval/speech@video-loudness/.
    """
    mode = _eval_mode(runs, split, out, driver, driver_video, driver_cache, relative, transfer, speech)
    if loudness != "own" and mode != "speech":
        raise OptionError("--loudness goes with --speech")
    if mode == "speech":
        given = {"--lpips-net": lpips_net != "vgg", "--lpips-unit-inputs": lpips_unit_inputs,
                 "--test-params": test_params != "fitted", "--save-images": save_images,
                 "--driver-cache": driver_cache is not None, "--relative": relative, "--transfer": bool(transfer)}
        if any(given.values()):  # said, not dropped: each would change what the scores mean
            raise OptionError(f"{', '.join(k for k, v in given.items() if v)}: not with --speech (it scores with VGG "
                              "LPIPS against the run's held-out parameters, or --data COPY's)")
        return eval_speech(runs[0], max_frames, device, data, checkpoint, backend, flame_dir, progress, loudness)
    if mode == "cross":
        return eval_cross(runs[0], driver, driver_video, driver_cache, relative, transfer, max_frames, device, data,
                          checkpoint, backend, flame_dir, progress)
    return _eval_split(runs, split, lpips_net, out, max_frames, device, data, test_params, checkpoint, save_images,
                       lpips_unit_inputs, mouth, floaters, floater_frames, backend, flame_dir, progress, faces)


def _eval_mode(runs: list[Path], split: str, out: Path | None, driver: Path | None, driver_video: Path | None,
               driver_cache: Path | None, relative: bool, transfer: tuple[str, ...], speech: bool) -> str:
    """What `geoavatar eval` was asked to do: "speech" (--speech), "cross" (--driver / --driver-video) or "split"
    (score runs on a split of their datasets). OptionError for options that do not go with it."""
    if speech:
        if len(runs) != 1 or split != "test" or out is not None or driver is not None or driver_video is not None:
            raise OptionError("--speech scores one RUN's held-out frames (no --split, --out, --driver)")
        return "speech"
    if driver is not None or driver_video is not None or driver_cache is not None:
        if len(runs) != 1 or split != "test" or out is not None:
            raise OptionError("--driver / --driver-video score one RUN (no --split, no --out)")
        return "cross"
    if relative or transfer:
        raise OptionError("--relative and --transfer go with --driver or --driver-video")
    return "split"


def _eval_split(runs: list[Path], split: str, lpips_net: str, out: Path | None, max_frames: int | None, device: str,
                data: Path | None, test_params: str, checkpoint: str, save_images: bool, lpips_unit_inputs: bool,
                mouth: bool, floaters: bool, floater_frames: int, backend: str, flame_dir: Path | None,
                progress: bool, faces: bool) -> int:
    """`geoavatar eval RUN [RUN ...]`: each run's RUN/eval/SPLIT report, then its metric table (one run) or the
    comparison of the runs (several, or --out)."""
    from geoavatar.eval.evaluate import EvalConfig
    from geoavatar.eval.report import check_comparison_target
    from geoavatar.runtime import resolve_device

    if not runs:
        raise SystemExit("geoavatar eval: give at least one RUN folder")
    config = EvalConfig(split=split, lpips_net=lpips_net, lpips_unit_inputs=lpips_unit_inputs, max_frames=max_frames,
                        mouth=mouth, backend=backend, keep_images=save_images, floaters=floaters,
                        floater_frames=floater_frames, faces=faces, test_params=test_params)
    config.validate()  # OptionError naming the option
    if out is not None:
        check_comparison_target(out)  # before the evaluation, not after it
    try:
        torch_device = resolve_device(device)
    except ValueError as err:  # resolve_device's messages name --device
        raise OptionError(str(err)) from err
    # RunError, DatasetError, LPIPSWeightsError...: GeoAvatarErrors, one line at the CLI
    results = [_evaluate_and_report(run_dir, config, split, test_params, torch_device, data, checkpoint, flame_dir,
                                    progress) for run_dir in runs]
    if len(results) == 1 and out is None:
        _print_run_tables(results)
    else:
        _write_comparison(results, runs, split, out)
    return 0


def _evaluate_and_report(run_dir: Path, config: EvalConfig, split: str, test_params: str, torch_device: torch.device,
                         data: Path | None, checkpoint: str, flame_dir: Path | None, progress: bool) -> EvalResult:
    """Evaluate one run, write its report (report_dir; the dataset's own parameters beside the
    fitted report) and say where it went."""
    from geoavatar.eval.evaluate import evaluate_run
    from geoavatar.eval.report import write_run_report
    from geoavatar.train.checkpoint import load_run

    run = load_run(run_dir, device=torch_device, checkpoint=checkpoint, flame_dir=flame_dir)
    result = evaluate_run(run, config, data=data, progress=progress, flame_dir=flame_dir)
    folder = report_dir(run.info.run_dir, split, run.info.data_root, data)
    if test_params == "dataset" and folder.name == split:  # the run's own dataset: beside the fitted report
        folder = folder.with_name(f"{split}@dataset_params")
    written = write_run_report(result, folder)
    left_out = result.settings.get("frames_left_out_unscored") or 0
    scored = f" (the held-out fit's runs; {left_out} frames between them not scored)" if left_out else ""
    print(f"{result.label}: {len(result.frames)} {split} frames{scored} in {result.seconds:.1f} s -> {written['json']}")
    return result


def _print_run_tables(results: list[EvalResult]) -> None:
    """One run's metric table and extra sections, on stdout."""
    from geoavatar.eval.report import extra_sections, metric_table

    print(metric_table(results, mark_best=False), end="")
    print(extra_sections(results), end="")


def _write_comparison(results: list[EvalResult], runs: list[Path], split: str, out: Path | None) -> None:
    """The comparison table of the runs, at `out` (default: eval_SPLIT_comparison.md in the runs' common parent
    folder) and on stdout."""
    from geoavatar.eval.report import comparison_markdown, distinct_labels, write_comparison

    results = distinct_labels(results)  # two runs of one preset on one dataset: their folders tell them apart
    target = out if out is not None else _common_parent(list(runs)) / f"eval_{split}_comparison.md"
    written = write_comparison(results, target)
    print(comparison_markdown(results), end="")
    print(f"comparison: {written['markdown']} (+ {written['json'].name})")


def eval_cross(run_dir: Path, driver: Path | None, driver_video: Path | None, driver_cache: Path | None,
               relative: bool, transfer: tuple[str, ...], max_frames: int | None, device: str, data: Path | None,
               checkpoint: str, backend: str, flame_dir: Path | None, progress: bool) -> int:
    """`geoavatar eval RUN --driver ...`: the cross re-enactment report, RUN/eval/cross@<driver>/."""
    from geoavatar.animation.expression_transfer import resolve_transfer
    from geoavatar.animation.sources.driver import DrivenAvatar, DrivingOptions
    from geoavatar.animation.sources.driver_video import track_driver
    from geoavatar.apps.reenact import check_driver_options
    from geoavatar.eval.cross import cross_dir, mode_table, write_cross_report
    from geoavatar.runtime import resolve_device
    from geoavatar.train.checkpoint import load_run

    modes = list(dict.fromkeys(resolve_transfer(mode, False) for mode in transfer)) if transfer else \
        [resolve_transfer(None, relative)]
    if relative and modes != ["relative"]:
        raise OptionError(f"--relative means --transfer relative; it cannot go with --transfer {' '.join(transfer)}")
    if max_frames is not None and max_frames <= 0:
        raise OptionError(f"--max-frames must be positive, got {max_frames}")
    check_driver_options(driver, driver_video, driver_cache, None, False, "eval")
    try:
        torch_device = resolve_device(device)
    except ValueError as err:
        raise OptionError(str(err)) from err
    run = load_run(run_dir, device=torch_device, checkpoint=checkpoint, flame_dir=flame_dir)
    root, _, name = track_driver(run, driver, driver_video, driver_cache, flame_dir=flame_dir, progress=progress)
    driven = DrivenAvatar(run, root, DrivingOptions(transfer=modes[0], data=data, backend=backend))
    result = evaluate_cross(run, driven, modes, name, max_frames, data=data, flame_dir=flame_dir, progress=progress)
    written = write_cross_report(result, cross_dir(run.info.run_dir, name))
    print(mode_table(result.summaries), end="")
    print(f"{result.label} driven by {name}: {len(next(iter(result.modes.values())))} frames x {len(modes)} "
          f"transfer modes in {result.seconds:.1f} s -> {written['json']}")
    return 0


def eval_speech(run_dir: Path, max_frames: int | None, device: str, data: Path | None, checkpoint: str, backend: str,
                flame_dir: Path | None, progress: bool, loudness: str = "own") -> int:
    """`geoavatar eval RUN --speech`: RUN/eval/speech/metrics.{json,md} (eval/speech.py; speech_dir for --loudness)."""
    from geoavatar.eval.speech import speech_dir, speech_table, write_speech_report
    from geoavatar.eval.speech_run import PICTURE_FRAMES, evaluate_speech
    from geoavatar.runtime import resolve_device
    from geoavatar.train.checkpoint import load_run
    from geoavatar.voice import VoiceModel

    if max_frames is not None and max_frames < 1:
        raise OptionError(f"--max-frames must be positive, got {max_frames}")
    try:
        torch_device = resolve_device(device)
    except ValueError as err:
        raise OptionError(str(err)) from err
    run = load_run(run_dir, device=torch_device, checkpoint=checkpoint, flame_dir=flame_dir)
    voice = VoiceModel.load(run.info.run_dir).hearing(loudness)
    result = evaluate_speech(run, voice, data, max_frames or PICTURE_FRAMES, backend, progress=progress)
    written = write_speech_report(result, speech_dir(run.info.run_dir, loudness, copy_name(run.info.data_root, data)))
    print(speech_table(result.scores), end="")
    print(f"{result.label}: {result.frames} held-out frames driven by their own sound in {result.seconds:.1f} s -> "
          f"{written['json']}")
    return 0


def evaluate_cross(run, driven, modes: Sequence[str], driver: str, max_frames: int | None = None,
                   scorer=None, data: Path | None = None, flame_dir: Path | None = None, progress: bool = True):
    """CrossResult of a DrivenAvatar (the animation layer's driver source): `max_frames` driver frames (spread evenly;
    all by default), its pictures rendered in each transfer mode of `modes`, scored against the driver's frames
    (eval/cross.py). `scorer`: a FaceScorer holding the avatar's identity reference (default: eval's, from the run's
    training frames; closed after)."""
    from geoavatar.data import evenly_spaced
    from geoavatar.eval.cross import CrossResult, score_cross
    from geoavatar.eval.evaluate import face_scorer, face_settings, run_label

    started = time.perf_counter()
    own_scorer = scorer is None
    scorer = face_scorer(run, data, flame_dir) if own_scorer else scorer
    try:
        scored = score_cross(driven.pictures(modes, max_frames), modes, scorer, progress, f"eval cross@{driver}")
    finally:
        if own_scorer:
            scorer.close()
    options = driven.options
    evaluated = len(evenly_spaced(len(driven.dataset), max_frames))
    settings = {
        "frames_in_driver": len(driven.dataset), "frames_evaluated": evaluated, "max_frames": max_frames, "driver_split": options.driver_split, "driver_neutral": options.driver_neutral,
        "avatar_neutral": options.avatar_neutral, "camera": options.camera, "backend": options.backend,
        "resolution": run.info.resolution, "faces": face_settings(scorer),
        "source": "the driver's frame composited on its background (what reenact shows beside the render)",
    }
    return CrossResult(run.info.run_dir, run_label(run)[0], driver, Path(driven.subject.root), scored, settings,
                       time.perf_counter() - started)


def report_dir(run_dir: Path, split: str, recorded: Path, data: Path | None) -> Path:
    """RUN/eval/SPLIT, or RUN/eval/SPLIT@NAME for a copy NAME of the dataset given while the recorded one exists."""
    from geoavatar.eval.report import eval_dir

    folder, copy = eval_dir(run_dir, split), copy_name(recorded, data)
    return folder if copy is None else folder.with_name(f"{split}@{copy}")


def copy_name(recorded: Path, data: Path | None) -> str | None:
    """The name a copy of a run's dataset (--data) gives its reports (prepare's OUT/dataset: OUT's); None for the
    run's own dataset (the folder it recorded, or the moved one)."""
    from geoavatar.animation.sources.driver_video import dataset_name
    from geoavatar.train.run_frames import is_own_dataset

    return None if data is None or is_own_dataset(recorded, data) else dataset_name(data)


__all__ = ["eval_cross", "eval_runs", "eval_speech", "evaluate_cross", "report_dir"]
