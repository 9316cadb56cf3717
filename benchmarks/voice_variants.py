"""Voice-model settings against the seed: each setting learned with several seeds on one run, scored on its held-out
frames (face scores only: LVE, lip-opening r, lag), and the seeds' models averaged (a larger ensemble).

One voice model's held-out r moves by up to 0.09 with its seed on french.mp4 (BENCHMARKS.md, Speech), more than most
settings do, so a setting is judged by its seeds together, never by one model.

    .venv/bin/python benchmarks/voice_variants.py RUN --set '{}' '{"past": 0.15}' [--seeds 0,1,2]
        [--reference fit|tracker] [--targets run|tracker] [--shares 0.25,0.5,0.75,1]

--set       VoiceConfig overrides as JSON, one setting each
--reference the held-out frames' parameters the faces are scored against: the run's (train's fit against the
            avatar, what `eval --speech` uses) or the tracker's rows in the dataset
--targets   what the voice learns: the run's training rows (refined by train, the default) or the tracker's rows
--smooth    also score each model with its output smoothed over time by these symmetric kernels ("1,2,1")
--shares    learn from the first share of the training frames only (in time; their sound cut after them, the
            validation blocks taken within that share): how the held-out scores grow with the speech heard
It also prints the tracker's held-out rows scored against the run's: how far the two references disagree.
"""

from __future__ import annotations

import argparse
import copy
import json
import time
from pathlib import Path

import numpy as np


def subject_rows(subject, timesteps) -> list[int]:
    """The dataset's parameter rows of `timesteps` (its rows need not be the run's)."""
    row = {t: i for i, t in enumerate(subject.timesteps)}
    return [row[t] for t in timesteps]


def tracker_frames(frames, subject):
    """The run's frames with every per-frame row replaced by the tracker's (the dataset's) row."""
    from geoavatar.head.params import HeadParams

    order = subject_rows(subject, frames.timesteps)
    values = frames.values.to_npz()
    rows = {k: (subject.params[k][order].to(v.dtype) if k in subject.params and v.dim() > 1 and k != "static_offset"
                else v) for k, v in values.items()}
    out = copy.copy(frames)
    out.values = HeadParams.from_npz(rows)
    return out


def first_share(run, share: float, sound):
    """The run as the voice trainer sees it, its training frames cut to the first `share` of them in time."""
    train = sorted(run.info.timesteps["train"], key=lambda t: sound.frame_times.get(t, t))
    info = copy.copy(run.info)
    info.timesteps = {**run.info.timesteps, "train": train[:max(1, int(round(share * len(train))))]}
    return run._replace(info=info)  # a LoadedRun


class Smoothed:
    """A voice model whose faces are smoothed over frames by a symmetric kernel (needs that much more look-ahead)."""

    def __init__(self, model, kernel):
        self.model, self.kernel = model, np.asarray(kernel, float) / np.sum(kernel)

    def __getattr__(self, name):
        return getattr(self.model, name)

    def predict_features(self, *args, **kwargs):
        from scipy.ndimage import convolve1d

        from geoavatar.voice import SpokenFace

        face = self.model.predict_features(*args, **kwargs)
        return SpokenFace(convolve1d(face.expr, self.kernel, axis=0, mode="nearest"),
                          convolve1d(face.jaw, self.kernel, axis=0, mode="nearest"))


