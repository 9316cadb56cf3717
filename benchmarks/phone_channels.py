"""Experiment (measured and not kept, #39): pocketsphinx's phones as extra input channels of the voice model.

pocketsphinx (BSD, `pip install pocketsphinx`) ships an en-US acoustic model and a phone language model; its
allphone search labels every 10 ms frame of a recording with one of 39 English phones or silence, offline, in
~3 s for 50 s of sound. This script appends those labels (one-hot, times PHONE_SCALE; or 14 viseme groups with
PHONE_GROUPS=viseme) to the voice's normalised log-mel frames, for training and for the held-out prediction, and
runs benchmarks/voice_variants.py with that input (by patching the feature functions: the product never had it).

    PHONE_SCALE=2 .venv/bin/python benchmarks/phone_channels.py RUN --seeds 0,1,2

Result on french.mp4 (docs/speech.md, BENCHMARKS.md Speech): the LVE falls a little and r falls more, within the
seeds' spread; not kept (and the live path would need a streaming phone decoder).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).parent))

SCALE = float(os.environ.get("PHONE_SCALE", "2.0"))
GROUPS = os.environ.get("PHONE_GROUPS", "all")
PHONES = "SIL AA AE AH AO AW AY B CH D DH EH ER EY F G HH IH IY JH K L M N NG OW OY P R S SH T TH UH UW V W Y Z ZH".split()
VISEME = {"SIL": 0, "P": 1, "B": 1, "M": 1, "F": 2, "V": 2, "TH": 3, "DH": 3, "T": 4, "D": 4, "N": 4, "L": 4,
          "S": 5, "Z": 5, "SH": 6, "ZH": 6, "CH": 6, "JH": 6, "K": 7, "G": 7, "NG": 7, "HH": 7, "R": 8, "W": 9,
          "UW": 9, "UH": 9, "OW": 10, "AO": 10, "OY": 10, "AA": 11, "AE": 11, "AH": 11, "AW": 11, "AY": 11,
          "EH": 12, "EY": 12, "ER": 8, "IH": 13, "IY": 13, "Y": 13}
CLASSES = 14 if GROUPS == "viseme" else len(PHONES)


def phone_labels(samples: np.ndarray, frames: int) -> np.ndarray:
    """[frames] pocketsphinx allphone labels of 16 kHz samples, 100 frames a second ("SIL" where none)."""
    from pocketsphinx import Decoder, get_model_path

    model = get_model_path()
    decoder = Decoder(hmm=os.path.join(model, "en-us", "en-us"),
                      allphone=os.path.join(model, "en-us", "en-us-phone.lm.bin"), lw=2.0, beam=1e-20, pbeam=1e-20,
                      loglevel="FATAL", frate=100)
    decoder.start_utt()
    decoder.process_raw((np.clip(samples, -1, 1) * 32767).astype(np.int16).tobytes(), full_utt=True)
    decoder.end_utt()
    labels = np.array(["SIL"] * frames, dtype=object)
    for segment in decoder.seg():
        labels[segment.start_frame:min(frames, segment.end_frame + 1)] = segment.word
    return labels


def one_hot(samples: np.ndarray) -> torch.Tensor:
    """[F, CLASSES] for the F = n // 160 + 1 feature frames of n samples (pocketsphinx's frame i is centred about one
    frame after ours)."""
    count = len(samples) // 160 + 1
    labels = phone_labels(np.asarray(samples, np.float32), count + 1)
    labels = np.concatenate([["SIL"], labels[:count - 1]]) if count > 1 else labels[:count]
    out = np.zeros((count, CLASSES), np.float32)
    for i, label in enumerate(labels):
        k = VISEME.get(label, 0) if GROUPS == "viseme" else (PHONES.index(label) if label in PHONES else 0)
        out[i, k] = SCALE
    return torch.from_numpy(out)


def patch() -> None:
    import geoavatar.eval.speech as eval_speech
    import geoavatar.voice.model as voice_model
    import geoavatar.voice.train as voice_train
    from geoavatar.sound import FRAME_RATE, N_MELS
    from geoavatar.voice.inputs import normalise
    from geoavatar.voice.net import VoiceEnsemble

    cache: dict[int, torch.Tensor] = {}  # feature frames -> phone channels of the sound that has that many
    power_frames, predict_features = voice_train.power_frames, voice_model.VoiceModel.predict_features

    def power(sound):
        out = power_frames(sound)
        cache.setdefault(len(out), one_hot(sound.samples if hasattr(sound, "samples") else sound))
        return out

    def with_phones(mel, stats):
        x = normalise(mel, stats)
        return torch.cat([x, cache[len(mel)].to(x.dtype)], dim=1)

    def predict(self, features, centres):
        if features.shape[1] == N_MELS:
            features = torch.cat([features, cache[len(features)].to(features.dtype)], dim=1)
        return predict_features(self, features, centres)

    def build_net(config, outputs):
        frames = int(round(config.past * FRAME_RATE)) + 1 + int(round(config.ahead * FRAME_RATE))
        return VoiceEnsemble(config.members, N_MELS + CLASSES, frames, outputs, config.width, config.hidden,
                             config.dropout)

    voice_train.power_frames = eval_speech.power_frames = power
    voice_train.normalise = with_phones
    voice_model.VoiceModel.predict_features = predict
    voice_model.VoiceModel.build_net = staticmethod(build_net)


if __name__ == "__main__":
    patch()
    import voice_variants

    voice_variants.main()
