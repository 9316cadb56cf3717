"""Learn how a person's face moves when they speak, from the training frames of their own video (`geoavatar voice`,
and `geoavatar train` at its end when the dataset has speech).

    voice = train_voice(run, VoiceConfig())              # a VoiceModel; VoiceModelError when the dataset has no speech
    voice.save(run.info.run_dir)

The targets are the run's own per-frame parameters of its training frames (the refined rows the avatar was trained
with): expression and jaw. The sound is the dataset's (data/sound.py), cut where the training frames end: nothing of
the held-out segment's sound is heard, not even by the last training frame's look-ahead. The loss is measured where
the face moves: the parameters' change mapped to lip and upper-face vertices (the head model linearised at the mean
training face), plus the frame-to-frame change of the same (runs of consecutive frames), so the mouth moves as much
and as smoothly as the tracked one. Every step hears a new recording condition (inputs.Augmentation) with statistics
taken from a random stretch of the (augmented) training sound, as a new recording would be normalised. Each member
of the ensemble holds out its own block of `validation` of the training frames (in time), which chooses the step it
keeps (checked every `validate_every` steps) and which the others learn from: together they learn every frame.
Last, the level slope: how the training frames' mean face changes with the speech level over 5-s stretches (a sound
heard at the video's loudness moves the mean face by it: VoiceModel.level_of).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from geoavatar.data.sound import DatasetSound, read_dataset_sound
from geoavatar.runtime import num_threads
from geoavatar.sound import FRAME_RATE
from geoavatar.sound.features import power_frames
from geoavatar.voice.config import VoiceConfig
from geoavatar.voice.face import FaceProbe
from geoavatar.voice.idle import IdleMotion, upper_face_projection
from geoavatar.voice.inputs import (Augmentation, log_mel_torch, loud_frames, normalise, speech_level, speech_stats,
                                    windows)
from geoavatar.voice.model import VoiceModel, VoiceModelError

STATS_SECONDS = (5.0, 20.0)  # the stretch of sound a step's normalisation statistics come from
LEVEL_STRETCH = 5.0  # seconds: the stretches (every half of it) over which the mean face is fitted to the speech level
MIN_TRAINING_SPEECH = 0.5  # seconds of speech in the training frames below which there is no word to learn from


@dataclass
class VoiceData:
    """The training frames of a run with their sound: what train_voice fits."""

    power: torch.Tensor  # [F, B] power spectra of the sound up to the end of the training frames
    centres: torch.Tensor  # [N] feature frame of each training frame (time order)
    targets: torch.Tensor  # [N, D] expression (expr_dims) and jaw of each
    params: dict[str, np.ndarray]  # their per-frame parameters [N, ...] (the idle motion's source)
    fps: float
    expr_width: int
    speech_seconds: float


def voice_data(run, frames, sound: DatasetSound, expr_dims: int) -> VoiceData:
    """The run's training frames in time order, their targets, and the sound cut between the last training frame and
    the first frame after it."""
    train = sorted(run.info.timesteps["train"], key=lambda t: sound.frame_times[t] if t in sound.frame_times else t)
    # frames shown before or after the sound track (one shorter than the picture) are left out: they hear nothing
    seconds = sound.sound.seconds
    train = [t for t in train if not (t in sound.frame_times and not 0.0 <= sound.frame_times[t] < seconds)]
    if not train:
        raise VoiceModelError("none of the training frames lies on the dataset's sound track (audio.json)")
    times = sound.times(train)  # [N] seconds
    later = [sound.frame_times[t] for t in frames.timesteps if t not in set(train) and t in sound.frame_times
             and sound.frame_times[t] > times[-1]]
    cut = 0.5 * (times[-1] + min(later)) if later else sound.sound.seconds
    power = torch.from_numpy(power_frames(sound.sound.segment(0.0, cut).samples))
    rows = [frames.row(t) for t in train]
    values = {k: v[rows].detach().cpu() for k, v in frames.values.to_npz().items()
              if v.dim() > 1 and k != "static_offset"}
    targets = torch.cat([values["expr"][:, :expr_dims], values["jaw_pose"]], dim=1).float()
    spacing = np.diff(times)
    fps = float(1.0 / np.median(spacing)) if len(spacing) else 25.0
    speech = sound.activity.mask(times).mean() * len(times) / fps
    return VoiceData(power, torch.from_numpy(np.round(times * FRAME_RATE).astype(np.int64)), targets,
                     {k: v.numpy() for k, v in values.items()}, fps, int(values["expr"].shape[1]), float(speech))


JACOBIAN_STEP = 1e-3  # central differences: expression coefficients are O(1), jaw angles O(0.1) rad


@torch.no_grad()
def face_jacobians(probe: FaceProbe, targets: torch.Tensor, expr_dims: int) -> tuple[torch.Tensor, torch.Tensor]:
    """([Kl*3, D], [Ku*3, D]): how lip and upper-face vertices move with each output at the mean training face (central
    differences, all 2D faces in one batch: the expression is linear, the jaw nearly so at this step)."""
    mean = targets.mean(0)
    steps = JACOBIAN_STEP * torch.eye(len(mean))
    faces = torch.cat([mean + steps, mean - steps])  # [2D, D]
    expr, jaw = faces[:, :expr_dims], faces[:, expr_dims:]
    out = []
    for which in ("lips", "upper"):
        moved = getattr(probe, which)(expr, jaw).double().reshape(2, len(mean), -1)  # [2, D, K*3]
        out.append(((moved[0] - moved[1]) / (2 * JACOBIAN_STEP)).T)
    return out[0], out[1]


def loss_metric(lips: torch.Tensor, upper: torch.Tensor, std: torch.Tensor, upper_weight: float) -> torch.Tensor:
    """[D, D] M such that d^T M d is the mean squared vertex error (m^2) of a standardised output error d."""
    metric = (lips.T @ lips + upper_weight * upper.T @ upper) / (lips.shape[0] + upper_weight * upper.shape[0]) * 3
    metric = std[:, None] * metric * std[None]  # standardised units
    ridge = 1e-3 * torch.trace(metric) / metric.shape[0]  # outputs that move no vertex still get a little loss
    return (metric + ridge * torch.eye(metric.shape[0], dtype=metric.dtype)).float()


def validation_blocks(count: int, config: VoiceConfig) -> list[slice]:
    """Each member's validation frames: a block of `validation` of the `count` frames (in time) ending at
    (k + 1) / members of them; member k learns from the rest. One member: the last block."""
    size = int(round(count * config.validation))
    if size == 0:  # no validation share: the step and gain are chosen on the training frames themselves
        return [slice(0, count)] * config.members
    ends = [int(round(count * (k + 1) / config.members)) for k in range(config.members)]
    return [slice(max(0, end - size), end) for end in ends]


def _runs(count: int, config: VoiceConfig, rng: np.random.Generator) -> torch.Tensor:
    """[R, L] rows of a step: R = batch // run_length runs of L = run_length consecutive frames, starting anywhere."""
    runs = max(1, config.batch // config.run_length)
    starts = rng.integers(0, max(1, count - config.run_length + 1), runs)
    return torch.as_tensor(starts[:, None] + np.arange(config.run_length)[None]).clamp_max(count - 1)


def level_slope(mel: torch.Tensor, centres: torch.Tensor, targets: torch.Tensor) -> np.ndarray:
    """[D] how the training frames' mean face (targets [N, D] at feature frames `centres` [N]) changes with the speech
    level (per log10 unit: voice.inputs.speech_level of the log-mel frames [F, M]), least squares over stretches of
    LEVEL_STRETCH seconds every half of that. On one microphone a person who speaks louder opens the mouth wider:
    over french.mp4's 5-s stretches their mean lip opening and speech level go together at r 0.74 (BENCHMARKS.md)."""
    span = int(LEVEL_STRETCH * FRAME_RATE)
    levels, faces = [], []
    for start in range(0, max(1, len(mel) - span + 1), span // 2):
        inside = (centres >= start) & (centres < start + span)
        if int(inside.sum()) >= 10:
            levels.append(speech_level(speech_stats(mel[start:start + span])))
            faces.append(targets[inside].double().mean(0).numpy())
    if len(levels) < 3:  # too little sound to tell: the face does not follow the level
        return np.zeros(targets.shape[1])
    level = np.asarray(levels) - np.mean(levels)  # [S]
    face = np.stack(faces) - np.mean(faces, axis=0)  # [S, D]
    return level @ face / max(float(level @ level), 1e-12)


class _Trainer:
    """One voice model's optimisation (see the module docstring); `step` and `validate` on the data given."""

    def __init__(self, data: VoiceData, config: VoiceConfig, net, metric: torch.Tensor, mean, std,
                 blocks: list[slice]):
        self.data, self.config, self.net, self.metric = data, config, net, metric
        self.mean, self.std, self.blocks = mean, std, blocks
        count = len(data.targets)
        self.learns = torch.ones(len(blocks), count, dtype=torch.bool)  # [K, N] the rows each member learns from
        for member, block in enumerate(blocks):
            if block.stop - block.start < count:
                self.learns[member, block] = False
        self.z = (data.targets - mean) / std  # [N, D]
        self.rng = np.random.default_rng([config.seed, 0x701CE])
        self.optimiser = torch.optim.AdamW(net.parameters(), lr=config.lr, weight_decay=config.weight_decay)
        # the rate falls along a half cosine to a tenth: late steps settle instead of jumping between minima
        self.schedule = torch.optim.lr_scheduler.LambdaLR(
            self.optimiser, lambda step: 0.1 + 0.45 * (1.0 + np.cos(np.pi * min(step / config.steps, 1.0))))
        clean = log_mel_torch(data.power)
        self.clean = normalise(clean, speech_stats(clean))  # [F, M] validation features
        self.loud_power = float(data.power[loud_frames(clean)].sum(-1).mean())
        self.past, self.ahead = int(round(config.past * FRAME_RATE)), int(round(config.ahead * FRAME_RATE))

    def _features(self) -> torch.Tensor:
        """[F, M] the training sound as a new recording: a random condition, normalised by a random stretch of it."""
        condition = Augmentation.sample(self.rng) if self.rng.random() < self.config.augment else Augmentation()
        power = condition.apply(self.data.power, self.loud_power) if condition != Augmentation() else self.data.power
        mel = log_mel_torch(power, condition.warp)
        span = int(self.rng.uniform(*STATS_SECONDS) * FRAME_RATE)
        start = int(self.rng.integers(0, max(1, len(mel) - span)))
        return normalise(mel, speech_stats(mel[start:start + span]))

    def _loss(self, predicted: torch.Tensor, target: torch.Tensor, learns: torch.Tensor) -> torch.Tensor:
        """Vertex-space error of frames and of their frame-to-frame change, summed over the ensemble's members (each
        learns on its own rows); predicted [K, R, L, D] runs of L frames, target [R, L, D], learns [K, R, L]."""
        error = predicted - target
        weight = learns.float()
        frame = torch.einsum("krld,de,krle->krl", error, self.metric, error)
        frame = ((frame * weight).sum((1, 2)) / weight.sum((1, 2)).clamp_min(1.0)).sum()
        change = error[:, :, 1:] - error[:, :, :-1]
        both = weight[:, :, 1:] * weight[:, :, :-1]
        velocity = torch.einsum("krld,de,krle->krl", change, self.metric, change)
        velocity = ((velocity * both).sum((1, 2)) / both.sum((1, 2)).clamp_min(1.0)).sum()
        return frame + self.config.velocity_weight * velocity

    def step(self) -> float:
        self.net.train()
        rows = _runs(len(self.z), self.config, self.rng)  # [R, L] anywhere; each member's block is masked
        predicted = self.net(windows(self._features(), self.data.centres[rows.reshape(-1)], self.past, self.ahead))
        loss = self._loss(predicted.reshape(predicted.shape[0], *rows.shape, -1), self.z[rows], self.learns[:, rows])
        self.optimiser.zero_grad(set_to_none=True)
        loss.backward()
        self.optimiser.step()
        self.schedule.step()
        return float(loss.detach())

    @torch.no_grad()
    def _predict(self, rows: slice, member: int) -> torch.Tensor:
        """[n, D] one member's standardised faces of the frames `rows`, clean sound."""
        self.net.eval()
        return self.net.members[member](windows(self.clean, self.data.centres[rows], self.past, self.ahead))

    @torch.no_grad()
    def gain(self, lip_metric: torch.Tensor) -> float:
        """The scale of the standardised output that minimises the lips' vertex error on the validation blocks, each
        predicted by the member that did not learn it: <predicted, target> / <predicted, predicted> in the lips'
        metric [D, D], within [1, 2]. (A single member shrinks less than the ensemble's mean: a cautious gain.)"""
        predicted = torch.cat([self._predict(block, k) for k, block in enumerate(self.blocks)])
        target = torch.cat([self.z[block] for block in self.blocks])
        along = torch.einsum("nd,de,ne->", predicted, lip_metric, target)
        norm = torch.einsum("nd,de,ne->", predicted, lip_metric, predicted)
        return float(min(2.0, max(1.0, float(along / norm)))) if float(norm) > 0 else 1.0

    @torch.no_grad()
    def validate(self) -> list[float]:
        """Per member, the mean squared vertex error (m^2) of its own validation block."""
        scores = []
        for member, block in enumerate(self.blocks):
            error = self._predict(block, member) - self.z[block]
            scores.append(float(torch.einsum("nd,de,ne->", error, self.metric, error) / max(1, error.shape[0])))
        return scores


def train_voice(run, config: VoiceConfig | None = None, data_root: Path | None = None,
                log: Callable[[str], None] = print) -> VoiceModel:
    """A voice model of the run's person from its dataset's sound (the dataset the run recorded, or `data_root`)."""
    from geoavatar.train.run_frames import RunFrames

    config = config or VoiceConfig()
    config.validate()
    root = Path(data_root) if data_root is not None else run.info.data_root
    sound = read_dataset_sound(root)
    if sound is None or not sound.activity.has_speech:
        heard = "no sound track" if sound is None else f"{sound.activity.speech_seconds:.1f} s of speech"
        raise VoiceModelError(f"{root}: the dataset has {heard}; a voice is learned from a video in which the person "
                              "talks (prepare it with its sound)")
    started = time.perf_counter()
    with num_threads(config.threads):
        return _fit(run, RunFrames(run), sound, config, started, log)


def _fit(run, frames, sound: DatasetSound, config: VoiceConfig, started: float, log) -> VoiceModel:
    expr_dims = int(run.head.num_expr)
    data = voice_data(run, frames, sound, expr_dims)
    if data.speech_seconds < MIN_TRAINING_SPEECH:  # the video's speech may all lie in the held-out frames
        raise VoiceModelError(f"the training frames hold {data.speech_seconds:.1f} s of speech (the video's "
                              f"{sound.activity.speech_seconds:.1f} s lie mostly in its held-out frames); a voice is "
                              "learned from a video in which the person talks")
    mean, std = data.targets.mean(0), data.targets.std(0).clamp_min(1e-4)
    probe = FaceProbe(run.head, {k: v.cpu() for k, v in frames.identity().items()})
    lips, upper = face_jacobians(probe, data.targets, expr_dims)
    metric = loss_metric(lips, upper, std.double(), config.upper_weight)
    count = len(data.targets)
    blocks = validation_blocks(count, config)
    torch.manual_seed(config.seed)  # the network's initial weights: the same run every time
    net = VoiceModel.build_net(config, data.targets.shape[1])
    trainer = _Trainer(data, config, net, metric, mean, std, blocks)
    best = [float("inf")] * config.members  # each member keeps its own best step
    best_state: list[dict | None] = [None] * config.members
    history, losses = [], []
    for step in range(1, config.steps + 1):
        losses.append(trainer.step())
        if step % config.validate_every and step != config.steps:
            continue
        scores = trainer.validate()
        history.append((step, float(np.mean(losses)), float(np.mean(scores))))
        losses = []
        for member, score in enumerate(scores):
            if score < best[member]:
                best[member] = score
                best_state[member] = {k: v.clone() for k, v in net.members[member].state_dict().items()}
        if (time.perf_counter() - started) / 60.0 > config.max_minutes:
            log(f"voice: stopped at step {step} of {config.steps}, the {config.max_minutes:g}-minute cap")
            break
    for member, state in enumerate(best_state):
        net.members[member].load_state_dict(state)
    gain = trainer.gain(loss_metric(lips, upper, std.double(), 0.0))  # measured on the lips alone
    projection = upper_face_projection(lips[:, :expr_dims], upper[:, :expr_dims]).float().numpy()
    idle_params = {**data.params, "expr": data.params["expr"][:, :expr_dims]}
    info = {"frames": count, "validation_frames": blocks[0].stop - blocks[0].start, "fps": data.fps,
            "speech_seconds": round(data.speech_seconds, 2), "sound_seconds": round(len(data.power) / FRAME_RATE, 2),
            "steps": history[-1][0], "best_validation_m2": float(np.mean(best)), "gain": round(gain, 4),
            "history": history,
            "seconds": round(time.perf_counter() - started, 1), "source": str(sound.source)}
    mel = log_mel_torch(data.power)
    slope = level_slope(mel, data.centres, data.targets)
    faces = torch.stack([mean, mean + 0.1 * torch.from_numpy(slope).float()])  # the mean face, and it 1 dB louder
    moved = probe.opening(faces[:, :expr_dims], faces[:, expr_dims:])
    info["opening_mm_per_db"] = round(1000.0 * float(moved[1] - moved[0]), 3)  # how this person's mouth follows level
    return VoiceModel(config, net, mean.double().numpy(), std.double().numpy(), expr_dims, data.expr_width,
                      speech_stats(mel), IdleMotion.from_training(idle_params, projection, data.fps), info, gain, slope)


__all__ = ["VoiceData", "face_jacobians", "level_slope", "loss_metric", "train_voice", "voice_data"]
