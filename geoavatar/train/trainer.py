"""The training loop of GeoAvatar (`geoavatar train`).

One step (GaussianAvatars' loop with GeoAvatar's additions; steps are numbered 1..steps):

    frame       the next frame of a seeded random permutation of the training frames (one per epoch)
    params      its tracked head parameters; with refine_tracking the per-timestep expression, pose and
                translation are learnable tensors (FrameParams), as GaussianAvatars fine-tunes them
    render      avatar.render_avatar: posed_head(head, params, MouthDeformer, T) (the deformer only when
                the preset enables it) -> avatar(vertices): local -> global -> rasterize
                on the dataset's background colour (native cpu kernel on CPU, gsplat on CUDA)
    target      image * mask + background * (1 - mask): pixels outside the foreground mask become the
                background colour, as GaussianAvatars does, so the avatar never learns clothing/backdrop;
                the background is the dataset's, or with TrainConfig.background = "random" a random colour
                per step (step_background), the same one behind the render
    loss        avatar_loss: L_rgb + L_reg (+ L_angle, + GaussianAvatars' scale loss) (+ mesh_prior_losses: rendered
                weight behind / outside the posed mesh, TrainConfig.mesh_prior; + turned_view_term: the frame warped
                to a turned camera, TrainConfig.warped_view; both off by default); NaN/Inf stops the run
                (the terms are read back in one transfer per step; value checks that wait for the device,
                rasterize's inputs and NaN/Inf in the learned tensors, run every VALUE_CHECK_EVERY steps,
                on log steps and before every checkpoint)
    backward    then Adam steps (position lr decays log-linearly), then densification statistics from
                means2d.grad and densify/prune/opacity reset on the (scaled) schedule, then APS at aps_step
                (3DGS densifies before the Adam step and so skips that step's update; see train_step)

Every step-based milestone comes from `TrainConfig.scaled_to(steps)`, so a short run keeps the paper's
proportions (APS at half the run, densification every 1 % from 5 %, opacity reset every 30 %).

State that makes a resumed run continue exactly where the uninterrupted one would be: parameters
and binding, the three Adam optimizers (Gaussians, tracking refinement, mouth MLPs), densification
statistics, APS decision and face sets, refined per-frame parameters, the step, and RNG states
(torch, CUDA, numpy, python, the densification generator). Frame order is a pure function of
(seed, epoch), so it needs no state. Validation renders use no randomness and change nothing.
"""

from __future__ import annotations

import json
import math
import random
import signal
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Literal

import numpy as np
import torch
from torch import Tensor

from geoavatar.avatar import APSState, GaussianAvatar, MouthDeformer, gaussian_param_groups, position_lr, render_avatar
from geoavatar.avatar import densify as densify_ops
from geoavatar.avatar import posed_head
from geoavatar.avatar.colour_init import face_colours
from geoavatar.avatar.model import rgb_to_sh_dc
from geoavatar.config import PresetName, TrainConfig
from geoavatar.data import DataConfig, DatasetError, HeadAvatarDataset, open_subject
from geoavatar.data.dataset import item_camera
from geoavatar.data.splits import evenly_spaced
from geoavatar.data.subject import Subject
from geoavatar.errors import GeoAvatarError
from geoavatar.head.regions import face_parts
from geoavatar.io.atomic import atomic_write_json, atomic_write_png
from geoavatar.render import composite_target
from geoavatar.runtime import resolve_device
from geoavatar.train import checkpoint as ckpt
from geoavatar.train.frame_params import FrameParams, RowAdam
from geoavatar.train.losses import avatar_loss
from geoavatar.train.mesh_prior import mesh_prior_losses
from geoavatar.train.warped_view import turned_view_term

OPTIMIZER_NAMES = ("gaussians", "tracking", "deformer")
MLP_ADAM_EPS = 1e-8  # the mouth MLPs use Adam's usual eps; GaussianAvatars' 1e-15 is for the Gaussians
# Steps between the value checks that wait for the device (rasterize's inputs, NaN/Inf in the learned
# tensors); they also run on a run's first step and before every checkpoint. The loss is checked every step.
VALUE_CHECK_EVERY = 50


class TrainingDiverged(GeoAvatarError, RuntimeError):
    """The loss became NaN or infinite; the message says where and which checkpoint is intact."""