class SeedAverage:
    """Several voice models' faces averaged (stands in for one model in evaluate_speech)."""

    def __init__(self, models):
        self.models = models

    def __getattr__(self, name):
        return getattr(self.models[0], name)

    def predict_features(self, *args, **kwargs):
        from geoavatar.voice import SpokenFace

        faces = [m.predict_features(*args, **kwargs) for m in self.models]
        return SpokenFace(np.mean([f.expr for f in faces], 0), np.mean([f.jaw for f in faces], 0))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--set", nargs="+", default=["{}"], help="VoiceConfig overrides as JSON, one setting each")
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--reference", choices=("fit", "tracker"), default="fit")
    parser.add_argument("--targets", choices=("run", "tracker"), default="run")
    parser.add_argument("--smooth", nargs="*", default=[], help="kernels such as 1,2,1")
    parser.add_argument("--shares", default="1", help="shares of the training frames learned from, such as 0.5,1")
    args = parser.parse_args()

    from geoavatar.runtime import setup_process

    setup_process()
    from geoavatar.data.sound import read_dataset_sound
    from geoavatar.eval.speech import face_scores
    from geoavatar.eval.speech_run import evaluate_speech
    from geoavatar.runtime import num_threads
    from geoavatar.train.checkpoint import open_run, open_run_dataset
    from geoavatar.train.run_frames import RunFrames
    from geoavatar.voice import SpokenFace
    from geoavatar.voice.config import VoiceConfig
    from geoavatar.voice.face import FaceProbe
    from geoavatar.voice.train import _fit  # the trainer's core, given the frames to learn from

    run = open_run(args.run, "cpu")
    frames = RunFrames(run)
    subject = open_run_dataset(run, "train").subject
    sound = read_dataset_sound(run.info.data_root)
    data = run.info.data_root if args.reference == "tracker" else None  # eval --speech --data: the dataset's rows

    test = sorted(run.info.timesteps["test"], key=lambda t: sound.frame_times.get(t, t))
    rows, own = [frames.row(t) for t in test], subject_rows(subject, test)
    fitted = SpokenFace.from_rows(frames.values.expr, frames.values.jaw_pose, rows)
    tracked = SpokenFace.from_rows(subject.params["expr"], subject.params["jaw_pose"], own)
    fps = 1.0 / float(np.median(np.diff(sound.times(test))))  # the lag is in frames of the video's own rate
    spread = face_scores(FaceProbe(run.head, frames.identity()), tracked, fitted, fps)
    print(f"the tracker's held-out rows against the run's: LVE {spread['lip_vertex_error']:.3e} m2, "
          f"r {spread['mouth_open_correlation']:.3f}")

    learn_from = tracker_frames(frames, subject) if args.targets == "tracker" else frames

    def show(label: str, voice) -> dict:
        scores = evaluate_speech(run, voice, data=data, render=False, progress=False).scores
        mine, mean, linear = (scores[k]["lip_vertex_error"] for k in ("voice", "mean_face", "linear"))
        row = {"r": scores["voice"]["mouth_open_correlation"], "lve": mine, "lve_vs_mean_face": mine / mean,
               "lve_vs_linear": mine / linear, "lag_ms": scores["voice"]["lag_ms"]}
        print(f"{label:60s} r {row['r']:.3f}  LVE {mine:.3e} m2 ({row['lve_vs_mean_face']:.3f}x mean face, "
              f"{row['lve_vs_linear']:.3f}x linear)  lag {row['lag_ms']:+.0f} ms", flush=True)
        return row

    results = {}
    for setting, share in ((s, float(f)) for s in args.set for f in args.shares.split(",")):
        overrides = json.loads(setting)
        if share != 1.0:
            setting = f"{setting} first {share:g}"
        models = []
        for seed in (int(s) for s in args.seeds.split(",")):
            config = VoiceConfig(**{**overrides, "seed": seed})
            started = time.perf_counter()
            with num_threads(config.threads):
                voice = _fit(first_share(run, share, sound), learn_from, sound, config, started, lambda _: None)
            models.append(voice)
            label = (f"{setting} seed {seed} ({voice.info['speech_seconds']:.1f} s of speech, gain "
                     f"{voice.info['gain']:.2f}, {time.perf_counter() - started:.0f} s)")
            results[f"{setting} seed {seed}"] = {**show(label, voice), "speech_seconds": voice.info["speech_seconds"]}
            for kernel in args.smooth:
                weights = [float(w) for w in kernel.split(",")]
                results[f"{setting} seed {seed} smoothed {kernel}"] = show(f"  smoothed by {kernel}",
                                                                           Smoothed(voice, weights))
        results[f"{setting} seeds averaged"] = show(f"{setting} the seeds' models averaged", SeedAverage(models))
    print(json.dumps(results))


if __name__ == "__main__":
    main()
