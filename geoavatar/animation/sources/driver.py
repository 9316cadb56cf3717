"""A tracked driver dataset drives the avatar: its motion, transferred (animation/transfer.py), as a source.

    driven = DrivenAvatar(run, driver_root, DrivingOptions(transfer="relative"), fps=25.0)   # reenact, eval --driver
    motion = DriverMotion(run, driver_root, "subspace", fps=25.0)                              # export --format web

DrivenAvatar walks the driver's dataset frames (its --driver-split, `max_frames` spread evenly): each frame's
parameters driven by the transfer mode, T = 0 (novel animation, as the paper does at inference), the driver's picture
(its photo on its background outside its mask, what reenact shows beside the avatar and eval scores against) and,
with --camera driver, the driver frame's camera; with --camera avatar the frames carry none and the sink uses
`fixed_camera`, the avatar's dataset camera of its neutral frame (its first frame with 'first' and 'mean') at the
renders' resolution. DriverMotion is the motion alone: one frame per driver timestep, no picture, no camera.

The driver keeps its own identity; only its motion is transferred. It must be tracked with the same head model as the
avatar (expression coefficients mean nothing across models).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Sequence

import torch
from torch import Tensor

from geoavatar.animation.expression_transfer import DEFAULT_TRANSFER, TransferMode
from geoavatar.animation.frames import AnimationFrame
from geoavatar.animation.posing import record_camera, render_params, run_background
from geoavatar.animation.transfer import subject_params
from geoavatar.data import DataConfig, HeadAvatarDataset, evenly_spaced, open_subject
from geoavatar.data.dataset import item_camera
from geoavatar.data.subject import Subject
from geoavatar.errors import GeoAvatarError, OptionError
from geoavatar.eval.cross import DrivenPicture
from geoavatar.head.params import HeadParams
from geoavatar.imaging import to_uint8
from geoavatar.render import composite_target
from geoavatar.train.checkpoint import LoadedRun, RunError
from geoavatar.train.run_frames import RunFrames


def frame_of(params: dict[str, Tensor], row: int) -> HeadParams:
    return HeadParams.from_npz(params).frame(row)


def open_driver(driver: Path, run: LoadedRun) -> Subject:
    try:
        subject = open_subject(driver)
    except GeoAvatarError as err:  # DatasetError, a FLAME file error: name the option
        raise RunError(f"--driver {driver}: {err}") from err
    if subject.head_model != run.info.head_model:
        raise RunError(f"--driver {driver}: tracked with head model '{subject.head_model}', but the avatar uses "
                       f"'{run.info.head_model}'; expression and pose parameters do not carry across head models")
    return subject


def driven_clip(run: LoadedRun, frames: RunFrames, driver_root: Path, mode: TransferMode | bool = "absolute",
                driver_neutral: str = "first", avatar_neutral: str = "first",
                driver_translation: bool = False) -> tuple[Subject, dict[str, Tensor]]:
    """The driver (`--driver`) and the avatar's parameters [T, ...] for each of its timesteps in transfer `mode` (a
    bool is the old `relative` flag)."""
    subject = open_driver(driver_root, run)
    return subject, subject_params(run, frames, subject, mode, driver_neutral, avatar_neutral, driver_translation)


def driver_picture(item: dict) -> Tensor:
    """[H, W, 3] the driver's frame as shown and scored: its photo on its background outside its mask."""
    return composite_target(item["image"], item["mask"], item["background"])


class DriverMotion:
    """Source: the driver's motion on the avatar, one frame per driver timestep (T = 0; no picture, no camera)."""

    live = False
    audio = None

    def __init__(self, run: LoadedRun, driver_root: Path, mode: TransferMode | bool = DEFAULT_TRANSFER,
                 fps: float = 25.0, frames: RunFrames | None = None):
        self.subject, self.params = driven_clip(run, frames if frames is not None else RunFrames(run), driver_root,
                                                mode)
        self.timesteps = list(self.subject.timesteps)
        self.fps = fps

    def __len__(self) -> int:
        return len(self.timesteps)

    def __iter__(self) -> Iterator[AnimationFrame]:
        for row, timestep in enumerate(self.timesteps):
            yield AnimationFrame(row, frame_of(self.params, row), None, timestep=timestep)

    def close(self) -> None:
        pass


@dataclass
class DrivingOptions:
    """How a driver drives the avatar: the options `reenact` and `eval --driver` share."""

    transfer: TransferMode = DEFAULT_TRANSFER
    driver_neutral: str = "first"
    avatar_neutral: str = "first"
    camera: str = "avatar"  # avatar: the avatar's dataset camera; driver: each driver frame's
    driver_split: str = "all"
    data: Path | None = None  # the avatar's dataset folder, when it moved since training
    backend: str = "auto"
    resolution: int | None = None  # longer side of the renders (None: the run's training resolution)


