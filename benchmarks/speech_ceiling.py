"""How close can a voice come to the reference at all? `eval --speech`'s scores for a "voice" that outputs another
measurement of the same held-out frames: the tracker's expression and jaw (prepare's photometric fit, which saw the
frames' pixels), rendered as the voice is (the run's head pose), beside the baselines and the reference render (the
voice model's own row: `geoavatar eval RUN --speech`).

    .venv/bin/python benchmarks/speech_ceiling.py RUN [--max-frames 40] [--training-blocks 4] [--late 1,2]

If the tracker's own rows fall short of a goal on the picture scores (the mouth PSNR within 1.5 dB of the reference
render, #39), no prediction from the sound can be expected to meet it: the reference is the run's fit against the
avatar, and two measurements of a frame from its pixels already disagree by that much.

--late 1,2 also scores the reference's own rows shown 1 and 2 frames late (and averaged over 3 and 5 frames, as
a voice's smooth output is): what exactness in time the mouth-PSNR goal asks, against the lag the other goals allow
(±40 ms).

--training-blocks K also asks whether the ruler leans: it fits K blocks of 16 training frames as train fits the
held-out ones (train/held_out_fit.py: its steps, the carry, one thread) and compares their lips' opening with the
rows the voice learns from (the run's) and the tracker's, and their lips' mean and LVE with the run's rows. The voice
can only learn the convention of its targets.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


class GivenFace:
    """Stands in for a voice model in evaluate_speech: a given face for the held-out frames, in time order."""

    def __init__(self, voice, face):
        self.voice, self.face = voice, face

    def __getattr__(self, name):
        return getattr(self.voice, name)

    def predict_features(self, *args, **kwargs):
        from geoavatar.voice import SpokenFace

        width = self.voice.predict_features(*args, **kwargs).expr.shape[1]
        return SpokenFace(self.face.expr[:, :width], self.face.jaw)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--max-frames", type=int, default=40, help="held-out frames rendered (eval --speech's 40)")
    parser.add_argument("--training-blocks", type=int, default=0, help="blocks of 16 training frames to fit")
    parser.add_argument("--late", default="", help="frames late (comma-separated) to show the reference's own rows")
    args = parser.parse_args()

    from geoavatar.runtime import setup_process

    setup_process()
    from geoavatar.data.sound import read_dataset_sound
    from geoavatar.eval.speech_run import evaluate_speech
    from geoavatar.train.checkpoint import open_run, open_run_dataset
    from geoavatar.voice import SpokenFace
    from geoavatar.voice.model import VoiceModel

    run = open_run(args.run, "cpu")
    subject = open_run_dataset(run, "train").subject
    sound = read_dataset_sound(run.info.data_root)
    test = sorted(run.info.timesteps["test"], key=lambda t: sound.frame_times.get(t, t))  # evaluate_speech's order
    row = {t: i for i, t in enumerate(subject.timesteps)}
    tracker = SpokenFace.from_rows(subject.params["expr"], subject.params["jaw_pose"], [row[t] for t in test])
    voice = VoiceModel.load(run.info.run_dir)
    scores = evaluate_speech(run, GivenFace(voice, tracker), picture_frames=args.max_frames, progress=False).scores
    scores["tracker_rows"] = scores.pop("voice")
    for name, values in scores.items():
        shown = ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in values.items())
        print(f"{name:13s} {shown}")
    rows, reference = scores["tracker_rows"], scores["tracked"]
    print(f"the tracker's rows: LVE {rows['lip_vertex_error'] / scores['mean_face']['lip_vertex_error']:.3f}x the mean "
          f"face's, mouth PSNR {reference['mouth_psnr'] - rows['mouth_psnr']:.2f} dB under the reference render")
    print(json.dumps({k: {kk: (None if vv is None else float(vv)) for kk, vv in v.items()} for k, v in scores.items()}))
    if args.late:
        reference_late(run, voice, test, [int(k) for k in args.late.split(",")], args.max_frames)
    if args.training_blocks:
        training_fit_openings(run, subject, args.training_blocks)


def reference_late(run, voice, test: list[int], lates: list[int], picture_frames: int) -> None:
    """eval --speech's scores of the reference's own rows of the held-out frames `test` (in time order) shown
    `lates` frames late, and averaged over 3 and 5 frames (centred): how far from the reference render a face that
    errs only in time falls."""
    import numpy as np

    from geoavatar.eval.speech_run import evaluate_speech
    from geoavatar.train.run_frames import RunFrames
    from geoavatar.voice import SpokenFace

    frames = RunFrames(run)
    reference = SpokenFace.from_rows(frames.values.expr, frames.values.jaw_pose, [frames.row(t) for t in test])
    count = len(reference.jaw)

    def late(frames: int) -> SpokenFace:
        return reference.take(list(np.clip(np.arange(count) - frames, 0, count - 1)))

    def averaged(frames: int) -> SpokenFace:
        window = [np.clip(np.arange(count) + k, 0, count - 1) for k in range(-(frames // 2), frames // 2 + 1)]
        return SpokenFace(*(np.mean([values[w] for w in window], 0).astype(np.float32)
                            for values in (reference.expr, reference.jaw)))

    faces = {f"{k} frame(s) late": late(k) for k in lates} | {f"averaged over {n}": averaged(n) for n in (3, 5)}
    for label, face in faces.items():
        scores = evaluate_speech(run, GivenFace(voice, face), picture_frames=picture_frames, progress=False).scores
        given, mean_face, tracked = scores["voice"], scores["mean_face"], scores["tracked"]
        print(f"the reference's rows {label}: LVE {given['lip_vertex_error'] / mean_face['lip_vertex_error']:.3f}x "
              f"the mean face's, mouth PSNR {given['mouth_psnr']:.2f} "
              f"({tracked['mouth_psnr'] - given['mouth_psnr']:.2f} dB under the reference render), "
              f"PSNR {given['psnr']:.2f}")


def training_fit_openings(run, subject, blocks: int) -> None:
    """Fit `blocks` spread-out blocks of training frames as the held-out fit does; print the lips' opening (mm) of
    that fit, of the run's rows (the voice's targets) and of the tracker's."""
    import time

    import numpy as np
    import torch

    from geoavatar.eval.speech import lip_vertex_error
    from geoavatar.train.avatar_tracking import AvatarTrackingConfig, dataset_frames, track_frames
    from geoavatar.train.checkpoint import open_run_dataset
    from geoavatar.train.held_out_fit import HeldOutFitConfig
    from geoavatar.train.run_frames import RunFrames
    from geoavatar.voice.face import FaceProbe

    block = 16  # frames a block: the held-out fit's blocks when this was measured (BENCHMARKS.md, Speech)
    train = open_run_dataset(run, "train")
    count = len(train.timesteps)
    starts = [int((count - block) * (k + 0.5) / blocks) for k in range(blocks)]
    held_out = HeldOutFitConfig()
    config = AvatarTrackingConfig(steps=held_out.steps, carry=held_out.carry)
    started = time.perf_counter()
    torch.set_num_threads(1)  # as the fit's workers
    fitted = [track_frames(run.avatar, run.head, run.deformer,
                           dataset_frames(train, range(s, s + block), run.device), config).params for s in starts]
    timesteps = [int(train.timesteps[s + i]) for s in starts for i in range(block)]
    frames = RunFrames(run)
    probe = FaceProbe(run.head, frames.identity())
    width = int(run.head.num_expr)
    row = {t: i for i, t in enumerate(subject.timesteps)}

    def opening(expr, jaw) -> np.ndarray:
        with torch.no_grad():
            return probe.opening(expr[:, :width].float(), jaw.float()).numpy() * 1000.0

    def lips(expr, jaw) -> torch.Tensor:
        with torch.no_grad():
            return probe.lips(expr[:, :width].float(), jaw.float()).double()  # [N, K, 3]

    fit = opening(torch.cat([p.expr for p in fitted]), torch.cat([p.jaw_pose for p in fitted]))
    rows = [frames.row(t) for t in timesteps]
    learned = opening(frames.values.expr[rows], frames.values.jaw_pose[rows])
    tracker_rows = [row[t] for t in timesteps]
    tracker = opening(subject.params["expr"][tracker_rows], subject.params["jaw_pose"][tracker_rows])
    print(f"{len(timesteps)} training frames fitted as the held-out ones in {time.perf_counter() - started:.0f} s; "
          f"lips' opening mean: fit {fit.mean():.2f} mm, the run's rows {learned.mean():.2f}, the tracker's "
          f"{tracker.mean():.2f}; fit - run's {np.mean(fit - learned):+.2f} mm (std {np.std(fit - learned):.2f}, "
          f"r {np.corrcoef(fit, learned)[0, 1]:.3f})")
    fit_lips = lips(torch.cat([p.expr for p in fitted]), torch.cat([p.jaw_pose for p in fitted]))
    run_lips = lips(frames.values.expr[rows], frames.values.jaw_pose[rows])
    offset = float(((fit_lips.mean(0) - run_lips.mean(0)) ** 2).sum(-1).max().sqrt()) * 1000.0
    apart = lip_vertex_error(fit_lips, run_lips)
    print(f"the fit's lips against the run's rows: means {offset:.2f} mm apart (at the vertex that moves most), LVE "
          f"between them {apart:.2e} m2")
    test = [int(t) for t in run.info.held_out_scored or run.info.timesteps["test"]]  # not the rows filled between
    fitted_rows, tracker_rows = [frames.row(t) for t in test], [row[t] for t in test]
    reference = opening(frames.values.expr[fitted_rows], frames.values.jaw_pose[fitted_rows])
    tracked = opening(subject.params["expr"][tracker_rows], subject.params["jaw_pose"][tracker_rows])
    print(f"the {len(test)} held-out frames: the run's fit {reference.mean():.2f} mm, the tracker's {tracked.mean():.2f}; "
          f"fit - tracker's {np.mean(reference - tracked):+.2f} mm (r {np.corrcoef(reference, tracked)[0, 1]:.3f})")


if __name__ == "__main__":
    main()
