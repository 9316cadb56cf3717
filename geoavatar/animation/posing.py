"""The one posing path of every command that shows a trained run (moved here from apps/common.py, which re-exports it).

    params, T = RunFrames(run).params(timestep)       # train/run_frames.py: the parameters and the T rule
    rgb = render_params(run, params, camera, T)       # avatar.render_avatar on the run's background, clamped
    vertices = posed_head_vertices(run, params, T)    # [V, 3] what the browser player places the splats on
    posed = PosedFrame(run, frame, gaussians=True)    # one AnimationFrame posed once for all of play's sinks

The T rule (the mouth deformer's time input gamma(T)) lives with RunFrames: a training timestep renders with its own T
and the run's refined parameters; any other frame (test frames, a driver's frames, edited parameters) with T = 0.
"""

from __future__ import annotations

import torch
from torch import Tensor

from geoavatar.animation.frames import AnimationFrame
from geoavatar.avatar import GlobalGaussians, PosedAvatar, pose_avatar, posed_head, render_avatar
from geoavatar.avatar.hair_motion import head_pose_code
from geoavatar.data import DatasetError
from geoavatar.data.subject import Subject
from geoavatar.head.params import HeadParams
from geoavatar.head.regions import skull_centre
from geoavatar.render.camera import Camera
from geoavatar.train.checkpoint import LoadedRun


def record_camera(subject: Subject, timestep: int, resolution: int | None) -> Camera:
    """The camera of `timestep` in a subject (its first camera), at `resolution` (longer side; None: stored)."""
    frames = subject.frames_of([timestep])
    if not frames:
        raise DatasetError(f"{subject.root}: has no frame with timestep {timestep}")
    frame = frames[0]
    camera = Camera(torch.from_numpy(frame.viewmat).float(), torch.from_numpy(frame.K).float(), frame.width, frame.height)
    if resolution is not None and resolution < max(frame.width, frame.height):
        camera = camera.resized(resolution)
    return camera


def run_background(run: LoadedRun) -> Tensor:
    """[3] the background colour the run was trained on."""
    return torch.tensor(run.info.background, dtype=torch.float32)


def posed_head_vertices(run: LoadedRun, params: HeadParams, timestep: int | None = None) -> Tensor:
    """[V, 3] the run's head model posed by `params`, with the mouth deformer's offsets."""
    return posed_head(run.head, params, run.deformer, timestep).vertices[0]


def browser_pose_code(run: LoadedRun, params: HeadParams) -> Tensor | None:
    """[6] the frame's head pose code when the run's hair follows the head's turn (the browser player moves the hair
    by it, web/pack.py), clamped to the training frames' range as the avatar clamps it, else None."""
    return run.avatar.clamp_pose_code(head_pose_code(params)) if run.avatar.follows_head else None


def pose_gaussians(run: LoadedRun, params: HeadParams, timestep: int | None = None) -> GlobalGaussians:
    """Head model (with the mouth deformer) posed by `params`, then the avatar's local -> global."""
    return pose_avatar(run.avatar, run.head, params, timestep, run.deformer).gaussians


@torch.no_grad()
def render_params(run: LoadedRun, params: HeadParams, camera: Camera, timestep: int | None = None,
                  background: Tensor | None = None, backend: str = "auto") -> Tensor:
    """The avatar posed by `params`, seen by `camera`: rgb [H, W, 3] in [0, 1] on the run's background."""
    background = run_background(run) if background is None else background
    frame = render_avatar(run.avatar, run.head, params, camera, timestep, run.deformer, background, backend)
    return frame.result.rgb.clamp(0.0, 1.0)


def head_centre(run: LoadedRun, params: HeadParams) -> Tensor:
    """[3] centre of the posed head (head.regions.skull_centre: the skin without the neck and the mouth),
    what an orbit turns about."""
    return skull_centre(posed_head(run.head, params, None, None).vertices[0], run.head)


class PosedFrame:
    """An AnimationFrame posed once for every sink of a play: with `gaussians` the whole avatar (avatar.pose_avatar,
    for sinks that rasterize), else only the head's vertices, posed when a sink first asks for them (a sink that
    needs neither poses nothing)."""

    def __init__(self, run: LoadedRun, frame: AnimationFrame, gaussians: bool):
        self.run, self.frame = run, frame
        self.avatar: PosedAvatar | None = (pose_avatar(run.avatar, run.head, frame.params, frame.T, run.deformer)
                                           if gaussians else None)
        self._vertices: Tensor | None = None

    @property
    def gaussians(self) -> GlobalGaussians:
        if self.avatar is None:
            raise ValueError("PosedFrame: posed without Gaussians (no sink of this play rasterizes)")
        return self.avatar.gaussians

    @property
    def vertices(self) -> Tensor:
        """[V, 3] the posed head with the mouth deformation."""
        if self.avatar is not None:
            return self.avatar.vertices
        if self._vertices is None:
            self._vertices = posed_head_vertices(self.run, self.frame.params, self.frame.T)
        return self._vertices


__all__ = ["PosedFrame", "browser_pose_code", "head_centre", "pose_gaussians", "posed_head_vertices", "record_camera",
           "render_params", "run_background"]