@dataclass
class RunOptions:
    """How a run is executed (not what is learned: that is TrainConfig). `geoavatar train` parses these
    fields as its options (--out, --data, --preset, ...); the comments are their help."""

    # Run folder to create (or to continue with --resume / --extend).
    out: Path
    # Dataset folder (VHAP / GaussianAvatars layout, e.g. from `geoavatar synth`, or INSTA); required for
    # a new run, with --resume the run's own unless given (a moved dataset).
    data: Path | None = None
    # Ablation preset of the paper (Tables 3, 6): A = GaussianAvatars (SH 0) ... E = GeoAvatar; its values
    # are the defaults of the --config.* options (default E for a new run; with --resume the run's own).
    preset: PresetName | None = None
    # Downscale images so that the longer side has this many pixels (default: as stored).
    resolution: int | None = None
    # Seed of frame order, initialisation and densification samples.
    seed: int = 0
    # auto (CUDA when available, else CPU), cpu, cuda or cuda:N.
    device: str = "auto"
    # Rasterizer: auto (gsplat on CUDA, the native cpu kernel on CPU when it builds, else torch), cpu,
    # torch or gsplat.
    backend: Literal["auto", "cpu", "torch", "gsplat"] = "auto"
    # Save a validation image every this many steps (default: 5 % of the run).
    val_every: int | None = None
    # Write OUT/checkpoints/last.pt every this many steps (default: 5 % of the run).
    ckpt_every: int | None = None
    # Write a loss line to OUT/train.log every this many steps (default: 0.5 % of the run).
    log_every: int | None = None
    # Hold out the last N frames as the test set (default: the dataset's split files, else the INSTA rule:
    # last 350, or the last 25 % of a short video).
    test_frames: int | None = None
    # Folder with your FLAME model files (datasets tracked with FLAME only).
    flame_dir: Path | None = None
    # Show progress bars.
    progress: bool = True

    def to_json(self) -> dict:
        out = asdict(self)
        for key in ("data", "out", "flame_dir"):
            out[key] = None if out[key] is None else str(out[key])
        return out


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


@dataclass
class StepReport:
    losses: dict[str, float]
    psnr: float
    num_gaussians: int
    densified: dict[str, int] | None = None
    aps_ran: bool = False


@dataclass
class TrainResult:
    run_dir: Path
    status: str  # "finished" | "interrupted"
    step: int
    steps: int
    seconds: float
    steps_per_second: float
    last: StepReport | None = None
    val_psnr: float | None = None
    history: list[dict] = field(default_factory=list)  # logged steps: step, loss, psnr, gaussians


# --- set-up -----------------------------------------------------------------------------------


def camera_centres(dataset: HeadAvatarDataset) -> Tensor:
    """[C, 3] world positions of the cameras of a split (C = -R^T t of each viewmat)."""
    viewmats = torch.stack([torch.from_numpy(f.viewmat).double() for f in dataset.frames])  # [M, 4, 4]
    rot, trans = viewmats[:, :3, :3], viewmats[:, :3, 3]
    return -(rot.transpose(1, 2) @ trans[..., None]).squeeze(-1).float()


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
    head = ckpt.load_head_for(subject.head_model, config.model.mouth, options.flame_dir).to(device)
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
    extent = densify_ops.scene_extent(camera_centres(train_set), config.densify.min_scene_extent)
    return TrainingData(
        subject=subject, train_set=train_set, val_set=val_set if len(val_set) else None, head=head,
        part_of_face=part_of_face, part_names=part_names, extent=extent,
        num_frames=max(subject.timesteps) + 1, device=device,
        backend=options.backend, data_config=data_config, warp_faces=warp_faces,
    )


def build_optimizers(
    avatar: GaussianAvatar, deformer: MouthDeformer | None, frames: FrameParams, config: TrainConfig, extent: float
) -> dict[str, torch.optim.Optimizer | None]:
    lr = config.lr
    # fused: one kernel per tensor (CPU and CUDA), a third of the per-op version's time at 100k Gaussians
    gaussians = torch.optim.Adam(gaussian_param_groups(avatar.params, lr, extent), lr=0.0, eps=lr.adam_eps, fused=True)
    tracking = None
    if frames.refine and config.refine_optimizer == "per-frame":
        tracking = RowAdam(frames.param_groups(lr), lr=0.0)
    elif frames.refine:
        tracking = torch.optim.Adam(frames.param_groups(lr), lr=0.0, eps=lr.adam_eps, fused=True)
    mouth = (torch.optim.Adam(deformer.parameters(), lr=lr.mouth_deform, eps=MLP_ADAM_EPS, fused=True)
             if deformer is not None else None)
    return {"gaussians": gaussians, "tracking": tracking, "deformer": mouth}


