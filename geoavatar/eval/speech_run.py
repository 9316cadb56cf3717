"""`geoavatar eval RUN --speech`: the held-out segment driven by its own sound, scored (eval/speech.py says how).

    result = evaluate_speech(run, voice, data=None)       # SpeechResult
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from geoavatar.avatar import render_avatar
from geoavatar.data.dataset import item_camera, item_to
from geoavatar.data.errors import DatasetError
from geoavatar.data.sound import read_dataset_sound
from geoavatar.eval import metrics
from geoavatar.eval.evaluate import (EvalConfig, RenderedFrame, image_metrics, measure_mouth, mouth_face_mask, run_label,
                                     spread_scored, test_params_source, unscored_timesteps)
from geoavatar.eval.speech import (SpeechInputs, SpeechResult, baseline_faces, face_scores, normalised_mel)
from geoavatar.head.params import HeadParams
from geoavatar.render import composite_target
from geoavatar.sound import FRAME_RATE
from geoavatar.sound.features import power_frames
from geoavatar.train.checkpoint import LoadedRun, RunError, open_run_dataset
from geoavatar.train.run_frames import RunFrames
from geoavatar.voice.face import FaceProbe
from geoavatar.voice.inputs import SpeechStats, log_mel_torch, normalise, speech_level, speech_stats
from geoavatar.voice.model import SpokenFace, VoiceModel
from geoavatar.voice.train import voice_data

NORMALISATION = {"own": "the held-out sound by its own speech statistics (as speak normalises a new recording)",
                 "video": "the held-out sound by the training sound's speech statistics, the mean face following its "
                          "speech level (speak --loudness video)",
                 "video, no level slope": "the held-out sound by the training sound's speech statistics (speak "
                                          "--loudness video; this voice has no level slope: learned before it)"}


def _segment_inputs(run: LoadedRun, frames: RunFrames, sound, test: list[int], expr_dims: int,
                    stats: SpeechStats | None = None) -> tuple[SpeechInputs, SpokenFace, float]:
    """The baselines' inputs, the tracked faces of the held-out frames, and their frame rate; the held-out sound
    normalised by `stats` (None: its own speech statistics)."""
    data = voice_data(run, frames, sound, expr_dims)
    times = sound.times(test)  # [N'] seconds
    cut = float(data.power.shape[0] - 1) / FRAME_RATE  # where the training sound ends
    start = min(float(times[0]) - 0.5 / max(data.fps, 1.0), cut)
    held_out = log_mel_torch(torch.from_numpy(power_frames(sound.sound.segment(start, sound.sound.seconds))))
    level = speech_level(speech_stats(held_out)) - speech_level(speech_stats(log_mel_torch(data.power)))
    train_mel = normalised_mel(sound.sound.segment(0.0, cut))
    inputs = SpeechInputs(data.targets.numpy(), train_mel, data.centres.numpy(),
                          normalise(held_out, stats or speech_stats(held_out)),
                          np.round((times - start) * FRAME_RATE).astype(np.int64), expr_dims, data.expr_width, level)
    rows = [frames.row(t) for t in test]
    tracked = SpokenFace.from_rows(frames.values.expr, frames.values.jaw_pose, rows)
    return inputs, tracked, data.fps


def spoken_params(tracked: HeadParams, face: SpokenFace, row: int) -> HeadParams:
    """A frame's tracked parameters (per-frame keys [1, ...]) with row `row` of a face's expression and jaw."""
    device = tracked.expr.device
    expr = torch.as_tensor(face.expr[row:row + 1], dtype=torch.float32, device=device)[:, :tracked.expr.shape[1]]
    return tracked.replace(expr=expr, jaw_pose=torch.as_tensor(face.jaw[row:row + 1], dtype=torch.float32,
                                                               device=device))


def _copy_faces(dataset, test: list[int], like: SpokenFace) -> SpokenFace:
    """The held-out frames' expression and jaw as a dataset copy's test split holds them (shaped as `like`)."""
    rows = {frame.timestep: frame.row for frame in dataset.frames}
    expr, jaw = np.zeros_like(like.expr), np.zeros_like(like.jaw)  # [N, E], [N, 3]
    for i, timestep in enumerate(test):
        params = dataset.subject.frame_params(rows[timestep])
        values = np.asarray(params["expr"], np.float32).reshape(-1)[:expr.shape[1]]
        expr[i, :len(values)] = values
        jaw[i] = np.asarray(params["jaw_pose"], np.float32).reshape(-1)[:3]
    return SpokenFace(expr, jaw)


def _test_items(run: LoadedRun, data: Path | None, split: str = "test"):
    dataset = open_run_dataset(run, split, data)
    return dataset, {int(dataset[i]["timestep"]): i for i in range(len(dataset))}


@torch.no_grad()
def picture_scores(run: LoadedRun, dataset, index_of: dict[int, int], timesteps: list[int],
                   faces: dict[str, SpokenFace], config: EvalConfig, progress: bool = True) -> dict[str, dict]:
    """PSNR, LPIPS, mouth PSNR of the held-out frames rendered with the tracked parameters ("tracked") and with each
    face's expression and jaw (the tracked head pose and gaze, T = 0); the mouth region is the tracked mesh's, the
    same pixels for every face."""
    from tqdm.auto import tqdm

    mouth_faces = mouth_face_mask(run.head)
    totals = {name: {"psnr": [], "lpips": [], "mouth_psnr": []} for name in ("tracked", *faces)}
    device = run.device
    frames = RunFrames(run)  # the run's held-out fit on its own dataset, a copy's parameters otherwise
    own = frames.is_own_dataset(dataset.subject.root)
    for row, timestep in enumerate(tqdm(timesteps, disable=not progress, desc="eval speech: render", leave=False)):
        item = item_to(dataset[index_of[timestep]], device)
        tracked = frames.params(timestep, HeadParams.from_npz(item["params"]), own_dataset=own)[0].to(device)
        target = composite_target(item["image"], item["mask"], item["background"])
        target_taps = metrics.LpipsTarget(target, config.lpips_net, config.lpips_unit_inputs)  # for all five renders
        camera = item_camera(item)
        tracked_vertices = None  # the tracked render comes first: its mesh gives every face's mouth pixels
        for name, face in {"tracked": None, **faces}.items():
            params = tracked if face is None else spoken_params(tracked, face, row)
            frame = render_avatar(run.avatar, run.head, params, camera, None, run.deformer, item["background"],
                                  config.backend)
            if face is None:
                tracked_vertices = frame.vertices
            rendered = RenderedFrame(row, item, frame.result.rgb.clamp(0, 1), target, tracked_vertices,
                                     frame.result.alpha, params, None)
            record = image_metrics(rendered, config, target_taps)
            measure_mouth(record, rendered, run.head, mouth_faces, config, lpips=False)  # its PSNR is what is kept
            for key in ("psnr", "lpips", "mouth_psnr"):
                value = getattr(record, key)
                if value is not None and np.isfinite(value):
                    totals[name][key].append(float(value))
    return {name: {k: (float(np.mean(v)) if v else None) for k, v in values.items()} for name, values in totals.items()}


PICTURE_FRAMES = 40  # held-out frames rendered for the picture scores (5 renders each: the voice, tracked, baselines)


def evaluate_speech(run: LoadedRun, voice: VoiceModel, data: Path | None = None,
                    picture_frames: int | None = PICTURE_FRAMES, backend: str = "auto", render: bool = True,
                    progress: bool = True) -> SpeechResult:
    """The voice model and the baselines on the run's held-out frames (module docstring of eval/speech.py): the face
    scores over every held-out frame, the picture scores over `picture_frames` of them spread evenly (None: all)."""
    started = time.perf_counter()
    root = Path(data) if data is not None else run.info.data_root
    sound = read_dataset_sound(root)
    if sound is None:
        raise RunError(f"{root}: the dataset has no sound track (audio.json); --speech scores a run whose video "
                       "had speech")
    frames = RunFrames(run)
    test = sorted(run.info.timesteps.get("test", []), key=lambda t: sound.frame_times.get(t, t))
    if len(test) < 3:
        raise RunError(f"{run.info.run_dir}: {len(test)} held-out frames; --speech needs at least 3")
    times = sound.times(test)  # [N'] seconds
    silent = int(np.sum(times >= sound.sound.seconds))  # the last frames of a track a little short: heard as a
    if silent > 0.05 * len(test):  # clip's end is (the windows padded); beyond that, the scores would be silence
        raise RunError(f"{root}: {silent} of the {len(test)} held-out frames lie after the end of its sound track; "
                       "--speech scores frames with their sound")
    trained = [t for t in run.info.timesteps.get("train", []) if t in sound.frame_times]
    if trained and times.min() < sound.times(trained).max():  # the voice heard all sound before its last
        raise RunError(f"{run.info.run_dir}: its held-out frames lie among its training frames (a dataset's own "
                       "split files), so the voice heard their sound; --speech scores held-out frames after them")
    copy = data is not None and not frames.is_own_dataset(root)  # the run's own folder given again is no copy
    dataset, index_of = _test_items(run, data) if render or copy else (None, {})
    try:
        inputs, tracked, fps = _segment_inputs(run, frames, sound, test, voice.expr_dims, voice.fixed_stats)
        if copy:  # a copy's parameters (track --avatar's) are the reference, as for plain eval --data
            tracked = _copy_faces(dataset, test, tracked)
    except DatasetError as err:
        raise RunError(f"{root}: {err}") from err
    faces = {"voice": voice.predict_features(inputs.test_mel, torch.from_numpy(inputs.test_centres),
                                             voice.level_shift(inputs.test_level))}
    faces.update(baseline_faces(inputs, voice.past, voice.ahead))
    probe = FaceProbe(run.head, {k: v.cpu() for k, v in frames.identity().items()})
    # the face scores over the whole segment (a sample of short runs scored french.mp4's r 0.09 lower with the same
    # reference: BENCHMARKS.md, Speech); the pictures on frames the held-out fit scores
    scores = {name: face_scores(probe, face, tracked, fps) for name, face in faces.items()}
    scores["tracked"] = {}
    unscored = unscored_timesteps(run, root)  # a long video's held-out frames outside the fit's scored runs
    rows = spread_scored(list(test), unscored, picture_frames)
    if render:
        config = EvalConfig(split="test", backend=backend)
        pictures = picture_scores(run, dataset, index_of, [test[r] for r in rows],
                                  {name: face.take(rows) for name, face in faces.items()}, config, progress)
        for name, values in pictures.items():
            scores[name].update(values)
    settings = {"voice": {k: voice.config.to_dict()[k] for k in ("past", "ahead", "members")},
                "held_out_frames": len(test), "picture_frames": len(rows) if render else 0,
                "normalisation": NORMALISATION[voice.loudness if voice.follows_level or voice.loudness == "own"
                                               else "video, no level slope"],
                "level_db": round(10.0 * inputs.test_level, 2), "render": render,
                "head_pose": "tracked (rotation, neck, translation, eyes); T = 0", "metrics": metrics.__name__,
                "test_params": test_params_source(run, root),
                "face_scores_reference": ("every held-out frame's row: fitted in the held-out fit's runs, between "
                                          "them the tracker's plus their fitted neighbours' correction"
                                          if unscored else "every held-out frame's row")}
    return SpeechResult(run.info.run_dir, run_label(run)[0], len(test), fps, scores, settings,
                        time.perf_counter() - started)


__all__ = ["evaluate_speech", "picture_scores", "spoken_params"]
