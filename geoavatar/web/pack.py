"""The web player's format: an avatar's local Gaussians with their face binding, and a clip of posed head meshes.

A player folder (`geoavatar export RUN --format web`) holds

    index.html, player.js   the page and its bundle (three.js + Spark + web/src), copied from static/
    avatar.json             the manifest below
    avatar.bin              the splats in export order (below): float32 anchors [N, 4] (little-endian), float16
                            splat rows [N, 20], uint32 faces [F, 3], then, when the avatar's hair follows the head's
                            turn, float16 pose rows [P, 36] of the first P splats
    clip.bin                uint16 posed vertices [T, V, 3]: v = offset + code * step per axis
    audio.wav               only with a sound track: 16-bit PCM mono at the track's rate (manifest clip.audio)

Splat (what web/src/generator.js reads as one RGBA32F texel and five RGBA16F texels):
    anchor: local mean xyz (face-scale units), face index (float32: float16 holds integers only to 2048) |
    row: local rotation x y z w (unit) | local scale (linear) xyz, opacity | colour rgb (0.5 + C0 f_dc), F[2][2] |
    F[0][0..2], F[1][0] | F[1][1..2], F[2][0..1]
F is the normal-shading matrix of model.normal_shading (colour += F n, n the world normal of the splat's face;
zeros without it). The browser computes each face's frame from the clip's vertices (web/src/binding.js, the
maths of avatar/binding.py) and places every splat as avatar/model.py does: mu = k R mu_l + C,
q = q_face (x) q_l, s = k s_l, colour = max(colour + F n, 0). float16 keeps three significant digits of the row,
below what a splat's shape, colour and shading show (the fidelity test holds the page to the CPU renderer).

Hair that follows the head's turn (model.hair_follows_head, avatar/hair_motion.py): each frame of the clip carries
its head pose code c [6] (head rotation, neck; "clip.pose" [T][6]). Only the splats on the moving faces have pose
offsets, so the export puts them first (`splat_order`: moving splats, then the rest, each in the avatar's order) and
the pose row i, M [3, 6] then C [3, 6] row-major, belongs to splat i < P ("avatar.posed"): the page adds M c to its
local mean before placing it and C c to its colour before shading, as avatar/model.py does. A real avatar's
moving splats are two thirds to three quarters of them.

Only posed vertices and the triangle list leave Python: a FLAME avatar ships no FLAME model file or basis.

avatar.json: {"format" (2), "avatar": {splats, faces, vertices, shading, file}, "clip": {frames, fps, offset, step,
timesteps, file, source, audio}, "camera": {viewmat [4][4] OpenCV world-to-camera, K [3][3], width, height},
"viewmats": per-frame viewmats when the clip's cameras differ, "orbit": {centre, yaw [lo, hi], pitch [lo, hi]}
(degrees about the dataset camera; the turns the training video covered plus a margin), "background",
"live" (absent, "view", "drive" or "speak": the page is the microphone, web/live.py), "edit" (view's sliders)};
avatar.followsHead and clip.pose with hair that follows the head, and avatar.posed (P).

A clip with sound (player_assets(..., audio=)) has clip.audio = {"file": "audio.wav", "rate": Hz, "seconds": S}:
the page plays the sound and takes the shown frame from its clock, floor(seconds played * fps) clamped to the clip,
and the clip ends (or loops) where the sound does. A folder without clip.audio (older ones) plays as before, on the
page's own clock: the format version is unchanged.
"""

from __future__ import annotations

import io
import json
import shutil
import wave
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from geoavatar.avatar.hair_motion import POSE_CODE_DIM
from geoavatar.avatar.model import SH_C0
from geoavatar.io.atomic import atomic_folder

FORMAT_VERSION = 2  # 2: anchors float32 + rows float16, pose rows of the moving splats only
MANIFEST = "avatar.json"
AVATAR_FILE = "avatar.bin"
CLIP_FILE = "clip.bin"
AUDIO_FILE = "audio.wav"
PLAYER_FILES = ("index.html", "player.js")
SPLAT_FLOATS = 24  # what splat_table holds per splat: the anchor texel, then five row texels
ANCHOR_FLOATS = 4  # 1 RGBA32F texel per splat: local mean, face index
POSE_FLOATS = 36  # 9 RGBA16F texels per moving splat: M [3, 6], C [3, 6] of the hair's pose offsets
CODE_MAX = 65535  # uint16 codes of the clip
PCM_MAX = 32767  # 16-bit PCM of audio.wav: sample = round(s * 32767), s clipped to [-1, 1]