def new_state(data: TrainingData, config: TrainConfig, seed: int) -> TrainingState:
    """A fresh avatar (one Gaussian per face), deformer, per-frame parameters and optimizers."""
    seed_everything(seed)
    device = data.device
    avatar = GaussianAvatar(data.head.faces.cpu(), config.model.init_opacity, config.model.normal_shading).to(device)
    deformer = None
    if config.model.mouth_deform.enabled:
        deformer = MouthDeformer.for_head(data.head, data.num_frames, config.model.mouth_deform).to(device)
    frames = FrameParams(data.subject.params, refine=config.refine_tracking).to(device)
    if config.model.init_colour == "images":
        colour, _ = face_colours(data.head.faces, training_views(data, frames))  # [F, 3]
        with torch.no_grad():
            avatar.params["f_dc"].copy_(rgb_to_sh_dc(colour.to(device))[avatar.binding])
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


INIT_COLOUR_FRAMES = 32  # training frames, evenly spread, that model.init_colour = "images" reads


@torch.no_grad()
def training_views(data: TrainingData, frames: FrameParams, count: int = INIT_COLOUR_FRAMES):
    """(vertices [V, 3], image, mask, viewmat, K) of evenly spread training frames, posed by their parameters."""
    for index in evenly_spaced(len(data.train_set), count):
        item = data.train_set[index]
        vertices = posed_head(data.head, frames(item["row"])).vertices[0]  # [V, 3]
        yield vertices, item["image"], item["mask"], item["viewmat"], item["K"]


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


# --- RNG state as checkpoint-safe values --------------------------------------------------------


def rng_state(generator: torch.Generator) -> dict:
    kind, keys, pos, has_gauss, cached = np.random.get_state()
    version, internal, gauss_next = random.getstate()
    return {
        "torch": torch.get_rng_state(),
        "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
        "numpy": {"kind": str(kind), "keys": torch.from_numpy(np.asarray(keys, dtype=np.int64)), "pos": int(pos),
                  "has_gauss": int(has_gauss), "cached": float(cached)},
        "python": {"version": int(version), "internal": [int(v) for v in internal], "gauss_next": gauss_next},
        "generator": generator.get_state(),
    }


def restore_rng(state: dict, generator: torch.Generator) -> None:
    torch.set_rng_state(state["torch"])
    if torch.cuda.is_available() and len(state["cuda"]) == torch.cuda.device_count():
        torch.cuda.set_rng_state_all(state["cuda"])
    n = state["numpy"]
    np.random.set_state((n["kind"], n["keys"].numpy().astype(np.uint32), n["pos"], n["has_gauss"], n["cached"]))
    p = state["python"]
    random.setstate((p["version"], tuple(p["internal"]), p["gauss_next"]))
    generator.set_state(state["generator"])


# --- checkpoints --------------------------------------------------------------------------------


def state_payload(state: TrainingState, data: TrainingData, config: TrainConfig, options: RunOptions) -> dict:
    import json

    return {
        "step": int(state.step),
        "config": json.dumps(ckpt.config_to_dict(config)),
        "run": json.dumps(options.to_json()),
        "dataset": data.dataset_record(),
        "avatar": state.avatar.state_dict(),
        "deformer": state.deformer.state_dict() if state.deformer is not None else None,
        "num_frames": int(data.num_frames),
        "frame_params": state.frames.as_dict(),
        "refine_tracking": bool(state.frames.refine),
        "optimizers": {name: (opt.state_dict() if opt is not None else None) for name, opt in state.optimizers.items()},
        "densify_stats": {k: v.detach().clone() for k, v in state.stats.items()},
        "aps": state.aps.to_dict(),
        "face_sets": state.face_sets.detach().cpu().clone(),
        "extent": float(data.extent),
        "rng": rng_state(state.generator),
    }


