"""What a training run holds: TrainingData (fixed during the run: dataset, head model, parts, scene extent, device)
and TrainingState (what changes: the avatar, the mouth deformer, per-frame parameters, optimizers, densification
statistics, APS), and how a new run builds them. train/checkpoint.py saves and restores a TrainingState."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from geoavatar.avatar import APSState, GaussianAvatar, MouthDeformer, gaussian_param_groups, posed_head
from geoavatar.avatar import densify as densify_ops
from geoavatar.avatar.colour_init import face_colours
from geoavatar.avatar.hair_motion import head_pose_codes
from geoavatar.avatar.model import rgb_to_sh_dc
from geoavatar.config import TrainConfig
from geoavatar.data import DataConfig, DatasetError, HeadAvatarDataset, open_subject
from geoavatar.data.splits import evenly_spaced
from geoavatar.data.subject import Subject
from geoavatar.geometry import camera_centre
from geoavatar.head.regions import face_parts
from geoavatar.runtime import resolve_device
from geoavatar.train.checkpoint import load_head_for
from geoavatar.train.frame_params import FrameParams, RowAdam
from geoavatar.train.options import RunOptions
from geoavatar.train.randomness import seed_everything

MLP_ADAM_EPS = 1e-8  # the mouth MLPs use Adam's usual eps; GaussianAvatars' 1e-15 is for the Gaussians
INIT_COLOUR_FRAMES = 32  # training frames, evenly spread, that model.init_colour = "images" reads


@dataclass
class TrainingData:
    """Everything fixed during a run: data, head model, partition, scene extent, device."""

    subject: Subject
    train_set: HeadAvatarDataset
    val_set: HeadAvatarDataset | None
    head: torch.nn.Module  # HeadModel on the device
    part_of_face: Tensor  # [F] APS part per face (-1 mouth)
    part_names: list[str]
    extent: float
    num_frames: int  # time normaliser of gamma(T): frames of the video
    device: torch.device
    backend: str
    data_config: DataConfig
    warp_faces: Tensor | None = None  # [F] bool on the device: faces of warped_view.parts (None: the loss is off)

    def dataset_record(self) -> dict:
        split = self.train_set.split
        return {
            "root": str(self.subject.root),
            "head_model": self.subject.head_model,
            "background": [float(c) for c in self.train_set.background],
            "resolution": self.data_config.resolution,
            "test_frames": self.data_config.test_frames,
            "timesteps": {"all": list(self.subject.timesteps), "train": list(split.train),
                          "val": list(split.val), "test": list(split.test)},
        }


@dataclass
class TrainingState:
    """Everything that changes during a run."""

    avatar: GaussianAvatar
    deformer: MouthDeformer | None
    frames: FrameParams
    optimizers: dict[str, torch.optim.Optimizer | None]
    stats: dict[str, Tensor]  # densification statistics {grad2d, count, max_radii} [N]
    aps: APSState
    face_sets: Tensor  # [F] regulariser set of every face
    generator: torch.Generator  # densification (split) samples
    step: int = 0


def open_training_data(options: RunOptions, config: TrainConfig) -> TrainingData:
    """Open the dataset and the head model it belongs to; DatasetError / ValueError on bad input."""
    device = resolve_device(options.device)
    subject = open_subject(options.data)
    data_config = DataConfig(resolution=options.resolution, test_frames=options.test_frames)
    head_options = {"flame_dir": options.flame_dir} if options.flame_dir is not None else {}
    train_set = HeadAvatarDataset(subject, "train", data_config, head_options=head_options)
    if len(train_set) == 0:
        raise DatasetError(f"{subject.root}: the training split is empty (every frame is a test frame?)")
    val_set = HeadAvatarDataset(subject, "val", data_config, check_head=False)
    head = load_head_for(subject.head_model, config.model.mouth, options.flame_dir).to(device)
    # APS needs the parts, and so does the warped view whatever the face sets (face_parts: ValueError without them)
    parts = face_parts(head.data) if config.model.face_sets == "aps" or config.warped_view.weight > 0 else None
    if config.model.face_sets == "aps":
        part_of_face, part_names = torch.as_tensor(parts.part_of_face), list(parts.part_names)
    else:
        part_of_face, part_names = torch.zeros(head.num_faces, dtype=torch.long), []
    warp_faces = None
    if config.warped_view.weight > 0:
        wanted = [parts.part_names.index(name) for name in config.warped_view.parts]
        warp_faces = torch.from_numpy(np.isin(parts.part_of_face, wanted)).to(device)
    viewmats = torch.stack([torch.from_numpy(f.viewmat).double() for f in train_set.frames])  # [M, 4, 4]
    extent = densify_ops.scene_extent(camera_centre(viewmats).float(), config.densify.min_scene_extent)
    return TrainingData(
        subject=subject, train_set=train_set, val_set=val_set if len(val_set) else None, head=head,
        part_of_face=part_of_face, part_names=part_names, extent=extent,
        num_frames=max(subject.timesteps) + 1, device=device,
        backend=options.backend, data_config=data_config, warp_faces=warp_faces,
    )


def tracking_optimizer(frames: FrameParams, lr, saved: dict | None = None) -> torch.optim.Optimizer | None:
    """The refinement's optimiser: RowAdam, one step per visit of a frame; torch's Adam over the table when `saved`
    (a checkpoint's state of it) was written by one, a run trained before issue #27, which resumes as it was trained."""
    if not frames.refine:
        return None
    states = (saved or {}).get("state") or {}
    if states and not any("row_steps" in state for state in states.values()):
        return torch.optim.Adam(frames.param_groups(lr), lr=0.0, eps=lr.adam_eps, fused=True)
    return RowAdam(frames.param_groups(lr), lr=0.0)


def build_optimizers(
    avatar: GaussianAvatar, deformer: MouthDeformer | None, frames: FrameParams, config: TrainConfig, extent: float,
    saved: dict | None = None,
) -> dict[str, torch.optim.Optimizer | None]:
    """The run's optimisers; `saved`: a checkpoint's optimiser states by name (which tracking optimiser to rebuild)."""
    lr = config.lr
    # fused: one kernel per tensor (CPU and CUDA), a third of the per-op version's time at 100k Gaussians
    gaussians = torch.optim.Adam(gaussian_param_groups(avatar.params, lr, extent), lr=0.0, eps=lr.adam_eps, fused=True)
    tracking = tracking_optimizer(frames, lr, (saved or {}).get("tracking"))
    mouth = (torch.optim.Adam(deformer.parameters(), lr=lr.mouth_deform, eps=MLP_ADAM_EPS, fused=True)
             if deformer is not None else None)
    return {"gaussians": gaussians, "tracking": tracking, "deformer": mouth}


def new_state(data: TrainingData, config: TrainConfig, seed: int) -> TrainingState:
    """A fresh avatar (one Gaussian per face), deformer, per-frame parameters and optimizers."""
    seed_everything(seed)
    device = data.device
    avatar = GaussianAvatar.for_model(data.head, config.model).to(device)
    deformer = None
    if config.model.mouth_deform.enabled:
        deformer = MouthDeformer.for_head(data.head, data.num_frames, config.model.mouth_deform).to(device)
    frames = FrameParams(data.subject.params, refine=config.refine_tracking).to(device)
    if config.model.init_colour == "images":
        colour, _ = face_colours(data.head.faces, training_views(data, frames))  # [F, 3]
        with torch.no_grad():
            avatar.params["f_dc"].copy_(rgb_to_sh_dc(colour.to(device))[avatar.binding])
    if avatar.follows_head:  # the box of the training frames' head pose codes, as tracked
        rows = [frame.row for frame in data.train_set.frames]
        avatar.set_pose_range(head_pose_codes(frames.values["rotation"][rows], frames.values["neck_pose"][rows]))
    aps = APSState(part_names=data.part_names)
    generator = torch.Generator(device=device)
    generator.manual_seed(seed)
    return TrainingState(
        avatar=avatar, deformer=deformer, frames=frames,
        optimizers=build_optimizers(avatar, deformer, frames, config, data.extent),
        stats=densify_ops.new_state(avatar.num_gaussians, device),
        aps=aps, face_sets=aps.face_sets(data.part_of_face, config.model.face_sets,
                                    mouth_set=config.model.mouth == "geoavatar").to(device),
        generator=generator,
    )


@torch.no_grad()
def training_views(data: TrainingData, frames: FrameParams, count: int = INIT_COLOUR_FRAMES):
    """(vertices [V, 3], image, mask, viewmat, K) of evenly spread training frames, posed by their parameters."""
    for index in evenly_spaced(len(data.train_set), count):
        item = data.train_set[index]
        vertices = posed_head(data.head, frames(item["row"])).vertices[0]  # [V, 3]
        yield vertices, item["image"], item["mask"], item["viewmat"], item["K"]


__all__ = ["INIT_COLOUR_FRAMES", "MLP_ADAM_EPS", "TrainingData", "TrainingState", "build_optimizers", "new_state",
           "open_training_data", "tracking_optimizer", "training_views"]
