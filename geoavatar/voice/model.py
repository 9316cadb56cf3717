"""A trained voice model: sound -> each video frame's expression and jaw, plus the person's idle motion; saved beside
the run as numpy arrays and JSON (nothing is unpickled when it loads).

    voice = VoiceModel.load(run_dir)                      # RUN/voice/voice.npz + voice.json; else VoiceModelError
    face = voice.predict(sound, times)                    # SpokenFace: expr [N, E], jaw [N, 3] at these times (s)
    voice.save(run_dir)

The expression has the run's width (a head model with fewer modes uses the leading ones); the model predicts its
`expr_dims` leading coefficients and the jaw, standardised by the training frames' mean and spread.
"""

from __future__ import annotations

import json
import warnings
import zipfile
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from geoavatar.errors import GeoAvatarError, GeoAvatarWarning
from geoavatar.io.atomic import atomic_write_json, atomic_write_npz
from geoavatar.sound import FRAME_RATE, Sound
from geoavatar.sound.features import power_frames
from geoavatar.voice.config import VoiceConfig
from geoavatar.voice.idle import IdleMotion
from geoavatar.voice.inputs import SpeechStats, log_mel_torch, normalise, speech_level, speech_stats, windows
from geoavatar.voice.net import VoiceEnsemble, load_state_arrays, state_arrays

VOICE_DIR = "voice"
WEIGHTS_FILE = "voice.npz"
INFO_FILE = "voice.json"
FORMAT = "geoavatar-voice"
VERSION = 2  # 2: an ensemble of networks (1: one)
# how a sound is normalised before the networks hear it (VoiceModel.hearing): by its own speech statistics, so that any
# voice and any microphone move the mouth; or by the video's, for a recording made as the video was, where how loudly
# the person speaks moves the mouth too, and the mean face follows the sound's speech level by the level slope
# (french.mp4's held-out LVE 0.80-0.82x -> 0.55-0.57x the mean face's, r +0.01-0.03, three seeds: BENCHMARKS.md, Speech)
LOUDNESS = ("own", "video")
# beyond this many log10 units (6 dB) from the training speech a recording is not one made as the video was: the mean
# face's shift stops there
LEVEL_LIMIT = 0.6


def loudness_tag(loudness: str, label: bool = False) -> str:
    """How an output names the loudness a sound was heard at, so that no output replaces another's: "" for own,
    "@video-loudness" in a file or folder name, " (video loudness)" in a label."""
    if loudness == "own":
        return ""
    return f" ({loudness} loudness)" if label else f"@{loudness}-loudness"


class VoiceModelError(GeoAvatarError, ValueError):
    """A run has no voice model, or its files cannot be read; the message says what to do."""


@dataclass
class SpokenFace:
    expr: np.ndarray  # [N, E]
    jaw: np.ndarray  # [N, 3]

    def take(self, rows: list[int]) -> "SpokenFace":
        return SpokenFace(self.expr[rows], self.jaw[rows])

    @classmethod
    def from_rows(cls, expr, jaw, rows: list[int]) -> "SpokenFace":
        """Rows `rows` of per-frame expression [T, E] and jaw [T, 3] (tensors or arrays): a run's or a dataset's."""
        def array(values) -> np.ndarray:
            return np.asarray(values.detach().cpu() if isinstance(values, torch.Tensor) else values, np.float32)

        return cls(array(expr[rows]), array(jaw[rows]))