def restore_state(payload: dict, data: TrainingData, config: TrainConfig, where: str) -> TrainingState:
    """The TrainingState saved in `payload` (a loaded checkpoint), on data.device."""
    device = data.device
    try:
        avatar = GaussianAvatar(data.head.faces.cpu(), config.model.init_opacity, config.model.normal_shading)
        avatar.load_state_dict(payload["avatar"])
        avatar = avatar.to(device)
        deformer = None
        if config.model.mouth_deform.enabled:
            if payload.get("deformer") is None:
                raise ckpt.RunError(f"{where}: the config enables the mouth deformer but the checkpoint has none")
            deformer = MouthDeformer.for_head(data.head, int(payload["num_frames"]), config.model.mouth_deform)
            deformer.load_state_dict(payload["deformer"])
            deformer = deformer.to(device)
        frames = FrameParams(payload["frame_params"], refine=bool(payload["refine_tracking"])).to(device)
        if frames.num_rows != data.subject.num_timesteps:
            raise ckpt.RunError(f"{where}: the checkpoint has parameters of {frames.num_rows} frames, the dataset "
                                f"{data.subject.root} has {data.subject.num_timesteps}")
        optimizers = build_optimizers(avatar, deformer, frames, config, float(payload["extent"]))
        for name, opt in optimizers.items():
            saved = payload["optimizers"].get(name)
            if (opt is None) != (saved is None):
                raise ckpt.RunError(f"{where}: optimizer '{name}' does not match the configuration")
            if opt is not None:
                opt.load_state_dict(saved)
        stats = {k: v.to(device) for k, v in payload["densify_stats"].items()}
        aps = APSState.from_dict(payload["aps"])
        generator = torch.Generator(device=device)
        restore_rng(payload["rng"], generator)
    except KeyError as err:
        raise ckpt.RunError(f"{where}: checkpoint lacks the entry {err}") from err
    data.extent = float(payload["extent"])
    return TrainingState(
        avatar=avatar, deformer=deformer, frames=frames, optimizers=optimizers, stats=stats, aps=aps,
        face_sets=payload["face_sets"].to(device), generator=generator, step=int(payload["step"]),
    )


# --- one frame ----------------------------------------------------------------------------------


def frame_index(step: int, count: int, seed: int) -> int:
    """Training frame of `step` (1-based): a seeded permutation per epoch, stateless for resuming."""
    epoch, position = divmod(step - 1, count)
    generator = torch.Generator().manual_seed(seed * 1_000_003 + epoch)
    return int(torch.randperm(count, generator=generator)[position])


def step_background(dataset_background: Tensor, mode: str, seed: int, step: int) -> Tensor:
    """[3] the training background of `step` (TrainConfig.background): the dataset's colour, or a uniform
    random colour that is a pure function of (seed, step), so a resumed run draws the same ones."""
    if mode == "dataset":
        return dataset_background
    generator = torch.Generator().manual_seed(seed * 1_000_003 + 7_919 * step + 1)
    return torch.rand(3, generator=generator).to(dataset_background)


def psnr_of(mse: float) -> float:
    return float("inf") if mse <= 0 else -10.0 * math.log10(mse)


def _item_to(item: dict, device: torch.device) -> dict:
    return {k: (v.to(device) if isinstance(v, Tensor) else v) for k, v in item.items()}