def static_dir() -> Path:
    """The built page and bundle inside the package (made by `make web`)."""
    return Path(str(resources.files("geoavatar.web") / "static"))


def splat_table(avatar) -> np.ndarray:
    """[N, 24] float32: the avatar's local Gaussians in the row layout of the module docstring."""
    p = {name: value.detach().to("cpu", torch.float64) for name, value in avatar.params.items()}  # any device
    n = avatar.num_gaussians
    table = torch.zeros(n, SPLAT_FLOATS, dtype=torch.float64)
    quats = torch.nn.functional.normalize(p["quats"], dim=-1)  # [N, 4] w x y z
    table[:, 0:3] = p["means"]
    table[:, 3] = avatar.binding.to("cpu", torch.float64)
    table[:, 4:7], table[:, 7] = quats[:, 1:4], quats[:, 0]  # x y z w (three.js order)
    table[:, 8:11] = p["scales"].exp()
    table[:, 11] = torch.sigmoid(p["opacities"])
    table[:, 12:15] = SH_C0 * p["f_dc"] + 0.5
    if avatar.normal_shading:
        shading = p["f_normal"].reshape(n, 9)  # F row-major: [F00 F01 F02 F10 F11 F12 F20 F21 F22]
        table[:, 15] = shading[:, 8]
        table[:, 16:20] = shading[:, 0:4]
        table[:, 20:24] = shading[:, 4:8]
    return table.float().numpy()


def pose_table(avatar) -> np.ndarray | None:
    """[N, 36] float16: each splat's pose offsets M [3, 6] then C [3, 6] (row-major; zeros off the moving faces), or
    None when the avatar's Gaussians do not follow the head's turn."""
    if not avatar.follows_head:
        return None
    moving = torch.from_numpy(moving_splats(avatar)).to(torch.float64)[:, None]  # [N, 1]
    table = torch.cat([avatar.params[name].detach().to("cpu", torch.float64) * moving
                       for name in ("means_pose", "f_pose")], dim=1)  # [N, 36]
    return _half(table.numpy(), "pose offsets")


def moving_splats(avatar) -> np.ndarray:
    """[N] bool: the splats on moving faces (hair that follows the head); none when the avatar's do not follow it."""
    if not avatar.follows_head:
        return np.zeros(avatar.num_gaussians, dtype=bool)
    return avatar.moving[avatar.binding].cpu().numpy()


def splat_order(avatar) -> tuple[np.ndarray, int]:
    """(order [N] int64, P): the export order of the splats, the P on moving faces first, then the rest, each in the
    avatar's order (the identity, P = 0, when the avatar's Gaussians do not follow the head)."""
    moving = moving_splats(avatar)  # [N]
    return np.concatenate([np.flatnonzero(moving), np.flatnonzero(~moving)]), int(moving.sum())


def _half(values: np.ndarray, what: str) -> np.ndarray:
    if not np.isfinite(values).all() or np.abs(values).max(initial=0.0) > np.finfo(np.float16).max:
        raise ValueError(f"web export: the avatar's {what} are not finite in float16")
    return values.astype("<f2")


@dataclass
class QuantisedClip:
    codes: np.ndarray  # [T, V, 3] uint16
    offset: np.ndarray  # [3] float64
    step: np.ndarray  # [3] float64

    def vertices(self) -> np.ndarray:
        """[T, V, 3] float32: what the page decodes."""
        return (self.offset + self.codes.astype(np.float64) * self.step).astype(np.float32)


