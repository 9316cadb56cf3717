"""Avatars for the web player's tests and benchmarks (benchmarks/web_player_bench.py imports this too)."""

from __future__ import annotations

import numpy as np
import torch


def varied_avatar(avatar, count: int, seed: int = 0) -> None:
    """Give `avatar` `count` Gaussians (in place) on random faces, with varied local means, rotations, scales,
    opacities, normal shading and pose offsets (hair that follows the head), and the colours of the Gaussians already on those faces (a run's step-0 state:
    the images' colours), so that every part of the player's GPU placement is exercised."""
    g = torch.Generator().manual_seed(seed)
    faces = torch.randint(0, avatar.num_gaussians, (count,), generator=g) if count > avatar.num_gaussians else \
        torch.randperm(avatar.num_gaussians, generator=g)[:count].sort().values
    p = avatar.params
    quats = torch.nn.functional.normalize(torch.randn(count, 4, generator=g) * 0.3 + torch.tensor([1.0, 0, 0, 0]), dim=-1)
    scales = torch.log(torch.rand(count, 3, generator=g) * 0.8 + 1.0) + torch.tensor([0.4, -1.0, 0.4])
    new = {"means": torch.randn(count, 3, generator=g) * 0.15, "quats": quats, "scales": scales,
           "f_dc": p["f_dc"].detach()[faces], "opacities": torch.logit(torch.rand(count, generator=g) * 0.4 + 0.55)}
    if "f_normal" in p:
        new["f_normal"] = torch.randn(count, 9, generator=g) * 0.08
    if "f_pose" in p:  # hair that follows the head: offsets that a frame's head turn (~0.1-0.3 rad) makes visible
        # (ignoring them costs the 64 px test frames 22-27 dB of PSNR against the CPU renderer)
        new["means_pose"] = torch.randn(count, 18, generator=g) * 2.0
        new["f_pose"] = torch.randn(count, 18, generator=g) * 2.0
    for name, value in new.items():
        p[name] = torch.nn.Parameter(value)
    avatar.binding = avatar.binding[faces].clone()


def cpu_and_truth(run, timestep: int) -> tuple[np.ndarray, np.ndarray]:
    """The CPU renderer's frame of a run's timestep from its dataset camera and the ground truth (the photo on the
    run's background), uint8 [H, W, 3], both at the run's resolution."""
    from geoavatar.apps.common import record_camera, render_params
    from geoavatar.data import DataConfig, HeadAvatarDataset, open_subject
    from geoavatar.imaging import to_uint8
    from geoavatar.render import composite_target
    from geoavatar.train.run_frames import RunFrames

    params, t = RunFrames(run).params(timestep)
    subject = open_subject(run.info.data_root)
    cpu = to_uint8(render_params(run, params, record_camera(subject, timestep, run.info.resolution), t))
    dataset = HeadAvatarDataset(subject, "all", DataConfig(resolution=run.info.resolution, cache="none"))
    item = dataset[dataset.timesteps.index(timestep)]
    background = torch.tensor(run.info.background, dtype=torch.float32)
    return cpu, to_uint8(composite_target(item["image"], item["mask"], background))


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR in dB of two uint8 images."""
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return 10.0 * float(np.log10(255.0 ** 2 / max(mse, 1e-12)))


def small_player(frames: int = 20, fps: float = 10.0, size: int = 64, splats: int = 300, audio=None,
                 live: str | None = None, seed: int = 0):
    """(PlayerAssets, posed vertices [T, V, 3] float32) of a small player with no run behind it: OpenHead (its
    mouth included) whose jaw opens and closes and whose head turns a little over `frames` frames, an avatar of
    `splats` Gaussians (varied_avatar, normal shading, hair that does not follow the head), seen from a camera 0.6 m in
    front at size x size px; `audio` and `live` as pack.player_assets takes them."""
    from geoavatar.avatar.model import GaussianAvatar
    from geoavatar.head import load_head_model
    from geoavatar.head.params import HeadParams
    from geoavatar.render.camera import Camera, look_at
    from geoavatar.web.pack import player_assets, quantise_clip

    head = load_head_model("openhead", mouth="geoavatar")
    phase = torch.linspace(0.0, 2.0 * np.pi, frames)
    zeros = torch.zeros(frames, 3)
    params = HeadParams(shape=torch.zeros(head.num_shape), expr=torch.zeros(frames, head.num_expr),
                        rotation=torch.stack([zeros[:, 0], 0.2 * torch.sin(phase), zeros[:, 0]], 1), neck_pose=zeros,
                        jaw_pose=torch.stack([0.15 * (1 - torch.cos(phase)), zeros[:, 0], zeros[:, 0]], 1),
                        eyes_pose=torch.zeros(frames, 6), translation=zeros)
    with torch.no_grad():
        vertices = head.forward_params(params).vertices.float()  # [T, V, 3]
    avatar = GaussianAvatar(head.faces, normal_shading=True)
    varied_avatar(avatar, splats, seed)
    centre = vertices[0].mean(0)
    camera = Camera(look_at(centre + torch.tensor([0.0, 0.0, 0.6]), centre),
                    torch.tensor([[1.5 * size, 0.0, size / 2], [0.0, 1.5 * size, size / 2], [0.0, 0.0, 1.0]]),
                    size, size)
    orbit = {"yaw": [-30.0, 30.0], "pitch": [-20.0, 20.0], "centre": centre.tolist()}
    assets = player_assets(avatar, quantise_clip(vertices), fps, camera, orbit, (1.0, 1.0, 1.0), list(range(frames)),
                           "test", live=live, audio=audio)
    return assets, vertices.numpy()


def on_off_tone(seconds: float, rate: int = 16000, frequency: float = 440.0, switch: float = 0.25,
                amplitude: float = 0.5):
    """pack.SoundTrack of a tone switched on and off every `switch` seconds (on first)."""
    from geoavatar.web.pack import SoundTrack

    t = np.arange(int(round(seconds * rate))) / rate
    on = (np.floor(t / switch) % 2) == 0
    return SoundTrack((amplitude * np.sin(2 * np.pi * frequency * t) * on).astype(np.float32), rate)