def train_step(data: TrainingData, state: TrainingState, config: TrainConfig, step: int, seed: int,
               check_values: bool | None = None) -> StepReport:
    """One optimisation step (numbered `step`, 1-based). Raises TrainingDiverged on a NaN/Inf loss.

    The step waits for the device once, to read the loss terms back (and stop on a NaN/Inf total
    before it reaches the parameters); `check_values` (default: every VALUE_CHECK_EVERY steps) adds
    rasterize's input value checks and the NaN/Inf check of the learned tensors."""
    if check_values is None:
        check_values = step % VALUE_CHECK_EVERY == 0
    item = _item_to(data.train_set[frame_index(step, len(data.train_set), seed)], data.device)
    background = step_background(item["background"], config.background, seed, step)  # [3]
    target = composite_target(item["image"], item["mask"], background)
    params = state.frames(item["row"])
    camera = item_camera(item)
    frame = render_avatar(state.avatar, data.head, params, camera, item["timestep"], state.deformer,
                          background, data.backend, check_values=check_values)
    result, g = frame.result, frame.gaussians
    p = state.avatar.params
    losses = avatar_loss(result.rgb, target, p["means"], p["scales"], state.avatar.binding, state.face_sets,
                         config.loss, visible=result.visible)
    prior = mesh_prior_losses(g, frame.vertices, data.head, camera, config.mesh_prior, seed, step, data.backend)
    if config.warped_view.active(step):
        prior["warped_view"] = turned_view_term(g, frame.vertices, data.head, data.warp_faces, item, camera,
                                                background, config.warped_view, seed, step, data.backend)
    if prior:  # logged by name before the total
        total = losses.pop("total") + sum(prior.values())
        losses = {**losses, **prior, "total": total}
    total = losses["total"]
    with torch.no_grad():
        mse = ((result.rgb.detach() - target) ** 2).mean()
    # The one read-back of the step: every loss term and the MSE for the PSNR, in one transfer.
    values = torch.stack([v.detach().reshape(()) for v in losses.values()] + [mse.reshape(())]).tolist()
    reported, mse_value = dict(zip(losses, values[:-1])), values[-1]
    if not math.isfinite(reported["total"]):
        terms = ", ".join(f"{k}={v:.4g}" for k, v in reported.items())
        raise TrainingDiverged(f"step {step}: the loss is not finite ({terms})")

    for opt in state.optimizers.values():
        if opt is not None:
            opt.zero_grad(set_to_none=True)
    total.backward()

    gaussians_opt = state.optimizers["gaussians"]
    for group in gaussians_opt.param_groups:
        if group["name"] == "means":
            group["lr"] = position_lr(step, config.lr, data.extent)
    for opt in state.optimizers.values():
        if opt is not None:
            opt.step()
    # Densification after the Adam step (3DGS runs it before, and a densifying step then loses its
    # update: densify replaces the tensors, whose .grad is gone; immaterial every 2000 of 200k steps,
    # but a schedule scaled to a few hundred steps densifies every 1-2 steps and would freeze them).
    binding, densified = densify_ops.step_post_backward(
        p, [gaussians_opt], state.avatar.binding, state.stats, config.densify, step,
        g.frames.scale.detach(), data.extent, result.means2d.grad, result.visible, result.radii,
        item["width"], item["height"], state.generator,
    )
    state.avatar.binding = binding
    if check_values:
        _assert_finite(state, f"step {step}: after the optimizer step")

    aps_ran = False
    if config.model.face_sets == "aps" and not state.aps.done and step >= config.aps_step:
        state.aps.run(p["means"].detach(), state.avatar.binding, data.part_of_face, step)
        state.face_sets = state.aps.face_sets(data.part_of_face, "aps").to(data.device)
        aps_ran = True
    state.step = step

    return StepReport(reported, psnr_of(mse_value), state.avatar.num_gaussians, densified, aps_ran)


@torch.no_grad()
def validation_image(data: TrainingData, state: TrainingState) -> tuple[np.ndarray, float] | None:
    """Ground truth | render for each validation frame, stacked; and their mean PSNR (training frames)."""
    if data.val_set is None:
        return None
    rows, psnrs = [], []
    for index in range(len(data.val_set)):
        item = _item_to(data.val_set[index], data.device)
        target = composite_target(item["image"], item["mask"], item["background"])
        result = render_avatar(state.avatar, data.head, state.frames(item["row"]), item_camera(item), item["timestep"],
                               state.deformer, item["background"], data.backend).result
        rgb = result.rgb.clamp(0.0, 1.0)
        psnrs.append(psnr_of(float(((rgb - target) ** 2).mean())))
        rows.append(torch.cat([target, rgb], dim=1))  # [H, 2W, 3]
    width = max(r.shape[1] for r in rows)
    rows = [torch.nn.functional.pad(r, (0, 0, 0, width - r.shape[1])) for r in rows]
    image = (torch.cat(rows, dim=0).cpu().numpy() * 255.0 + 0.5).astype(np.uint8)
    return image, float(np.mean(psnrs))


def save_png(path: Path, image: np.ndarray) -> None:
    atomic_write_png(path, image)


# --- the run ------------------------------------------------------------------------------------


