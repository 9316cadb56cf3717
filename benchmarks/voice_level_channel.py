"""Does the voice learn the mouth's slow changes from the sound's level? Two measurements on a run (#39).

    .venv/bin/python benchmarks/voice_level_channel.py RUN --stretches
    LEVEL_S=3 JITTER=0 .venv/bin/python benchmarks/voice_level_channel.py RUN --seeds 0

--stretches  over 5-s stretches of the video (every 2.5 s), the run's mean lip opening against the stretch's speech
             level (its loud frames' mean, dB, one fixed reference: the same microphone), pause share (Silero VAD)
             and peak level; the correlations over the training stretches and over all
otherwise     benchmarks/voice_level.py with a voice that hears one more input channel: the speech level of the past
             LEVEL_S seconds (the mean of the louder half of their frames' band means) relative to the statistics
             its features were normalised by. It learns that channel from the training sound normalised by the
             whole training sound's statistics (plus a random offset of JITTER normalised units a step), so at
             prediction `own` gives it the clip's level against the clip, `video` against the video.
"""

from __future__ import annotations

import os
import runpy
import sys
from pathlib import Path

import numpy as np
import torch

STRETCH = 5.0  # seconds


def stretches(run_dir: Path) -> None:
    from geoavatar.data.sound import read_dataset_sound
    from geoavatar.eval.speech import pearson
    from geoavatar.sound.features import power_frames
    from geoavatar.train.checkpoint import open_run
    from geoavatar.train.run_frames import RunFrames
    from geoavatar.voice.face import FaceProbe
    from geoavatar.voice.inputs import log_mel_torch
    from geoavatar.voice.model import SpokenFace

    run = open_run(run_dir, "cpu")
    frames, sound = RunFrames(run), read_dataset_sound(run.info.data_root)
    probe = FaceProbe(run.head, {k: v.cpu() for k, v in frames.identity().items()})
    order = lambda ts: sorted(ts, key=lambda t: sound.frame_times.get(t, t))  # noqa: E731
    timesteps = order(run.info.timesteps["train"] + run.info.timesteps["test"])
    face = SpokenFace.from_rows(frames.values.expr, frames.values.jaw_pose, [frames.row(t) for t in timesteps])
    dims = int(run.head.num_expr)
    with torch.no_grad():
        opening = 1000.0 * probe.opening(torch.from_numpy(face.expr[:, :dims]), torch.from_numpy(face.jaw)).numpy()
    times, speaking = sound.times(timesteps), sound.activity.mask(sound.times(timesteps))
    training_end = float(sound.times(order(run.info.timesteps["train"]))[-1])
    mel = log_mel_torch(torch.from_numpy(power_frames(sound.sound.samples)))
    energy = 10.0 * torch.log10((10.0 ** mel.double()).sum(-1)).numpy()  # [F] dB, 100 a second
    rows = []
    for start in np.arange(0.0, times[-1] - STRETCH + 0.01, STRETCH / 2):
        inside = (times >= start) & (times < start + STRETCH)
        heard = energy[int(start * 100):int((start + STRETCH) * 100)]
        loud = heard >= np.percentile(heard, 95) - 35.0
        rows.append((start, opening[inside].mean(), (~speaking[inside]).mean(), heard[loud].mean(),
                     np.percentile(heard, 95)))
        print(f"{start:5.1f} s  opening {rows[-1][1]:.2f} mm  pauses {rows[-1][2]:.2f}  level {rows[-1][3]:+.1f} dB  "
              f"peak {rows[-1][4]:+.1f} dB")
    table = np.array(rows)
    training = table[:, 0] + STRETCH <= training_end
    for column, name in ((2, "pause share"), (3, "level"), (4, "peak level")):
        within, overall = pearson(table[training, 1], table[training, column]), pearson(table[:, 1], table[:, column])
        print(f"r of the mean opening with the {name}: training stretches {within:.2f}, all {overall:.2f}")


def level(features: torch.Tensor, span: int) -> torch.Tensor:
    """[F] the mean of the louder half of the past `span` frames' band means, for normalised features [F, M]."""
    means = features.mean(1).double().numpy()
    out = np.empty_like(means)
    for frame in range(len(means)):
        heard = np.sort(means[max(0, frame - span + 1):frame + 1])
        out[frame] = heard[len(heard) // 2:].mean()
    return torch.from_numpy(out).float()


def patch_level_channel(span: int, jitter: float) -> None:
    import geoavatar.voice.model as voice_model
    import geoavatar.voice.net as voice_net
    import geoavatar.voice.train as voice_train
    from geoavatar.sound import FRAME_RATE, N_MELS

    with_level = lambda features, channel: torch.cat([features, channel[:, None]], 1)  # noqa: E731

    def build_net(config, outputs):
        frames = int(round(config.past * FRAME_RATE)) + 1 + int(round(config.ahead * FRAME_RATE))
        return voice_net.VoiceEnsemble(config.members, N_MELS + 1, frames, outputs, config.width, config.hidden,
                                       config.dropout)

    predict_features = voice_model.VoiceModel.predict_features
    trainer_init, trainer_features = voice_train._Trainer.__init__, voice_train._Trainer._features

    def init(self, *args, **kwargs):
        trainer_init(self, *args, **kwargs)
        self.level = level(self.clean, span)  # the clean training sound, by the whole training sound's statistics
        self.clean = with_level(self.clean, self.level)

    def features(self):
        offset = float(self.rng.normal(0.0, jitter)) if jitter else 0.0
        return with_level(trainer_features(self), self.level + offset)

    voice_model.VoiceModel.build_net = staticmethod(build_net)
    voice_model.VoiceModel.predict_features = lambda self, feats, centres: predict_features(
        self, with_level(feats, level(feats, span)), centres)
    voice_model.VoiceModel.exists = staticmethod(lambda run_dir: False)  # the run's own voice has no such channel
    voice_train._Trainer.__init__, voice_train._Trainer._features = init, features


def main() -> None:
    if "--stretches" in sys.argv:
        stretches(Path(sys.argv[1]))
        return
    from geoavatar.sound import FRAME_RATE

    patch_level_channel(int(float(os.environ.get("LEVEL_S", "3")) * FRAME_RATE), float(os.environ.get("JITTER", "0")))
    script = Path(__file__).with_name("voice_level.py")
    sys.argv = [str(script)] + sys.argv[1:]
    runpy.run_path(str(script), run_name="__main__")


if __name__ == "__main__":
    main()
