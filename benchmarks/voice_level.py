"""Where the voice's held-out lip error lies: the segment's mean mouth, and the loudness that per-clip normalisation
takes away.

    .venv/bin/python benchmarks/voice_level.py RUN [--seeds 0,1,2]

`eval --speech` normalises the held-out sound by its own speech statistics, as `geoavatar speak` normalises a new
recording (so that another voice or a quieter microphone still moves the mouth). For each seed's voice model (the
run's own for its seed, others learned here as `geoavatar voice` learns them) and for the linear baseline, this
prints the held-out LVE (× the mean face's) and the lips' opening r three ways:

    own        the held-out sound by its own statistics (eval --speech, speak)
    video      by the training sound's statistics, the mean face following the sound's speech level (`speak
               --loudness video`, `eval --speech --loudness video`)
    video-flat the same without the level's shift (the product before the level slope)
    centred    own, with the predicted lips moved by their mean error over the segment (an oracle: what is left when
               the segment's mean mouth is given)

and the level of the held-out speech against the training speech (dB, the bands' mean). Then where the error lies:
each model's per-frame lip error (own) in the thirds of the held-out frames by their tracked opening, and in their
speech and silence (Silero VAD), beside the mean face's; and the lips' opening of the training and held-out frames.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--stats-seconds", default=None,
                        help="LO,HI: learn with each step's statistics from a stretch of LO-HI s (voice/train.py)")
    args = parser.parse_args()

    from geoavatar.runtime import num_threads, setup_process

    setup_process()
    from geoavatar.data.sound import read_dataset_sound
    from geoavatar.eval.speech import baseline_faces, lip_vertex_error, pearson
    from geoavatar.eval.speech_run import _segment_inputs
    from geoavatar.train.checkpoint import open_run
    from geoavatar.train.run_frames import RunFrames
    from geoavatar.voice import SpokenFace, VoiceConfig, VoiceModel
    from geoavatar.voice.face import FaceProbe
    from geoavatar.voice.inputs import log_mel_torch, speech_stats
    from geoavatar.voice.train import _fit, voice_data

    if args.stats_seconds:
        import geoavatar.voice.train as voice_train

        voice_train.STATS_SECONDS = tuple(float(s) for s in args.stats_seconds.split(","))
    run = open_run(args.run, "cpu")
    frames = RunFrames(run)
    sound = read_dataset_sound(run.info.data_root)
    test = sorted(run.info.timesteps["test"], key=lambda t: sound.frame_times.get(t, t))
    dims = int(run.head.num_expr)
    own_inputs, tracked, fps = _segment_inputs(run, frames, sound, test, dims)
    probe = FaceProbe(run.head, {k: v.cpu() for k, v in frames.identity().items()})
    as_tensor = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731

    def lips(face) -> torch.Tensor:
        with torch.no_grad():
            return probe.lips(as_tensor(face.expr), as_tensor(face.jaw)).double()  # [N, K, 3]

    def opening(face) -> np.ndarray:
        with torch.no_grad():
            return probe.opening(as_tensor(face.expr), as_tensor(face.jaw)).numpy()

    reference = lips(tracked)
    lve = lambda predicted: lip_vertex_error(predicted, reference)  # noqa: E731
    mean_face_lips = lips(baseline_faces(own_inputs, 1, 1)["mean_face"])
    mean_face = lve(mean_face_lips)

    # the held-out sound normalised by the training sound's statistics (what the voice model keeps: speak --loudness
    # video), for the voice and the baselines alike
    data = voice_data(run, frames, sound, dims)
    video_inputs, _, _ = _segment_inputs(run, frames, sound, test, dims, speech_stats(log_mel_torch(data.power)))
    level_db = 10.0 * own_inputs.test_level
    print(f"{args.run}: held-out speech {level_db:+.1f} dB against the training speech; mean face LVE "
          f"{mean_face:.3e} m2", flush=True)

    def per_frame(predicted: torch.Tensor) -> np.ndarray:
        return ((predicted - reference) ** 2).sum(-1).max(-1).values.numpy()  # [N] m^2: the LVE's terms

    tracked_open = 1000.0 * opening(tracked)  # [N] mm
    thirds = np.digitize(tracked_open, np.quantile(tracked_open, [1 / 3, 2 / 3]))  # [N] 0 closed .. 2 open
    speaking = sound.activity.mask(sound.times(test))  # [N] bool
    mean_face_frames = per_frame(mean_face_lips)
    training_open = 1000.0 * opening(SpokenFace(data.targets[:, :dims].numpy(), data.targets[:, dims:].numpy()))
    training_speaking = sound.activity.mask(sound.times(sorted(run.info.timesteps["train"],
                                                                key=lambda t: sound.frame_times.get(t, t))))
    mean_mm = lambda values, where: f"{values[where].mean():.2f}" if where.any() else "-"  # noqa: E731
    print(f"lips' opening (mm), mean in speech / silence: training frames {mean_mm(training_open, training_speaking)}"
          f" / {mean_mm(training_open, ~training_speaking)} ({(~training_speaking).mean():.0%} silence), held-out "
          f"{mean_mm(tracked_open, speaking)} / {mean_mm(tracked_open, ~speaking)} ({(~speaking).mean():.0%})")

    def breakdown(label: str, face) -> dict:
        """The per-frame lip error of `face` (own) by thirds of the tracked opening and by speech / silence."""
        errors, predicted_open = per_frame(lips(face)), 1000.0 * opening(face)
        parts = {name: m for name, m in ({f"third {k}": thirds == k for k in range(3)}
                                          | {"speech": speaking, "silence": ~speaking}).items() if m.any()}
        out = {name: {"tracked_mm": float(tracked_open[m].mean()), "predicted_mm": float(predicted_open[m].mean()),
                      "lve_x": float(errors[m].mean() / mean_face_frames[m].mean()),
                      "share": float(errors[m].sum() / errors.sum())} for name, m in parts.items()}
        print(f"  {label} (thirds by tracked opening: closed, middle, open): " + "; ".join(
            f"{name} {v['tracked_mm']:.2f} -> {v['predicted_mm']:.2f} mm, {v['lve_x']:.2f}x, {v['share']:.0%}"
            for name, v in out.items()), flush=True)
        return out

    def row(label: str, faces: dict) -> dict:
        out = {}
        for way, face in faces.items():
            predicted = lips(face)
            centred = predicted - (predicted - reference).mean(0)
            out[way] = {"lve_x": lve(predicted) / mean_face, "r": pearson(opening(face), opening(tracked))}
            if way == "own":
                out["centred"] = {"lve_x": lve(centred) / mean_face, "r": out[way]["r"]}
        print(f"{label:24s} " + "  ".join(f"{way} {v['lve_x']:.3f}x r {v['r']:.3f}" for way, v in out.items()),
              flush=True)
        return out | {"where": breakdown(label.split(" (")[0], faces["own"])}

    results = {"level_db": level_db,
               "linear": row("linear", {"own": baseline_faces(own_inputs, 1, 1)["linear"],
                                        "video": baseline_faces(video_inputs, 1, 1)["linear"]})}
    saved = VoiceModel.load(run.info.run_dir) if VoiceModel.exists(run.info.run_dir) else None
    for seed in (int(s) for s in args.seeds.split(",")):
        started = time.perf_counter()
        if saved is not None and saved.config.seed == seed and saved.level_slope is not None and not args.stats_seconds:
            voice = saved
        else:
            config = VoiceConfig(**{**saved.config.to_dict(), "seed": seed}) if saved else VoiceConfig(seed=seed)
            with num_threads(config.threads):
                voice = _fit(run, frames, sound, config, started, lambda _: None)
        centres = torch.from_numpy(own_inputs.test_centres)
        video = voice.hearing("video")
        faces = {"own": voice.predict_features(own_inputs.test_mel, centres),
                 "video": video.predict_features(video_inputs.test_mel, centres,
                                                 video.level_shift(video_inputs.test_level)),
                 "video-flat": voice.predict_features(video_inputs.test_mel, centres)}
        results[f"voice seed {seed}"] = row(f"voice seed {seed} ({time.perf_counter() - started:.0f} s)", faces)
    print(json.dumps(results))


if __name__ == "__main__":
    main()