def quantise_clip(vertices: Tensor | np.ndarray) -> QuantisedClip:
    """[T, V, 3] posed vertices -> uint16 codes over the clip's box per axis (a 30 cm box: 5 micrometre steps)."""
    v = np.asarray(vertices.detach().cpu() if isinstance(vertices, Tensor) else vertices, dtype=np.float64)
    if v.ndim != 3 or v.shape[-1] != 3 or v.shape[0] < 1:
        raise ValueError(f"quantise_clip: vertices must be [T, V, 3] with T >= 1, got {v.shape}")
    if not np.isfinite(v).all():
        raise ValueError("quantise_clip: the posed vertices hold NaN or Inf")
    low, high = v.min(axis=(0, 1)), v.max(axis=(0, 1))
    step = np.maximum(high - low, 1e-9) / CODE_MAX
    codes = np.clip(np.rint((v - low) / step), 0, CODE_MAX).astype("<u2")
    return QuantisedClip(codes, low, step)


@dataclass
class SoundTrack:
    """A clip's sound: mono samples in [-1, 1] at `rate` Hz. player_assets takes any object with `.samples` and
    `.rate` (geoavatar.sound's Sound too)."""

    samples: np.ndarray  # [n] float32
    rate: int  # Hz


def wav_bytes(sound) -> bytes:
    """audio.wav's contents: `sound` (.samples [n] in [-1, 1], .rate Hz) as 16-bit PCM mono; ValueError naming what
    is wrong (not mono, empty, not finite, a rate that is not a positive integer)."""
    samples = _array(sound.samples)
    if samples.ndim != 1 or samples.size == 0:
        raise ValueError(f"player_assets: the sound must be mono samples [n], n >= 1, got shape {samples.shape}")
    if not np.isfinite(samples).all():
        raise ValueError("player_assets: the sound's samples hold NaN or Inf")
    rate = sound.rate
    if isinstance(rate, bool) or not float(rate).is_integer() or not 0 < int(rate) < 2**31:
        raise ValueError(f"player_assets: the sound's rate must be a positive integer (Hz), got {rate!r}")
    pcm = np.rint(np.clip(samples, -1.0, 1.0) * PCM_MAX).astype("<i2")
    out = io.BytesIO()
    with wave.open(out, "wb") as wav:
        wav.setnchannels(1)
        wav.setsampwidth(2)
        wav.setframerate(int(rate))
        wav.writeframes(pcm.tobytes())
    return out.getvalue()


def read_wav(data: bytes) -> SoundTrack:
    """audio.wav's contents back as a SoundTrack (float32 samples / 32767); ValueError when it is not 16-bit mono."""
    with wave.open(io.BytesIO(data), "rb") as wav:
        if wav.getnchannels() != 1 or wav.getsampwidth() != 2:
            raise ValueError(f"audio.wav: 16-bit mono expected, got {wav.getnchannels()} channels of "
                             f"{8 * wav.getsampwidth()} bits")
        pcm = np.frombuffer(wav.readframes(wav.getnframes()), dtype="<i2")
        return SoundTrack((pcm / PCM_MAX).astype(np.float32), wav.getframerate())


@dataclass
class PlayerAssets:
    """Everything a player serves besides the page: the manifest and the binary files (audio.wav with a sound)."""

    manifest: dict
    avatar_bytes: bytes
    clip_bytes: bytes
    extra: dict = field(default_factory=dict)
    audio_bytes: bytes | None = None  # audio.wav (manifest clip.audio), or None: a clip without sound

    def files(self) -> dict[str, bytes]:
        """name -> contents of the data files (page and bundle not included)."""
        files = {MANIFEST: json.dumps(self.manifest, indent=1).encode(), AVATAR_FILE: self.avatar_bytes,
                 CLIP_FILE: self.clip_bytes}
        if self.audio_bytes is not None:
            files[AUDIO_FILE] = self.audio_bytes
        return files


def _array(values: Tensor | np.ndarray) -> np.ndarray:
    return np.asarray(values.detach().cpu() if isinstance(values, Tensor) else values, dtype=np.float64)


def _listed(matrix: Tensor | np.ndarray) -> list:
    return _array(matrix).tolist()


