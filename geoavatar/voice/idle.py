"""What the face does while its owner talks that the sound does not say: head motion, gaze, blinks and brows, played
from the person's own training frames so that a speaking avatar is never a frozen head.

    idle = IdleMotion.from_training(params, upper_projection, fps)   # the training frames' motion, in order
    player = idle.player(fps=25, seed=0)
    player.take(n) -> {"rotation": [n, 3], "neck_pose": [n, 3], "translation": [n, 3], "eyes_pose": [n, 6],
                       "upper_expr": [n, E]}

The player walks through segments of the training sequence (3-6 s each, starting anywhere), cross-fading 0.4 s from
one to the next, at any frame rate: the head turns, nods and sways as the person did while speaking to the camera,
the eyes move and blink as they did. `upper_expr` is each frame's expression change from the training mean projected
so that it moves the upper face (brows, eyelids) and keeps the lips still (`upper_face_projection`): the voice model
owns the mouth, this adds the blinks and brow movements the sound cannot predict.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

POSE_KEYS = ("rotation", "neck_pose", "translation", "eyes_pose")
SEGMENT_SECONDS = (3.0, 6.0)
FADE_SECONDS = 0.4


def upper_face_projection(lips_jacobian: torch.Tensor, upper_jacobian: torch.Tensor, lip_weight: float = 100.0
                          ) -> torch.Tensor:
    """[E, E] P: an expression change r -> P r that moves the upper-face vertices as r does and the lip vertices as
    little as possible (least squares: min |J_u (P r - r)|^2 + lip_weight |J_l P r|^2). Jacobians: [K*3, E]."""
    upper = upper_jacobian.T @ upper_jacobian  # [E, E]
    lips = lips_jacobian.T @ lips_jacobian
    ridge = 1e-6 * torch.trace(upper) / upper.shape[0] * torch.eye(upper.shape[0], dtype=upper.dtype)
    return torch.linalg.solve(upper + lip_weight * lips + ridge, upper)


@dataclass
class IdleMotion:
    sequences: dict[str, np.ndarray]  # POSE_KEYS and "upper_expr": [N, ...] the training frames in order
    fps: float  # their frame rate

    @staticmethod
    def from_training(params: dict[str, np.ndarray], projection: np.ndarray, fps: float) -> "IdleMotion":
        """params: the training frames' rows in time order (per-frame keys [N, ...], expr [N, E]); projection [E, E]."""
        expr = np.asarray(params["expr"], np.float32)
        upper = (expr - expr.mean(0)) @ np.asarray(projection, np.float32).T
        sequences = {key: np.asarray(params[key], np.float32) for key in POSE_KEYS}
        sequences["upper_expr"] = upper.astype(np.float32)
        return IdleMotion(sequences, float(fps))

    def __len__(self) -> int:
        return int(len(self.sequences["rotation"]))

    def player(self, fps: float, seed: int = 0) -> "IdlePlayer":
        return IdlePlayer(self, fps, seed)

    def arrays(self) -> dict[str, np.ndarray]:
        return {f"idle.{k}": v for k, v in self.sequences.items()} | {"idle.fps": np.array(self.fps)}

    @staticmethod
    def from_arrays(arrays: dict) -> "IdleMotion":
        sequences = {k[len("idle."):]: np.asarray(v) for k, v in arrays.items()
                     if k.startswith("idle.") and k != "idle.fps"}
        return IdleMotion(sequences, float(arrays["idle.fps"]))


class IdlePlayer:
    """Plays IdleMotion at `fps`, one frame at a time (a live source) or many (a file): segments and fades are drawn
    from a generator seeded with `seed`, so a clip is the same every time it is made."""

    def __init__(self, motion: IdleMotion, fps: float, seed: int = 0):
        self.motion, self.fps = motion, float(fps)
        self.rng = np.random.default_rng([seed, 0x1D1E])
        self.position = 0.0  # seconds into the current segment
        self.segment = self._new_segment()
        self.previous: tuple[float, float] | None = None  # the segment being faded out and its position

    def _new_segment(self) -> tuple[float, float]:
        """(start, length) in seconds of the training sequence."""
        total = len(self.motion) / self.motion.fps
        length = min(float(self.rng.uniform(*SEGMENT_SECONDS)), total)
        return float(self.rng.uniform(0.0, max(total - length, 0.0))), length

    def _at(self, seconds: float) -> dict[str, np.ndarray]:
        """The training sequence at a time (linear between frames)."""
        x = np.clip(seconds * self.motion.fps, 0, len(self.motion) - 1)
        a = int(np.floor(x))
        b, w = min(a + 1, len(self.motion) - 1), float(x - np.floor(x))
        return {k: (1 - w) * v[a] + w * v[b] for k, v in self.motion.sequences.items()}

    def next(self) -> dict[str, np.ndarray]:
        start, length = self.segment
        frame = self._at(start + self.position)
        if self.previous is not None:  # fading from the previous segment into this one
            fade = min(self.position / FADE_SECONDS, 1.0)
            old = self._at(self.previous[0] + self.previous[1] + self.position)
            frame = {k: fade * frame[k] + (1 - fade) * old[k] for k in frame}
            if fade >= 1.0:
                self.previous = None
        self.position += 1.0 / self.fps
        if self.position >= length:
            self.previous = (start, length)
            self.segment, self.position = self._new_segment(), 0.0
        return frame

    def take(self, count: int) -> dict[str, np.ndarray]:
        frames = [self.next() for _ in range(count)]
        return {k: np.stack([f[k] for f in frames]).astype(np.float32) for k in self.motion.sequences} if frames else \
            {k: np.zeros((0, *v.shape[1:]), np.float32) for k, v in self.motion.sequences.items()}


__all__ = ["IdleMotion", "IdlePlayer", "POSE_KEYS", "upper_face_projection"]