class DrivenAvatar:
    """Source: an avatar driven by a tracked driver dataset, frame by frame (module docstring): the one driving path
    of `reenact` and of `eval --driver`, whose renders in several transfer modes come from `pictures`."""

    live = False
    audio = None

    def __init__(self, run: LoadedRun, driver_root: Path, options: DrivingOptions, fps: float = 25.0,
                 max_frames: int | None = None, pictures: bool = True):
        if options.camera not in ("avatar", "driver"):
            raise OptionError(f"--camera must be avatar or driver, got {options.camera!r}")
        self.run, self.options, self.fps, self.max_frames, self.show_pictures = run, options, fps, max_frames, pictures
        self.frames = frames = RunFrames(run)
        self.device = frames.device
        self.subject = open_driver(driver_root, run)
        self.row_of = {t: i for i, t in enumerate(self.subject.timesteps)}
        self._params: dict[str, dict[str, Tensor]] = {}
        self.params(options.transfer)  # the neutral frames checked before any work
        self.dataset = HeadAvatarDataset(self.subject, options.driver_split, DataConfig(cache="none"), check_head=False)
        if len(self.dataset) == 0:
            raise OptionError(f"--driver-split {options.driver_split}: the driver has no frames in this split")
        self.resolution = options.resolution or run.info.resolution
        self.fixed_camera = self._avatar_camera(frames) if options.camera == "avatar" else None
        self.background = run_background(run).to(self.device)

    def _avatar_camera(self, frames: RunFrames):
        """The camera of the avatar's neutral frame (its first frame for 'first' and 'mean') at the renders' size."""
        run = self.run
        avatar_root = Path(self.options.data) if self.options.data is not None else run.info.data_root
        if not avatar_root.is_dir():
            raise RunError(f"{run.info.run_dir}: its dataset folder {avatar_root} is not found (the camera comes from "
                           "it); pass --data DIR, or --camera driver")
        neutral = self.options.avatar_neutral
        camera_timestep = frames.timesteps[0] if neutral in ("first", "mean") else int(neutral)
        return record_camera(open_subject(avatar_root), camera_timestep, self.resolution)

    def params(self, mode: TransferMode) -> dict[str, Tensor]:
        """The avatar's per-frame parameters [T, ...] driven in transfer `mode` (computed once per mode)."""
        if mode not in self._params:
            options = self.options
            self._params[mode] = subject_params(self.run, self.frames, self.subject, mode, options.driver_neutral,
                                                options.avatar_neutral, options.camera == "driver")
        return self._params[mode]

    def camera(self, item: dict):
        if self.fixed_camera is not None:
            return self.fixed_camera
        camera = item_camera(item)
        resolution = self.resolution
        if resolution is not None and max(camera.width, camera.height) > resolution:
            camera = camera.resized(resolution)
        return camera

    def __len__(self) -> int:
        return len(evenly_spaced(len(self.dataset), self.max_frames))

    def __iter__(self) -> Iterator[AnimationFrame]:
        for index, row in enumerate(evenly_spaced(len(self.dataset), self.max_frames)):
            yield self.frame(index, self.dataset[row])

    def frame(self, index: int, item: dict, mode: TransferMode | None = None) -> AnimationFrame:
        """The output frame `index` of the driver's dataset item (default: the options' transfer mode)."""
        params = self.params(mode or self.options.transfer)
        timestep = int(item["timestep"])
        return AnimationFrame(index, frame_of(params, self.row_of[timestep]), None,
                              None if self.fixed_camera is not None else self.camera(item),
                              to_uint8(driver_picture(item)) if self.show_pictures else None, timestep)

    def close(self) -> None:
        pass

    @torch.no_grad()
    def render(self, item: dict, mode: TransferMode | None = None) -> Tensor:
        """rgb [H, W, 3] in [0, 1]: the avatar driven by the driver's dataset item (default: the options' mode)."""
        params = self.params(mode or self.options.transfer)
        return render_params(self.run, frame_of(params, self.row_of[item["timestep"]]), self.camera(item), None,
                             self.background, self.options.backend)

    def pictures(self, modes: Sequence[str], max_frames: int | None = None) -> Iterator[DrivenPicture]:
        """(driver timestep, driver picture uint8, {mode: render uint8}) of `max_frames` driver frames spread evenly
        (all by default), each rendered in every transfer mode of `modes`: what `eval --driver` scores."""
        for index in evenly_spaced(len(self.dataset), max_frames):
            item = self.dataset[index]
            yield (int(item["timestep"]), to_uint8(driver_picture(item)),
                   {mode: to_uint8(self.render(item, mode)) for mode in modes})


__all__ = ["DrivenAvatar", "DriverMotion", "DrivingOptions", "driven_clip", "driver_picture", "frame_of",
           "open_driver"]
