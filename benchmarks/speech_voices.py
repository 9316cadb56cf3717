"""Does another voice still move the mouth? The run's voice model on other sounds, against its own held-out sound.

For each sound, the lips' opening over the frames the voice model makes (voice/face.FaceProbe: the mean gap of the
inner lip rings' middle points, millimetres): its mean and standard deviation, and the standard deviation relative to
the one on the held-out segment's own sound (1.0: the mouth moves as much as on the person's own voice). Sounds:
    own        the held-out segment's sound (never heard in training)
    own -20 dB the same, 20 dB quieter (a quieter microphone)
    others     any files given (another speaker's video, a speech synthesiser's wav, ...)
    --text     texts spoken by the offline synthesisers installed (espeak-ng: --tts-voice; flite)
The tracked held-out frames' opening is printed beside (what the person's mouth did).

    .venv/bin/python benchmarks/speech_voices.py RUN [--sounds german.mp4 ...] [--text "..." --tts-voice fr]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def opening_mm(probe, face) -> np.ndarray:
    import torch

    with torch.no_grad():
        return 1000.0 * probe.opening(torch.as_tensor(face.expr), torch.as_tensor(face.jaw)).numpy()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--sounds", type=Path, nargs="*", default=[])
    parser.add_argument("--text", default=None, help="a text for the speech synthesisers")
    parser.add_argument("--tts-voice", default=None, help="espeak-ng's voice for --text (fr, de, en-us, ...)")
    parser.add_argument("--fps", type=float, default=25.0)
    args = parser.parse_args()

    from geoavatar.runtime import setup_process

    setup_process()
    import shutil

    from geoavatar.data.sound import read_dataset_sound
    from geoavatar.sound import RATE, Sound, read_sound
    from geoavatar.sound.synthesis import speak_text
    from geoavatar.train.checkpoint import open_run
    from geoavatar.train.run_frames import RunFrames
    from geoavatar.voice import SpokenFace, VoiceModel
    from geoavatar.voice.face import FaceProbe

    run = open_run(args.run, "cpu")
    voice = VoiceModel.load(args.run)
    frames = RunFrames(run)
    probe = FaceProbe(run.head, frames.identity())
    dataset = read_dataset_sound(run.info.data_root)
    test = sorted(run.info.timesteps["test"])
    held = dataset.sound.segment(dataset.frame_times[test[0]], dataset.sound.seconds)
    sounds: dict[str, Sound] = {"own (held-out)": held,
                                "own -20 dB": Sound(held.samples * 0.1, held.rate, held.start)}
    for path in args.sounds:
        sounds[path.name] = read_sound(path, RATE)
    if args.text:
        for engine in ("espeak-ng", "flite"):
            if shutil.which(engine):
                voice_name = args.tts_voice if engine == "espeak-ng" else None
                sounds[f"{engine} {voice_name or ''}".strip()] = speak_text(args.text, engine, voice_name)
    rows = {}
    rows_t = [frames.row(t) for t in test]
    tracked = opening_mm(probe, SpokenFace.from_rows(frames.values.expr, frames.values.jaw_pose, rows_t))
    for name, sound in sounds.items():
        times = np.arange(int(sound.seconds * args.fps)) / args.fps
        opening = opening_mm(probe, voice.predict(sound, times))
        rows[name] = {"seconds": round(sound.seconds, 1), "mean_mm": round(float(opening.mean()), 2),
                      "std_mm": round(float(opening.std()), 2)}
    own = rows["own (held-out)"]["std_mm"]
    print(f"tracked held-out opening: mean {tracked.mean():.2f} mm, std {tracked.std():.2f} mm")
    print("| sound | seconds | opening mean (mm) | opening std (mm) | std / own voice's |")
    print("|---|---|---|---|---|")
    for name, row in rows.items():
        print(f"| {name} | {row['seconds']} | {row['mean_mm']:.2f} | {row['std_mm']:.2f} | "
              f"{row['std_mm'] / own:.2f} |")
    print(json.dumps({"tracked": {"mean_mm": float(tracked.mean()), "std_mm": float(tracked.std())}, **rows}))


if __name__ == "__main__":
    main()
