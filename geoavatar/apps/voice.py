"""`geoavatar voice RUN`: learn the run's voice model from the training frames of its dataset (RUN/voice/).

`geoavatar train` does this by itself at its end when the dataset has speech; this command gives a voice to a run
trained before, or learns it again with other settings, without training the avatar again.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

from geoavatar.apps.common import RunPath
from geoavatar.errors import OptionError
from geoavatar.sound.activity import ADVISED_SPEECH_SECONDS
from geoavatar.voice.config import VoiceConfig

_DEFAULTS = VoiceConfig()


def learn_voice(run, data: Path | None = None, config: VoiceConfig | None = None, log=print,
                advise: bool = True) -> Path:
    """Train and save the run's voice model; returns its folder. VoiceModelError when the dataset has no speech.
    `advise`: say when the video held little speech to learn from."""
    from geoavatar.voice.train import train_voice

    started = time.perf_counter()
    voice = train_voice(run, config or VoiceConfig(), data, log=log)
    folder = voice.save(run.info.run_dir)
    info = voice.info
    log(f"voice: learned from {info['frames']} training frames ({info['speech_seconds']:.0f} s of speech) in "
        f"{time.perf_counter() - started:.0f} s -> {folder}")
    if advise and info["speech_seconds"] < ADVISED_SPEECH_SECONDS:
        log(f"voice: {info['speech_seconds']:.0f} s of speech is little to learn from: the mouth follows the sound "
            "closer with a minute or more of talking (docs/speech.md)")
    return folder


def voice(
    run: RunPath,
    data: Optional[Path] = None,
    steps: int = _DEFAULTS.steps,
    seed: int = _DEFAULTS.seed,
    threads: int = _DEFAULTS.threads,
    flame_dir: Optional[Path] = None,
) -> int:
    """Learn how the run's person moves their face when they speak, from the sound of its training frames.

    Writes RUN/voice/voice.npz (the network, the person's idle head motion and blinks) and voice.json (settings and
    training report); `geoavatar speak RUN` then makes the avatar say something new. The dataset needs a sound track
    with speech (`geoavatar prepare` keeps a video's sound); the held-out frames' sound is never heard.

    Args:
        run: Run folder written by `geoavatar train`.
        data: The run's dataset folder, when it moved since training.
        steps: Optimisation steps (each hears the training sound in a new recording condition).
        seed: Seed of the network's initialisation and of the recording conditions it trains with.
        threads: CPU threads.
        flame_dir: Folder with your FLAME model files (runs on FLAME-tracked data only).
    """
    from geoavatar.train.checkpoint import open_run

    if steps < 1:
        raise OptionError(f"--steps must be >= 1, got {steps}")
    if threads < 1:
        raise OptionError(f"--threads must be >= 1, got {threads}")
    loaded = open_run(run, "cpu", flame_dir)
    learn_voice(loaded, data, VoiceConfig(steps=steps, seed=seed, threads=threads))
    return 0


__all__ = ["learn_voice", "voice"]