class RunLog:
    """Appends timestamped lines to RUN/train.log (and mirrors them to TensorBoard when importable)."""

    def __init__(self, run_dir: Path, echo: Callable[[str], None] | None = None):
        self.path = run_dir / ckpt.LOG_FILE
        self.echo = echo
        self.tensorboard = None
        try:  # optional: only when the tensorboard package is installed
            from torch.utils.tensorboard import SummaryWriter

            self.tensorboard = SummaryWriter(str(run_dir / "tensorboard"))
        except Exception:  # noqa: BLE001 - not installed (the usual case): skip silently
            self.tensorboard = None

    def line(self, text: str, echo: bool = False) -> None:
        stamp = time.strftime("%Y-%m-%d %H:%M:%S")
        with open(self.path, "a", encoding="utf-8") as handle:
            handle.write(f"{stamp} {text}\n")
        if echo and self.echo is not None:
            self.echo(text)

    def scalars(self, step: int, values: dict[str, float]) -> None:
        if self.tensorboard is not None:
            for key, value in values.items():
                self.tensorboard.add_scalar(key, value, step)

    def close(self) -> None:
        if self.tensorboard is not None:
            self.tensorboard.close()


class _InterruptFlag:
    """First Ctrl-C (SIGINT) asks the loop to stop after the current step and save; a second one aborts."""

    def __init__(self):
        self.requested = False
        self._previous = None
        self._installed = False

    def __enter__(self) -> "_InterruptFlag":
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handle)
            self._installed = True
        return self

    def _handle(self, signum, frame) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True

    def __exit__(self, *exc) -> None:
        if self._installed:
            signal.signal(signal.SIGINT, self._previous)


def default_interval(steps: int, fraction: float) -> int:
    return max(1, int(round(steps * fraction)))


def _check_resume_config(saved: TrainConfig, requested: TrainConfig | None, where: str) -> None:
    if requested is None or requested == saved:
        return
    flat_saved, flat_req = _flatten(ckpt.config_to_dict(saved)), _flatten(ckpt.config_to_dict(requested))
    diffs = [f"{k}: run has {flat_saved.get(k)!r}, asked {flat_req.get(k)!r}"
             for k in sorted(set(flat_saved) | set(flat_req)) if flat_saved.get(k) != flat_req.get(k)]
    longer = ("; to train the run longer, use --extend N instead of --steps"
              if requested.steps != saved.steps else "")
    raise ckpt.RunError(f"{where}: --resume continues the run's own configuration, but the options ask for a "
                        f"different one ({'; '.join(diffs[:6])}). Resume without those options, or train into a new "
                        f"--out{longer}.")