def player_assets(avatar, clip: QuantisedClip, fps: float, camera, orbit: dict, background, timesteps: list[int],
                  source: str, viewmats: list | None = None, live: str | None = None,
                  edit: dict | None = None, pose_codes: Tensor | np.ndarray | None = None,
                  audio=None) -> PlayerAssets:
    """The manifest and binaries of `avatar` playing `clip` (see the module docstring); camera: render.camera.Camera;
    pose_codes [T, 6]: each frame's head pose code, needed when the avatar's hair follows the head; audio: the clip's
    sound (.samples [n] float in [-1, 1], mono, .rate Hz: a SoundTrack or geoavatar.sound's Sound), written as
    audio.wav and played by the page as the clip's clock."""
    order, posed = splat_order(avatar)  # [N], P
    table = splat_table(avatar)[order]  # [N, 24]
    poses = pose_table(avatar)
    codes = None if pose_codes is None else _array(pose_codes)  # [T, 6]
    faces = avatar.faces.detach().cpu().numpy().astype("<u4")  # [F, 3]
    frames, vertex_count, _ = clip.codes.shape
    if poses is not None and (codes is None or codes.shape != (frames, POSE_CODE_DIM)):
        raise ValueError(f"player_assets: the avatar's hair follows the head, so each of the {frames} frames needs its "
                         f"head pose code [{frames}, {POSE_CODE_DIM}], got {None if codes is None else codes.shape}")
    manifest = {
        "format": FORMAT_VERSION,
        "avatar": {"splats": int(table.shape[0]), "faces": int(faces.shape[0]), "vertices": int(vertex_count),
                   "shading": bool(avatar.normal_shading), "file": AVATAR_FILE},
        "clip": {"frames": int(frames), "fps": float(fps), "offset": clip.offset.tolist(), "step": clip.step.tolist(),
                 "timesteps": [int(t) for t in timesteps], "source": source, "file": CLIP_FILE},
        "camera": {"viewmat": _listed(camera.viewmat), "K": _listed(camera.K), "width": int(camera.width),
                   "height": int(camera.height)},
        "orbit": orbit,
        "background": [float(c) for c in background],
    }
    if poses is not None:
        manifest["avatar"]["followsHead"] = True
        manifest["avatar"]["posed"] = posed
        manifest["clip"]["pose"] = codes.tolist()
    if viewmats is not None:
        manifest["viewmats"] = [_listed(v) for v in viewmats]
    if live is not None:
        manifest["live"] = live
    if edit is not None:
        manifest["edit"] = edit
    audio_bytes = None
    if audio is not None:
        audio_bytes = wav_bytes(audio)
        rate, count = int(audio.rate), int(_array(audio.samples).size)
        manifest["clip"]["audio"] = {"file": AUDIO_FILE, "rate": rate, "seconds": count / rate}
    avatar_bytes = (table[:, :ANCHOR_FLOATS].astype("<f4").tobytes()
                    + _half(table[:, ANCHOR_FLOATS:], "splat rows").tobytes() + faces.tobytes())
    if poses is not None:
        avatar_bytes += poses[order[:posed]].astype("<f2").tobytes()  # [P, 36]: the moving splats' rows
    return PlayerAssets(manifest, avatar_bytes, clip.codes.tobytes(), audio_bytes=audio_bytes)


def write_player_folder(out: str | Path, assets: PlayerAssets) -> Path:
    """The page, its bundle and the assets into the folder `out`, which appears complete or not at all."""
    static = static_dir()
    missing = [name for name in PLAYER_FILES if not (static / name).is_file()]
    if missing:
        raise FileNotFoundError(f"the web player is not built ({', '.join(missing)} missing in {static}): run make web")
    with atomic_folder(out) as folder:
        for name in PLAYER_FILES:
            shutil.copyfile(static / name, folder / name)
        for name, data in assets.files().items():
            (folder / name).write_bytes(data)
    return Path(out)


__all__ = ["AUDIO_FILE", "AVATAR_FILE", "CLIP_FILE", "MANIFEST", "PLAYER_FILES", "PlayerAssets", "QuantisedClip",
           "SoundTrack", "moving_splats", "player_assets", "pose_table", "quantise_clip", "read_wav", "splat_order",
           "splat_table", "static_dir", "wav_bytes", "write_player_folder"]
