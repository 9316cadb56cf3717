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
                per step (randomness.step_background), the same one behind the render
    loss        avatar_loss: L_rgb + L_reg (+ L_angle, + GaussianAvatars' scale loss) (+ turned_view_term: the frame
                warped to a turned camera, TrainConfig.warped_view, off by default); NaN/Inf stops the run
                (the terms are read back in one transfer per step; value checks that wait for the device,
                rasterize's inputs and NaN/Inf in the learned tensors, run every VALUE_CHECK_EVERY steps,
                on log steps and before every checkpoint)
    backward    then Adam steps (position lr decays log-linearly), then densification statistics from
                means2d.grad and densify/prune/opacity reset on the (scaled) schedule, then APS at aps_step
                (3DGS densifies before the Adam step and so skips that step's update; see train_step)

Every step-based milestone comes from `TrainConfig.scaled_to(steps)`, so a short run keeps the paper's
proportions (APS at half the run, densification every 1 % from 5 %, opacity reset every 30 %).

The run around the steps: resume.py decides where it starts (new, --resume, --extend), state.py builds the
TrainingData and TrainingState, checkpoint.py saves and restores the state (parameters and binding, the three Adam
optimizers, densification statistics, APS decision and face sets, refined per-frame parameters, the step, the RNG
states of randomness.py), run_log.py writes RUN/train.log (and TensorBoard), interrupt.py turns Ctrl-C into a saved
stop. Frame order is a pure function of (seed, epoch), so it needs no state. Validation renders use no randomness
and change nothing.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
from torch import Tensor

from geoavatar.avatar import position_lr, render_avatar
from geoavatar.avatar import densify as densify_ops
from geoavatar.avatar.render import AvatarRender
from geoavatar.config import TrainConfig
from geoavatar.data.dataset import item_camera, item_to
from geoavatar.errors import GeoAvatarError
from geoavatar.imaging import psnr_from_mse, to_uint8
from geoavatar.io.atomic import atomic_write_json, atomic_write_png
from geoavatar.render import Camera, composite_target
from geoavatar.train import checkpoint as ckpt
from geoavatar.train.interrupt import InterruptFlag
from geoavatar.train.losses import avatar_loss
from geoavatar.train.options import Intervals, RunOptions
from geoavatar.train.randomness import frame_index, step_background
from geoavatar.train.resume import start_run
from geoavatar.train.run_log import RunLog
from geoavatar.train.state import TrainingData, TrainingState, new_state, open_training_data
from geoavatar.train.warped_view import turned_view_term

# Steps between the value checks that wait for the device (rasterize's inputs, NaN/Inf in the learned
# tensors); they also run on a run's first step and before every checkpoint. The loss is checked every step.
VALUE_CHECK_EVERY = 50


class TrainingDiverged(GeoAvatarError, RuntimeError):
    """The loss became NaN or infinite; the message says where and which checkpoint is intact."""


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


# --- one step -----------------------------------------------------------------------------------


def train_step(data: TrainingData, state: TrainingState, config: TrainConfig, step: int, seed: int,
               check_values: bool | None = None) -> StepReport:
    """One optimisation step (numbered `step`, 1-based). Raises TrainingDiverged on a NaN/Inf loss.

    The step waits for the device once, to read the loss terms back (and stop on a NaN/Inf total
    before it reaches the parameters); `check_values` (default: every VALUE_CHECK_EVERY steps) adds
    rasterize's input value checks and the NaN/Inf check of the learned tensors."""
    if check_values is None:
        check_values = step % VALUE_CHECK_EVERY == 0
    item = item_to(data.train_set[frame_index(step, len(data.train_set), seed)], data.device)
    background = step_background(item["background"], config.background, seed, step)  # [3]
    target = composite_target(item["image"], item["mask"], background)
    camera = item_camera(item)
    frame = render_avatar(state.avatar, data.head, state.frames(item["row"]), camera, item["timestep"], state.deformer,
                          background, data.backend, check_values=check_values)
    losses = step_losses(data, state, config, frame, target, item, camera, background, seed, step)
    reported, mse = read_back(losses, frame.result.rgb, target, step)
    optimizer_step(data, state, config, losses["total"], step)
    # Densification after the Adam step (3DGS runs it before, and a densifying step then loses its
    # update: densify replaces the tensors, whose .grad is gone; immaterial every 2000 of 200k steps,
    # but a schedule scaled to a few hundred steps densifies every 1-2 steps and would freeze them).
    densified = densify_step(data, state, config, frame, camera, step)
    if check_values:
        assert_finite(state, f"step {step}: after the optimizer step")
    aps_ran = aps_if_due(data, state, config, step)
    state.step = step
    return StepReport(reported, psnr_from_mse(mse), state.avatar.num_gaussians, densified, aps_ran)


def step_losses(data: TrainingData, state: TrainingState, config: TrainConfig, frame: AvatarRender, target: Tensor,
                item: dict, camera: Camera, background: Tensor, seed: int, step: int) -> dict[str, Tensor]:
    """The step's named loss terms and their "total" (last): avatar_loss, plus the warped view when it is due."""
    p = state.avatar.params
    losses = avatar_loss(frame.result.rgb, target, p["means"], p["scales"], state.avatar.binding, state.face_sets,
                         config.loss, visible=frame.result.visible)
    if config.warped_view.active(step):  # logged by name before the total
        warped = turned_view_term(frame.gaussians, frame.vertices, data.head, data.warp_faces, item, camera,
                                  background, config.warped_view, seed, step, data.backend)
        total = losses.pop("total") + warped
        losses = {**losses, "warped_view": warped, "total": total}
    return losses


def read_back(losses: dict[str, Tensor], rgb: Tensor, target: Tensor, step: int) -> tuple[dict[str, float], float]:
    """(loss terms as floats, the render's MSE) in the step's one read-back from the device; TrainingDiverged when
    the total is not finite."""
    with torch.no_grad():
        mse = ((rgb.detach() - target) ** 2).mean()
    values = torch.stack([v.detach().reshape(()) for v in losses.values()] + [mse.reshape(())]).tolist()
    reported = dict(zip(losses, values[:-1]))
    if not math.isfinite(reported["total"]):
        terms = ", ".join(f"{k}={v:.4g}" for k, v in reported.items())
        raise TrainingDiverged(f"step {step}: the loss is not finite ({terms})")
    return reported, values[-1]


def optimizer_step(data: TrainingData, state: TrainingState, config: TrainConfig, total: Tensor, step: int) -> None:
    """Backward from the total loss, then one step of every optimizer (the positions' learning rate decayed to
    `step`)."""
    for opt in state.optimizers.values():
        if opt is not None:
            opt.zero_grad(set_to_none=True)
    total.backward()
    for group in state.optimizers["gaussians"].param_groups:
        if group["name"] in ("means", "means_pose"):
            group["lr"] = position_lr(step, config.lr, data.extent)
    for opt in state.optimizers.values():
        if opt is not None:
            opt.step()


def densify_step(data: TrainingData, state: TrainingState, config: TrainConfig, frame: AvatarRender, camera: Camera,
                 step: int) -> dict[str, int] | None:
    """Densification statistics of this step's render and the schedule's densify/prune/opacity reset; the counts
    when it densified."""
    result = frame.result
    strategy = densify_ops.DensifyStrategy(config.densify, data.extent, state.generator)
    info = densify_ops.DensifyInfo(state.avatar.binding, frame.gaussians.frames.scale.detach(), result.means2d.grad,
                                   result.visible, result.radii, camera.width, camera.height)
    state.avatar.binding, densified = strategy.step_post_backward(
        state.avatar.params, [state.optimizers["gaussians"]], state.stats, step, info)
    return densified


def aps_if_due(data: TrainingData, state: TrainingState, config: TrainConfig, step: int) -> bool:
    """APS at aps_step (face_sets "aps"): the parts' rigid / flexible decision, the new face sets; True when it ran."""
    if config.model.face_sets != "aps" or state.aps.done or step < config.aps_step:
        return False
    state.aps.run(state.avatar.params["means"].detach(), state.avatar.binding, data.part_of_face, step)
    state.face_sets = state.aps.face_sets(data.part_of_face, "aps").to(data.device)
    return True


def assert_finite(state: TrainingState, where: str) -> None:
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


@torch.no_grad()
def validation_image(data: TrainingData, state: TrainingState) -> tuple[np.ndarray, float] | None:
    """Ground truth | render for each validation frame, stacked; and their mean PSNR (training frames)."""
    if data.val_set is None:
        return None
    rows, psnrs = [], []
    for index in range(len(data.val_set)):
        item = item_to(data.val_set[index], data.device)
        target = composite_target(item["image"], item["mask"], item["background"])
        result = render_avatar(state.avatar, data.head, state.frames(item["row"]), item_camera(item), item["timestep"],
                               state.deformer, item["background"], data.backend).result
        rgb = result.rgb.clamp(0.0, 1.0)
        psnrs.append(psnr_from_mse(float(((rgb - target) ** 2).mean())))
        rows.append(torch.cat([target, rgb], dim=1))  # [H, 2W, 3]
    width = max(r.shape[1] for r in rows)
    rows = [torch.nn.functional.pad(r, (0, 0, 0, width - r.shape[1])) for r in rows]
    image = to_uint8(torch.cat(rows, dim=0))
    return image, float(np.mean(psnrs))


# --- the run ------------------------------------------------------------------------------------


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
    from tqdm.auto import tqdm

    start = start_run(options, config, resume, extend, record)
    config, run_dir = start.config, Path(options.out)
    data = open_training_data(options, config)
    run_dir.mkdir(parents=True, exist_ok=True)
    if start.payload is not None:
        state = ckpt.restore_state(start.payload, data, config, str(ckpt.run_checkpoint_path(run_dir, "last")))
    else:
        state = new_state(data, config, options.seed)
    atomic_write_json(run_dir / ckpt.CONFIG_FILE, {
        "preset": options.preset, "config": ckpt.config_to_dict(config), **start.record, "run": options.to_json(),
        "dataset": data.dataset_record(), "device": str(data.device),
    })
    bar = tqdm(total=config.steps, initial=state.step, disable=not options.progress, dynamic_ncols=True, unit="step")
    result = TrainResult(run_dir, "finished", state.step, config.steps, 0.0, 0.0)
    run = RunSession(options, config, start.record, data, state, RunLog(run_dir, echo=bar.write), bar,
                     options.intervals(config.steps), result)
    try:
        run.announce(resumed=start.payload is not None, extend=extend)
        start_step, started = state.step, time.perf_counter()
        run.result.status = run.loop(callback, started)
    finally:
        bar.close()
        run.log.close()
    result.step, result.seconds = state.step, time.perf_counter() - started
    result.steps_per_second = (state.step - start_step) / max(result.seconds, 1e-9)
    return result


@dataclass
class RunSession:
    """One session of a run (from its start or a resume to its end or an interruption): the loop and what it writes
    besides the TrainingState: the log, the progress bar, validation images, checkpoints."""

    options: RunOptions
    config: TrainConfig
    record: dict  # RUN/config.json's overrides / schedule / extensions, kept in every checkpoint
    data: TrainingData
    state: TrainingState
    log: RunLog
    bar: Any  # tqdm progress bar
    intervals: Intervals
    result: TrainResult

    @property
    def last_path(self) -> Path:
        return ckpt.run_checkpoint_path(self.result.run_dir, "last")

    def loop(self, callback: Callable[[int, TrainingState, StepReport], None] | None, started: float) -> str:
        """Train to the last step, or to a Ctrl-C (saved): "finished" | "interrupted"."""
        steps, start_step = self.config.steps, self.state.step
        with InterruptFlag() as interrupt:
            for step in range(start_step + 1, steps + 1):
                check_values = step == start_step + 1 or step % VALUE_CHECK_EVERY == 0 or step % self.intervals.log == 0
                report = self.step(step, check_values)
                self.after_step(step, report, (step - start_step) / max(time.perf_counter() - started, 1e-9))
                if callback is not None:
                    callback(step, self.state, report)
                if step % self.intervals.val == 0 and step != steps:
                    self.result.val_psnr = self.validate()
                if interrupt.requested and step != steps:
                    self.save()
                    self.log.line(f"interrupted at step {step}: saved {self.last_path}; continue with --resume",
                                  echo=True)
                    return "interrupted"
                if step % self.intervals.ckpt == 0 and step != steps:
                    self.save()
                    self.log.line(f"step {step}: checkpoint {self.last_path}")
        self.result.val_psnr = self.validate()
        self.save(final=True)
        self.log.line(f"finished {steps} steps: {ckpt.run_checkpoint_path(self.result.run_dir, 'final')}", echo=True)
        return "finished"

    def step(self, step: int, check_values: bool) -> StepReport:
        """train_step; on a NaN/Inf loss the log says so and the error names the last good checkpoint."""
        try:
            return train_step(self.data, self.state, self.config, step, self.options.seed, check_values=check_values)
        except TrainingDiverged as err:
            self.log.line(f"STOPPED: {err}", echo=True)
            raise TrainingDiverged(f"{err}. Training stopped; the {ckpt.last_good_checkpoint(self.last_path)}. "
                                   "Lower the learning rates or check the data, then resume with --resume.") from None

    def after_step(self, step: int, report: StepReport, rate: float) -> None:
        """The progress bar, and the log lines, TensorBoard scalars and history of a logged step."""
        self.result.last = report
        self.bar.update(1)
        self.bar.set_postfix(loss=f"{report.losses['total']:.4f}", psnr=f"{report.psnr:.2f}",
                             N=report.num_gaussians, sps=f"{rate:.2f}", refresh=False)
        if report.densified is not None:
            self.log.line(f"step {step}: densify {report.densified}")
        if report.aps_ran:
            self.log.line(self.state.aps.report(), echo=True)
            ckpt.write_aps_report(self.result.run_dir, self.state.aps, self.config)
        if step % self.intervals.log == 0 or step == self.config.steps:
            terms = " ".join(f"{k} {v:.5f}" for k, v in report.losses.items())
            self.log.line(f"step {step}: {terms} psnr {report.psnr:.2f} gaussians {report.num_gaussians} "
                          f"steps/s {rate:.3f}")
            self.log.scalars(step, {**{f"loss/{k}": v for k, v in report.losses.items()},
                                    "train/psnr": report.psnr, "train/gaussians": report.num_gaussians})
            self.result.history.append({"step": step, "loss": report.losses["total"], "psnr": report.psnr,
                                        "gaussians": report.num_gaussians})

    def announce(self, resumed: bool, extend: int) -> None:
        """The log's first lines: where the run starts, its data, options set and schedule."""
        data, config, record = self.data, self.config, self.record
        self.log.line(f"{'resume' if resumed else 'start'} at step {self.state.step}/{config.steps}: data "
                      f"{data.subject.root} ({len(data.train_set)} training frames), head {data.subject.head_model} + "
                      f"mouth {config.model.mouth}, preset {self.options.preset}, device {data.device}, extent "
                      f"{data.extent:.3f}, seed {self.options.seed}")
        if record["overrides"]:
            self.log.line("overrides: " + ", ".join(f"{k}={v!r}" for k, v in record["overrides"].items()))
        if record.get("schedule"):
            self.log.line(f"schedule: {json.dumps(record['schedule'])}")
        if extend:
            self.log.line(f"extend: {config.steps - extend} -> {config.steps} steps; milestones stay (densify.stop "
                          f"{config.densify.stop}, aps_step {config.aps_step}, lr.position_decay_steps "
                          f"{config.lr.position_decay_steps})", echo=True)

    def save(self, final: bool = False) -> None:
        """RUN/checkpoints/last.pt (and final.pt) and RUN/aps.json; never a checkpoint with NaN/Inf in it."""
        assert_finite(self.state, f"step {self.state.step}")
        body = {**ckpt.state_payload(self.state, self.data, self.config, self.options),
                "record": json.dumps(self.record)}
        ckpt.save_checkpoint(self.last_path, body)
        if final:
            ckpt.save_checkpoint(ckpt.run_checkpoint_path(self.result.run_dir, "final"), body)
        ckpt.write_aps_report(self.result.run_dir, self.state.aps, self.config)

    def validate(self) -> float | None:
        """RUN/val/step_XXXXXX.png and its PSNR (None without validation frames)."""
        shown = validation_image(self.data, self.state)
        if shown is None:
            return None
        image, val_psnr = shown
        atomic_write_png(self.result.run_dir / ckpt.VAL_DIR / f"step_{self.state.step:06d}.png", image)
        self.log.line(f"step {self.state.step}: validation PSNR {val_psnr:.2f} dB (training frames)")
        self.log.scalars(self.state.step, {"val/psnr": val_psnr})
        return val_psnr


__all__ = [
    "RunSession", "StepReport", "TrainResult", "TrainingDiverged", "VALUE_CHECK_EVERY", "assert_finite", "train",
    "train_step", "validation_image",
]