def _flatten(data: dict, prefix: str = "") -> dict:
    out = {}
    for key, value in data.items():
        if isinstance(value, dict):
            out.update(_flatten(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def train(
    options: RunOptions,
    config: TrainConfig | None = None,
    resume: bool = False,
    callback: Callable[[int, TrainingState, StepReport], None] | None = None,
    extend: int = 0,
    record: dict | None = None,
) -> TrainResult:
    """Train (or resume) the run in options.out. Returns a TrainResult; raises TrainingDiverged,
    DatasetError / RunError / ValueError on bad input. `callback(step, state, report)` runs after each step.

    extend > 0 (implies resume): train the run `extend` steps longer, `TrainConfig.extended`: a finished run
    continues from its last step with every milestone where it was (no new densification or APS, the
    final position learning rate); the extended configuration is saved, so an interrupted extension
    resumes exactly with plain `resume`. `record`: what RUN/config.json notes besides the configuration
    (the command-line overrides, how the steps were chosen); kept in the checkpoint across resumes, and
    every extension is added to its "extensions"."""
    run_dir = Path(options.out)
    last_path = ckpt.run_checkpoint_path(run_dir, "last")
    payload = None
    if resume or extend:
        if not last_path.is_file():
            if extend:
                raise ckpt.RunError(f"{run_dir}: --extend continues a run, but there is none here "
                                    f"(no {ckpt.CHECKPOINT_DIR}/{ckpt.LAST_CHECKPOINT})")
            raise ckpt.RunError(f"{run_dir}: nothing to resume (no {ckpt.CHECKPOINT_DIR}/{ckpt.LAST_CHECKPOINT}); "
                                "start the run without --resume")
        payload = ckpt.load_checkpoint(last_path)
        saved = ckpt.config_from_json(payload["config"], f"{last_path} [config]")
        record = {**json.loads(payload.get("record", "{}")), **(record or {})}
        if extend:
            if config is not None:
                raise ValueError("train: extend continues the run's own configuration; pass config=None")
            config = saved.extended(extend)
            record["extensions"] = [*record.get("extensions", []), {
                "at_step": int(payload["step"]), "from_steps": saved.steps, "to_steps": config.steps}]
        else:
            _check_resume_config(saved, config, str(last_path))
            config = saved
        saved_options = json.loads(payload.get("run", "{}"))
        if options.resolution is None:
            options.resolution = saved_options.get("resolution")
        elif options.resolution != saved_options.get("resolution"):
            raise ckpt.RunError(f"{last_path}: the run trained at --resolution {saved_options.get('resolution')}, "
                                f"asked {options.resolution}; resume without --resolution")
        if options.data is None:
            if not saved_options.get("data"):
                raise ckpt.RunError(f"{last_path}: the run does not record its dataset; pass --data")
            options.data = Path(saved_options["data"])
        if options.test_frames is None:
            options.test_frames = saved_options.get("test_frames")
        options.seed = int(saved_options.get("seed", options.seed))
        options.preset = options.preset or saved_options.get("preset")
    else:
        if last_path.exists():
            raise ckpt.RunError(f"{run_dir}: already holds a run ({ckpt.CHECKPOINT_DIR}/{ckpt.LAST_CHECKPOINT}); pass "
                                "--resume to continue it, or choose a new --out")
        if config is None:
            raise ValueError("train: a TrainConfig is needed for a new run")
        record = dict(record or {})
    config = config.validate()
    record.setdefault("overrides", {})

    data = open_training_data(options, config)
    run_dir.mkdir(parents=True, exist_ok=True)
    if payload is not None:
        state = restore_state(payload, data, config, str(last_path))
    else:
        state = new_state(data, config, options.seed)
    atomic_write_json(run_dir / ckpt.CONFIG_FILE, {
        "preset": options.preset, "config": ckpt.config_to_dict(config), **record, "run": options.to_json(),
        "dataset": data.dataset_record(), "device": str(data.device),
    })

    steps = config.steps
    val_every = options.val_every or default_interval(steps, 0.05)
    ckpt_every = options.ckpt_every or default_interval(steps, 0.05)
    log_every = options.log_every or default_interval(steps, 0.005)

    from tqdm.auto import tqdm

    bar = tqdm(total=steps, initial=state.step, disable=not options.progress, dynamic_ncols=True, unit="step")
    log = RunLog(run_dir, echo=bar.write)
    log.line(f"{'resume' if payload is not None else 'start'} at step {state.step}/{steps}: data {data.subject.root} "
             f"({len(data.train_set)} training frames), head {data.subject.head_model} + mouth {config.model.mouth}, "
             f"preset {options.preset}, device {data.device}, extent {data.extent:.3f}, seed {options.seed}")
    if record["overrides"]:
        log.line("overrides: " + ", ".join(f"{k}={v!r}" for k, v in record["overrides"].items()))
    if record.get("schedule"):
        log.line(f"schedule: {json.dumps(record['schedule'])}")
    if extend:
        log.line(f"extend: {config.steps - extend} -> {config.steps} steps; milestones stay (densify.stop "
                 f"{config.densify.stop}, aps_step {config.aps_step}, lr.position_decay_steps "
                 f"{config.lr.position_decay_steps})", echo=True)

    def save(final: bool = False) -> None:
        _assert_finite(state, f"step {state.step}")
        body = {**state_payload(state, data, config, options), "record": json.dumps(record)}
        ckpt.save_checkpoint(last_path, body)
        if final:
            ckpt.save_checkpoint(ckpt.run_checkpoint_path(run_dir, "final"), body)
        write_aps_report(run_dir, state.aps, config)

    def validate() -> float | None:
        shown = validation_image(data, state)
        if shown is None:
            return None
        image, val_psnr = shown
        save_png(run_dir / ckpt.VAL_DIR / f"step_{state.step:06d}.png", image)
        log.line(f"step {state.step}: validation PSNR {val_psnr:.2f} dB (training frames)")
        log.scalars(state.step, {"val/psnr": val_psnr})
        return val_psnr

    result = TrainResult(run_dir, "finished", state.step, steps, 0.0, 0.0)
    start_step, started = state.step, time.perf_counter()
    status = "finished"
    try:
        with _InterruptFlag() as interrupt:
            for step in range(state.step + 1, steps + 1):
                try:
                    sampled = step == start_step + 1 or step % VALUE_CHECK_EVERY == 0 or step % log_every == 0
                    report = train_step(data, state, config, step, options.seed, check_values=sampled)
                except TrainingDiverged as err:
                    saved_at = _saved_step(last_path)
                    log.line(f"STOPPED: {err}", echo=True)
                    raise TrainingDiverged(
                        f"{err}. Training stopped; the last good checkpoint is {last_path} "
                        f"({'step ' + str(saved_at) if saved_at is not None else 'none written yet'}). "
                        "Lower the learning rates or check the data, then resume with --resume."
                    ) from None
                result.last = report
                elapsed = time.perf_counter() - started
                rate = (step - start_step) / max(elapsed, 1e-9)
                bar.update(1)
                bar.set_postfix(loss=f"{report.losses['total']:.4f}", psnr=f"{report.psnr:.2f}",
                                N=report.num_gaussians, sps=f"{rate:.2f}", refresh=False)
                if report.densified is not None:
                    log.line(f"step {step}: densify {report.densified}")
                if report.aps_ran:
                    log.line(state.aps.report(), echo=True)
                    write_aps_report(run_dir, state.aps, config)
                if step % log_every == 0 or step == steps:
                    terms = " ".join(f"{k} {v:.5f}" for k, v in report.losses.items())
                    log.line(f"step {step}: {terms} psnr {report.psnr:.2f} gaussians {report.num_gaussians} "
                             f"steps/s {rate:.3f}")
                    log.scalars(step, {**{f"loss/{k}": v for k, v in report.losses.items()},
                                       "train/psnr": report.psnr, "train/gaussians": report.num_gaussians})
                    result.history.append({"step": step, "loss": report.losses["total"], "psnr": report.psnr,
                                           "gaussians": report.num_gaussians})
                if callback is not None:
                    callback(step, state, report)
                if step % val_every == 0 and step != steps:
                    result.val_psnr = validate()
                if interrupt.requested and step != steps:
                    save()
                    log.line(f"interrupted at step {step}: saved {last_path}; continue with --resume", echo=True)
                    status = "interrupted"
                    break
                if step % ckpt_every == 0 and step != steps:
                    save()
                    log.line(f"step {step}: checkpoint {last_path}")
            else:
                result.val_psnr = validate()
                save(final=True)
                log.line(f"finished {steps} steps: {ckpt.run_checkpoint_path(run_dir, 'final')}", echo=True)
    finally:
        bar.close()
        log.close()
    result.status, result.step = status, state.step
    result.seconds = time.perf_counter() - started
    result.steps_per_second = (state.step - start_step) / max(result.seconds, 1e-9)
    return result


def _saved_step(path: Path) -> int | None:
    if not path.is_file():
        return None
    try:
        return int(ckpt.load_checkpoint(path)["step"])
    except (ckpt.RunError, KeyError, ValueError):
        return None


def _assert_finite(state: TrainingState, where: str) -> None:
    """Raise TrainingDiverged when a learned tensor holds NaN/Inf (so no such checkpoint is ever written)."""
    modules = [("avatar", state.avatar), ("frame parameters", state.frames)]
    if state.deformer is not None:
        modules.append(("mouth deformer", state.deformer))
    named = [(name, pname, value) for name, module in modules for pname, value in module.named_parameters()]
    with torch.no_grad():  # one flag per tensor, read back in one transfer
        finite = torch.stack([torch.isfinite(value).all() for _, _, value in named]).tolist()
    for (name, pname, _), ok in zip(named, finite):
        if not ok:
            raise TrainingDiverged(f"{where}: {name} parameter '{pname}' holds NaN/Inf")


def write_aps_report(run_dir: Path, aps: APSState, config: TrainConfig) -> None:
    """RUN/aps.json: the APS decision (or why there is none)."""
    body = {"face_sets": config.model.face_sets, "aps_step": config.aps_step, **aps.to_dict(),
            "report": aps.report() if config.model.face_sets == "aps"
            else f"APS not used: face_sets = '{config.model.face_sets}'"}
    atomic_write_json(run_dir / ckpt.APS_FILE, body)


__all__ = [
    "RunOptions", "StepReport", "TrainResult", "TrainingData", "TrainingDiverged", "TrainingState",
    "VALUE_CHECK_EVERY", "build_optimizers", "frame_index", "item_camera", "new_state", "open_training_data",
    "restore_state", "state_payload", "train", "train_step", "validation_image",
]