@dataclass
class VoiceModel:
    config: VoiceConfig
    net: VoiceEnsemble
    target_mean: np.ndarray  # [D] D = expr_dims + 3
    target_std: np.ndarray  # [D]
    expr_dims: int
    expr_width: int  # the run's expression width (predictions are zero-padded to it)
    # the training sound's statistics: a live microphone starts from them; hearing("video") normalises sounds by them
    speech: SpeechStats
    idle: IdleMotion
    info: dict = field(default_factory=dict)  # training report (times, losses, frames)
    # the networks' standardised output is scaled by this, fitted on the validation frames: averaging what a sound may
    # mean (and three networks' outputs) shrinks the mouth's motion; the least-squares gain restores what it can
    gain: float = 1.0
    # [D] how the training frames' mean face changes per log10 unit of speech level (train.level_slope); None: a voice
    # learned before it was kept, whose face does not follow the level
    level_slope: np.ndarray | None = None
    loudness: str = "own"  # LOUDNESS: the caller's choice (hearing), not saved with the model

    def hearing(self, loudness: str) -> "VoiceModel":
        """This voice, normalising what it hears by `loudness` (LOUDNESS)."""
        if loudness not in LOUDNESS:
            raise ValueError(f"loudness must be one of {', '.join(LOUDNESS)}, got {loudness!r}")
        if loudness == "video" and self.level_slope is None:
            warnings.warn(GeoAvatarWarning(
                "this voice model was learned before the level slope: with --loudness video the sound is heard at "
                "the video's loudness, but the mean mouth does not follow its level; `geoavatar voice RUN` learns "
                "the voice again with it"), stacklevel=2)
        return replace(self, loudness=loudness)

    @property
    def fixed_stats(self) -> SpeechStats | None:
        """The statistics every sound is normalised by when the loudness is the video's; None: each sound's own."""
        return self.speech if self.loudness == "video" else None

    @property
    def follows_level(self) -> bool:
        """Whether the mean face follows a sound's speech level: hearing the video's loudness, with a level slope
        (another microphone's level is the microphone's)."""
        return self.loudness == "video" and self.level_slope is not None

    def level_of(self, mel: torch.Tensor) -> float:
        """The level that the face follows for log-mel frames [F, M] (level_shift of their speech level)."""
        if not self.follows_level:  # spare the statistics (the live stream asks every half second)
            return 0.0
        return self.level_shift(speech_level(speech_stats(mel)) - speech_level(self.speech))

    def level_shift(self, level: float) -> float:
        """What the face follows of a sound whose speech level is `level` log10 units above the training sound's:
        that level within +-LEVEL_LIMIT when follows_level, otherwise 0."""
        return float(np.clip(level, -LEVEL_LIMIT, LEVEL_LIMIT)) if self.follows_level else 0.0

    def stats_of(self, mel: torch.Tensor) -> SpeechStats:
        """The statistics a sound's log-mel frames [F, M] are normalised by (`loudness`)."""
        return self.fixed_stats or speech_stats(mel)

    @property
    def past(self) -> int:
        return int(round(self.config.past * FRAME_RATE))

    @property
    def ahead(self) -> int:
        return int(round(self.config.ahead * FRAME_RATE))

    @staticmethod
    def build_net(config: VoiceConfig, outputs: int) -> VoiceEnsemble:
        from geoavatar.sound import N_MELS

        frames = int(round(config.past * FRAME_RATE)) + 1 + int(round(config.ahead * FRAME_RATE))
        return VoiceEnsemble(config.members, N_MELS, frames, outputs, config.width, config.hidden, config.dropout)

    @torch.no_grad()
    def predict_features(self, features: torch.Tensor, centres: torch.Tensor, level: float = 0.0) -> SpokenFace:
        """Normalised log-mel frames [F, M] and the feature frame of each video frame [N] -> SpokenFace; `level`: the
        sound's speech level that the mean face follows (level_of)."""
        self.net.eval()
        outputs = []
        for chunk in torch.split(centres, 512):
            outputs.append(self.net.predict(windows(features, chunk, self.past, self.ahead)))
        z = torch.cat(outputs).double().numpy() if outputs else np.zeros((0, len(self.target_mean)))
        values = self.target_mean + self.gain * z * self.target_std  # [N, D]
        if level and self.level_slope is not None:
            values = values + level * self.level_slope
        expr = np.zeros((len(values), self.expr_width), np.float32)
        expr[:, :self.expr_dims] = values[:, :self.expr_dims]
        return SpokenFace(expr, values[:, self.expr_dims:].astype(np.float32))

    def predict(self, sound: Sound, times: np.ndarray, stats: SpeechStats | None = None) -> SpokenFace:
        """Each frame's face at `times` (seconds from the sound's first sample); the sound normalised as `loudness`
        says unless `stats` are given."""
        mel = log_mel_torch(torch.from_numpy(power_frames(sound)))
        stats = stats or self.stats_of(mel)
        centres = torch.from_numpy(np.round(np.asarray(times) * FRAME_RATE).astype(np.int64))
        return self.predict_features(normalise(mel, stats), centres, self.level_of(mel))

    # --- files ---------------------------------------------------------------------------------------

    def save(self, run_dir: str | Path) -> Path:
        folder = Path(run_dir) / VOICE_DIR
        folder.mkdir(parents=True, exist_ok=True)
        arrays = state_arrays(self.net) | self.idle.arrays() | {
            "target_mean": self.target_mean, "target_std": self.target_std,
            "speech.mean": self.speech.mean.numpy(), "speech.scale": self.speech.scale.numpy(),
            "gain": np.asarray(self.gain, np.float64)} | (
            {} if self.level_slope is None else {"level_slope": np.asarray(self.level_slope, np.float64)})
        staged = atomic_write_npz(folder / f".{WEIGHTS_FILE}.new", **arrays)  # a voice learned before stays whole
        (folder / INFO_FILE).unlink(missing_ok=True)  # until here; the json goes last: with it, the model is complete
        staged.replace(folder / WEIGHTS_FILE)
        atomic_write_json(folder / INFO_FILE, {"format": FORMAT, "version": VERSION, "config": self.config.to_dict(),
                                               "expr_dims": self.expr_dims, "expr_width": self.expr_width,
                                               "info": self.info})
        return folder

    @staticmethod
    def exists(run_dir: str | Path) -> bool:
        return (Path(run_dir) / VOICE_DIR / INFO_FILE).is_file()

    @staticmethod
    def readable(run_dir: str | Path) -> bool:
        """Whether the run holds a voice model this code reads (not one damaged, or of an older format)."""
        try:
            VoiceModel.load(run_dir)
        except VoiceModelError:
            return False
        return True

    @staticmethod
    def load(run_dir: str | Path) -> "VoiceModel":
        """The run's voice model; VoiceModelError saying how to get one when it has none."""
        folder = Path(run_dir) / VOICE_DIR
        if not (folder / INFO_FILE).is_file():
            raise VoiceModelError(
                f"{run_dir}: the run has no voice model ({VOICE_DIR}/{INFO_FILE}); it learns one from a dataset with "
                f"speech: prepare a video in which you talk, then `geoavatar train`, or `geoavatar voice {run_dir}` "
                "for a run trained on such a dataset")
        try:
            return VoiceModel._read(folder)
        except (OSError, ValueError, KeyError, TypeError, AttributeError, RuntimeError, zipfile.BadZipFile) as err:
            raise VoiceModelError(f"{folder}: the voice model cannot be read ({type(err).__name__}: {err}); learn it "
                                  f"again with `geoavatar voice {run_dir}`") from err

    @staticmethod
    def _read(folder: Path) -> "VoiceModel":
        info = json.loads((folder / INFO_FILE).read_text())
        if not isinstance(info, dict) or info.get("format") != FORMAT or info.get("version") != VERSION:
            found = (info.get("format"), info.get("version")) if isinstance(info, dict) else type(info).__name__
            raise ValueError(f"{INFO_FILE} is {found}, expected {FORMAT} {VERSION}")
        config = VoiceConfig(**info["config"])
        with np.load(folder / WEIGHTS_FILE, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
        mean, std = arrays["target_mean"], arrays["target_std"]  # [D]
        outputs = int(info["expr_dims"]) + 3  # D: the expression's leading coefficients and the jaw
        for name in ("target_mean", "target_std", "level_slope"):
            if name in arrays and arrays[name].shape != (outputs,):
                raise ValueError(f"{WEIGHTS_FILE}'s {name} has shape {arrays[name].shape}, expected ({outputs},)")
        net = VoiceModel.build_net(config, len(mean))
        load_state_arrays(net, arrays)
        speech = SpeechStats(torch.from_numpy(arrays["speech.mean"]), torch.from_numpy(arrays["speech.scale"]))
        return VoiceModel(config, net, mean, std, int(info["expr_dims"]), int(info["expr_width"]), speech,
                          IdleMotion.from_arrays(arrays), info.get("info", {}), float(arrays.get("gain", 1.0)),
                          arrays.get("level_slope"))


__all__ = ["FORMAT", "INFO_FILE", "LEVEL_LIMIT", "LOUDNESS", "SpokenFace", "VOICE_DIR", "VoiceModel", "VoiceModelError",
           "WEIGHTS_FILE", "loudness_tag"]
