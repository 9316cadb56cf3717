"""A run's voice model scored on its held-out frames with its output gain set by hand: how far the LVE could move
with the gain alone (a measurement, not a setting: the held-out segment must not choose the gain).

    .venv/bin/python benchmarks/voice_gain.py RUN [--gains 1 1.4 1.6 1.8 2]

Face scores only (LVE against the mean face's, lip-opening r), as `geoavatar eval RUN --speech` computes them; the
voice's own gain is scored too.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--gains", type=float, nargs="+", default=[1.0, 1.4, 1.6, 1.8, 2.0])
    args = parser.parse_args()

    from geoavatar.runtime import setup_process

    setup_process()
    from geoavatar.eval.speech_run import evaluate_speech
    from geoavatar.train.checkpoint import open_run
    from geoavatar.voice.model import VoiceModel

    run = open_run(args.run, "cpu")
    voice = VoiceModel.load(args.run)
    own = voice.gain
    for gain in sorted({*args.gains, own}):
        voice.gain = gain
        scores = evaluate_speech(run, voice, render=False, progress=False).scores
        lve, mean_face = scores["voice"]["lip_vertex_error"], scores["mean_face"]["lip_vertex_error"]
        print(f"gain {gain:.2f}{' (its own)' if gain == own else ''}: r {scores['voice']['mouth_open_correlation']:.3f}"
              f"  LVE {lve:.3e} m2 = {lve / mean_face:.3f}x the mean face", flush=True)


if __name__ == "__main__":
    main()
