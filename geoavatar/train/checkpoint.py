"""Checkpoints and the RUN folder of `geoavatar train`: the checkpoint schema, atomic writes, safe loading, `load_run`.

RUN layout (what later commands — eval, render, reenact, export — read):

    RUN/config.json              the resolved TrainConfig (every field) + the run options (JSON); the
                                 options set on the command line ("overrides"), how the steps were
                                 chosen ("schedule": --steps / --minutes with its measurements) and
                                 the --extend history ("extensions")
    RUN/checkpoints/last.pt      newest checkpoint (rewritten every --ckpt-every steps, on Ctrl-C, at the end)
    RUN/checkpoints/final.pt     the checkpoint of the finished run (same content as last.pt then)
    RUN/aps.json                 the APS decision: Distance(k) per part, tau_part, rigid/flexible
    RUN/held_out.npz, .json      the test frames' parameters fitted against the finished avatar (train's last
                                 stage, train/held_out_fit.py), tagged with the checkpoint's step; load_run lays them
                                 over frame_params while that step is the checkpoint's (RunInfo.held_out)
    RUN/train.log                one line per logged step, densification and APS events, validation PSNR
    RUN/val/step_XXXXXX.png      progress images: ground truth | render, one row per validation frame

A checkpoint holds only tensors, numbers, strings, lists and dicts (configs as JSON strings), so it
loads with `torch.load(weights_only=True)`: a checkpoint from someone else cannot run code. Keys:

    format, version, step          "geoavatar-checkpoint", 1, the number of finished steps
    config, run                    JSON strings: TrainConfig, run options (data dir, seed, device, ...)
    record                         JSON string: overrides / schedule / extensions of config.json (kept on resume)
    dataset                        dict: root, head_model, background, resolution, timesteps of the splits
    avatar                         GaussianAvatar.state_dict() (params.*, binding [N], faces [F, 3])
    deformer, num_frames           MouthDeformer.state_dict() or None; the num_frames it was built for
    frame_params, refine_tracking  per-timestep head parameters [T, ...] (refined when refine_tracking)
    optimizers                     {"gaussians", "tracking", "deformer"}: Adam state dicts (absent: None)
    densify_stats                  {grad2d, count, max_radii} [N]
    aps, face_sets                 APSState.to_dict(); [F] regulariser set of every face
    extent                         scene extent (metres) used by the position lr and densification
    rng                            torch / cuda / numpy / python / trainer generator states (train/randomness.py)

`state_payload` writes these from a training run's state (train/state.py) and `restore_state` reads them back for an
exact resume; `load_run` reads what eval and the apps need. A stored configuration reads fields it predates with the
values it was trained with (FIELDS_ADDED_LATER) and drops options removed since (FIELDS_REMOVED), with a note.

Every write goes through geoavatar.io.atomic (temporary file in the same folder, os.replace), so a
killed process leaves either the old or the new file, never a torn one; a full disk raises
DiskFullError naming the file and the last good checkpoint.
"""

from __future__ import annotations

import dataclasses
import io
import json
import os
import typing
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import torch

from geoavatar.config import TrainConfig
from geoavatar.data import DataConfig, DatasetError, HeadAvatarDataset, open_subject
from geoavatar.errors import DiskFullError, GeoAvatarError, GeoAvatarWarning, OptionError, disk_full_error
from geoavatar.io.atomic import atomic_write_bytes, atomic_write_json
from geoavatar.train.randomness import restore_rng, rng_state

if typing.TYPE_CHECKING:
    from geoavatar.train.options import RunOptions
    from geoavatar.train.state import TrainingData, TrainingState

FORMAT = "geoavatar-checkpoint"
VERSION = 1
CHECKPOINT_DIR = "checkpoints"
LAST_CHECKPOINT = "last.pt"
FINAL_CHECKPOINT = "final.pt"
CONFIG_FILE = "config.json"
APS_FILE = "aps.json"
LOG_FILE = "train.log"
VAL_DIR = "val"


class RunError(GeoAvatarError, ValueError):
    """A RUN folder or checkpoint is missing or unusable; the message names the path."""


# --- writing and reading checkpoints -----------------------------------------------------------


def save_checkpoint(path: str | os.PathLike, payload: dict) -> Path:
    """torch.save `payload` (plus format/version) atomically.

    On a full disk, DiskFullError names the checkpoint and the last good one, which is intact."""
    path = Path(path)
    buffer = io.BytesIO()
    torch.save({"format": FORMAT, "version": VERSION, **payload}, buffer)
    try:
        return atomic_write_bytes(path, buffer.getvalue())
    except DiskFullError as err:
        raise disk_full_error(path, err, f"{last_good_checkpoint(path)}, which --resume continues from") from err


def last_good_checkpoint(failed: str | os.PathLike) -> str:
    """'last good checkpoint: <path> (step N)' for a run whose write of `failed` did not happen, or says there is none."""
    failed = Path(failed)
    for candidate in (failed, failed.with_name(LAST_CHECKPOINT)):  # final.pt failing: last.pt holds the same step
        if candidate.is_file():
            step = saved_step(candidate)
            return f"last good checkpoint: {candidate} ({'unreadable' if step is None else f'step {step}'})"
    return "last good checkpoint: none written yet"


def saved_step(path: str | os.PathLike) -> int | None:
    """The number of finished steps the checkpoint at `path` holds; None when there is none or it is unreadable."""
    if not Path(path).is_file():
        return None
    try:
        return int(load_checkpoint(path)["step"])
    except (RunError, KeyError, TypeError, ValueError):
        return None


def load_checkpoint(path: str | os.PathLike, map_location: str | torch.device = "cpu") -> dict:
    """Load a checkpoint safely (weights_only=True); RunError naming the file when it is unusable."""
    path = Path(path)
    if not path.is_file():
        raise RunError(f"{path}: checkpoint not found")
    try:
        payload = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as err:  # noqa: BLE001 - torch raises many kinds for a corrupt or foreign file
        raise RunError(f"{path}: not a readable GeoAvatar checkpoint ({type(err).__name__}: {err})") from err
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise RunError(f"{path}: not a GeoAvatar checkpoint (no format marker '{FORMAT}')")
    if payload.get("version") != VERSION:
        raise RunError(f"{path}: checkpoint version {payload.get('version')} is not supported (expected {VERSION})")
    return payload


# --- configs as JSON --------------------------------------------------------------------------


def config_to_dict(config: TrainConfig) -> dict:
    return dataclasses.asdict(config)


def dataclass_from_dict(cls: type, data: dict, where: str = "config") -> Any:
    """Rebuild a (nested) dataclass from its asdict() form; ValueError naming an unknown key."""
    if not isinstance(data, dict):
        raise ValueError(f"{where}: expected an object, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {', '.join(unknown)}")
    values = {}
    for name, value in data.items():
        hint = hints.get(name)
        if isinstance(hint, type) and dataclasses.is_dataclass(hint):
            value = dataclass_from_dict(hint, value, f"{where}.{name}")
        elif typing.get_origin(hint) is tuple and isinstance(value, list):  # JSON has no tuples
            value = tuple(value)
        values[name] = value
    return cls(**values)


# Fields added to the configuration after runs had been written, with the value those runs were trained with
# (a stored configuration without the field predates it); their defaults today differ.
FIELDS_ADDED_LATER: dict[str, dict[str, Any]] = {
    "model": {"normal_shading": False, "init_colour": "grey", "hair_follows_head": False}}


# Options removed after runs had been written (measured and rejected: docs/REJECTED.md), by dotted name, with the value
# at which the option changed nothing (None: any value, a setting of a removed term). A stored configuration holding
# them loads without them, with a one-line note (RemovedOptionWarning); SECTIONS_REMOVED go when nothing is left.
FIELDS_REMOVED: dict[str, Any] = {
    "loss.angle_axis": "normal",
    "warped_view.colours_only": False,
    "mesh_prior.lambda_behind": 0.0, "mesh_prior.lambda_turned_behind": 0.0, "mesh_prior.lambda_turned_outside": 0.0,
    "mesh_prior.margin": None, "mesh_prior.outside_dilate": None, "mesh_prior.turned_yaw": None,
    "mesh_prior.turned_pitch": None, "mesh_prior.turned_every": None,
}
SECTIONS_REMOVED = ("mesh_prior",)


class RemovedOptionWarning(GeoAvatarWarning):
    """A stored configuration holds options that no longer exist; it loads without them."""


def drop_removed_fields(data: dict, where: str) -> list[str]:
    """Remove FIELDS_REMOVED from a stored configuration's dict (in place), with a note; the dotted names dropped."""
    dropped, active = [], []
    for name, inert in FIELDS_REMOVED.items():
        section, _, key = name.partition(".")
        block = data.get(section)
        if isinstance(block, dict) and key in block:
            value = block.pop(key)
            dropped.append(name)
            if inert is not None and value != inert:
                active.append(f"{name}={value!r}")
    for section in SECTIONS_REMOVED:
        if data.get(section) == {}:
            del data[section]
    if dropped:
        names = sorted({f"{name.partition('.')[0]}.*" if name.partition('.')[0] in SECTIONS_REMOVED else name
                        for name in dropped})
        used = (f"this run set {', '.join(active)}, which it now trains and renders without" if active
                else "none of them was on in this run")
        warnings.warn(f"{where}: ignoring options removed as measured and rejected (docs/REJECTED.md): "
                      f"{', '.join(names)}; {used}", RemovedOptionWarning, stacklevel=3)
    return dropped


def config_from_json(text: str, where: str = "config") -> TrainConfig:
    """A stored TrainConfig; fields it predates (FIELDS_ADDED_LATER) take the value it was trained with, fields
    removed since (FIELDS_REMOVED) are dropped with a note."""
    try:
        data = json.loads(text)
        if isinstance(data, dict):
            drop_removed_fields(data, where)
        for section, added in FIELDS_ADDED_LATER.items():
            if isinstance(data, dict) and isinstance(data.get(section), dict):
                data[section] = {**added, **data[section]}
        return dataclass_from_dict(TrainConfig, data, where).validate()
    except (json.JSONDecodeError, TypeError, ValueError) as err:
        raise RunError(f"{where}: not a valid training configuration ({err})") from err


# --- a training run's state ------------------------------------------------------------------


def state_payload(state: "TrainingState", data: "TrainingData", config: TrainConfig, options: "RunOptions") -> dict:
    """The checkpoint of a training run (the keys of the module docstring, but for format, version and record)."""
    return {
        "step": int(state.step),
        "config": json.dumps(config_to_dict(config)),
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


def restore_state(payload: dict, data: "TrainingData", config: TrainConfig, where: str) -> "TrainingState":
    """The TrainingState saved in `payload` (a loaded checkpoint), on data.device; RunError naming `where` when the
    checkpoint does not fit the configuration or the dataset. Sets data.extent to the saved one."""
    from geoavatar.avatar import APSState, GaussianAvatar, MouthDeformer
    from geoavatar.train.frame_params import FrameParams
    from geoavatar.train.state import TrainingState, build_optimizers

    device = data.device
    try:
        avatar = GaussianAvatar.for_model(data.head, config.model)
        avatar.load_state_dict(payload["avatar"])
        avatar = avatar.to(device)
        deformer = None
        if config.model.mouth_deform.enabled:
            if payload.get("deformer") is None:
                raise RunError(f"{where}: the config enables the mouth deformer but the checkpoint has none")
            deformer = MouthDeformer.for_head(data.head, int(payload["num_frames"]), config.model.mouth_deform)
            deformer.load_state_dict(payload["deformer"])
            deformer = deformer.to(device)
        frames = FrameParams(payload["frame_params"], refine=bool(payload["refine_tracking"])).to(device)
        if frames.num_rows != data.subject.num_timesteps:
            raise RunError(f"{where}: the checkpoint has parameters of {frames.num_rows} frames, the dataset "
                           f"{data.subject.root} has {data.subject.num_timesteps}")
        optimizers = build_optimizers(avatar, deformer, frames, config, float(payload["extent"]), payload["optimizers"])
        for name, opt in optimizers.items():
            saved = payload["optimizers"].get(name)
            if (opt is None) != (saved is None):
                raise RunError(f"{where}: optimizer '{name}' does not match the configuration")
            if opt is not None:
                opt.load_state_dict(saved)
        stats = {k: v.to(device) for k, v in payload["densify_stats"].items()}
        aps = APSState.from_dict(payload["aps"])
        generator = torch.Generator(device=device)
        restore_rng(payload["rng"], generator)
    except KeyError as err:
        raise RunError(f"{where}: checkpoint lacks the entry {err}") from err
    data.extent = float(payload["extent"])
    return TrainingState(
        avatar=avatar, deformer=deformer, frames=frames, optimizers=optimizers, stats=stats, aps=aps,
        face_sets=payload["face_sets"].to(device), generator=generator, step=int(payload["step"]),
    )


def write_aps_report(run_dir: Path, aps: Any, config: TrainConfig) -> None:
    """RUN/aps.json: the APS decision (APSState `aps`), or why there is none."""
    body = {"face_sets": config.model.face_sets, "aps_step": config.aps_step, **aps.to_dict(),
            "report": aps.report() if config.model.face_sets == "aps"
            else f"APS not used: face_sets = '{config.model.face_sets}'"}
    atomic_write_json(run_dir / APS_FILE, body)


# --- loading a finished (or interrupted) run --------------------------------------------------


@dataclass
class RunInfo:
    """What a run knows about its data, besides the learned avatar."""

    run_dir: Path
    checkpoint: Path
    step: int
    data_root: Path
    head_model: str
    background: list[float]  # [3] colour the avatar was trained on
    resolution: int | None
    num_frames: int  # the MouthDeformer's time normaliser (frames of the video)
    timesteps: dict[str, list[int]]  # "all", "train", "val", "test"
    frame_params: dict[str, torch.Tensor]  # per-timestep head parameters [T, ...] (refined ones when on)
    aps: dict  # APSState.to_dict()
    face_sets: torch.Tensor  # [F]
    run_options: dict = field(default_factory=dict)
    held_out: list[int] = field(default_factory=list)  # timesteps whose rows train's held-out fit wrote
    held_out_scored: list[int] = field(default_factory=list)  # those eval scores (a long video's: some, the rest filled)


def _lay_held_out_over(info: RunInfo) -> None:
    """The held-out fit's rows (train/held_out_fit.py) over `info.frame_params`, while they belong to its step."""
    from geoavatar.train.held_out_fit import read_held_out

    held_out = read_held_out(info.run_dir, info.step)
    if held_out is None:
        return
    timesteps, rows = held_out.timesteps, held_out.rows
    row_of = {t: i for i, t in enumerate(info.timesteps["all"])}
    if any(t not in row_of for t in timesteps):
        return  # fitted on other frames: not this run's rows
    index = torch.as_tensor([row_of[t] for t in timesteps])
    for key, values in rows.items():
        if key in info.frame_params:
            merged = info.frame_params[key].clone()
            merged[index] = torch.as_tensor(values, dtype=merged.dtype)
            info.frame_params[key] = merged
    info.held_out = list(timesteps)
    info.held_out_scored = list(held_out.scored)


class LoadedRun(NamedTuple):
    config: TrainConfig
    head: Any  # geoavatar.head.HeadModel
    avatar: Any  # geoavatar.avatar.GaussianAvatar
    deformer: Any  # geoavatar.avatar.MouthDeformer | None
    info: RunInfo

    @property
    def device(self) -> torch.device:
        """The device the run's modules were opened on (open_run's --device)."""
        return self.avatar.binding.device


def run_checkpoint_path(run_dir: str | os.PathLike, which: str = "last") -> Path:
    names = {"last": LAST_CHECKPOINT, "final": FINAL_CHECKPOINT}
    if which not in names:
        raise ValueError(f"checkpoint must be one of {', '.join(names)}, got {which!r}")
    return Path(run_dir) / CHECKPOINT_DIR / names[which]


def load_head_for(name: str, mouth: str, flame_dir: str | os.PathLike | None = None):
    """The head model a run (or a dataset) needs, with the mouth structure of its config."""
    from geoavatar.head import load_head_model

    options = {"flame_dir": flame_dir} if name == "flame" else {}
    return load_head_model(name, mouth=mouth, **options)


def load_run(
    run_dir: str | os.PathLike,
    device: str | torch.device = "cpu",
    checkpoint: str = "last",
    flame_dir: str | os.PathLike | None = None,
) -> LoadedRun:
    """(config, head, avatar, deformer, info) of a RUN folder written by `geoavatar train`.

    The modules are on `device` in eval mode. flame_dir overrides the FLAME folder the run used.
    """
    from geoavatar.avatar import GaussianAvatar, MouthDeformer

    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise RunError(f"{run_dir}: run folder not found")
    path = run_checkpoint_path(run_dir, checkpoint)
    if not path.is_file():
        raise RunError(
            f"{run_dir}: not a GeoAvatar run (no {CHECKPOINT_DIR}/{path.name}); "
            "train one with `geoavatar train --data DIR --out RUN`"
        )
    ckpt = load_checkpoint(path, map_location="cpu")
    try:
        config = config_from_json(ckpt["config"], f"{path} [config]")
        run_options = json.loads(ckpt.get("run", "{}"))
        dataset = ckpt["dataset"]
        head = load_head_for(dataset["head_model"], config.model.mouth, flame_dir or run_options.get("flame_dir"))
        faces = ckpt["avatar"]["faces"]
        if tuple(faces.shape) != tuple(head.faces.shape) or not torch.equal(faces, head.faces.cpu()):
            raise RunError(
                f"{path}: the avatar is bound to a mesh with {faces.shape[0]} faces, but the head model "
                f"'{dataset['head_model']}' (mouth '{config.model.mouth}') here has {head.num_faces} different ones"
            )
        avatar = GaussianAvatar.for_model(head, config.model)
        avatar.load_state_dict(ckpt["avatar"])
        deformer = None
        if ckpt.get("deformer") is not None:
            deformer = MouthDeformer.for_head(head, int(ckpt["num_frames"]), config.model.mouth_deform)
            deformer.load_state_dict(ckpt["deformer"])
        info = RunInfo(
            run_dir=run_dir,
            checkpoint=path,
            step=int(ckpt["step"]),
            data_root=Path(dataset["root"]),
            head_model=str(dataset["head_model"]),
            background=[float(c) for c in dataset["background"]],
            resolution=dataset.get("resolution"),
            num_frames=int(ckpt["num_frames"]),
            timesteps={k: [int(t) for t in v] for k, v in dataset["timesteps"].items()},
            frame_params=dict(ckpt["frame_params"]),
            aps=dict(ckpt["aps"]),
            face_sets=ckpt["face_sets"],
            run_options=run_options,
        )
        _lay_held_out_over(info)
    except KeyError as err:
        raise RunError(f"{path}: checkpoint lacks the entry {err}") from err
    except (ValueError, RuntimeError) as err:
        if isinstance(err, RunError):
            raise
        raise RunError(f"{path}: cannot rebuild the avatar ({err})") from err
    head, avatar = head.to(device).eval(), avatar.to(device).eval()
    deformer = deformer.to(device).eval() if deformer is not None else None
    return LoadedRun(config, head, avatar, deformer, info)


def open_run(run_dir: str | os.PathLike, device: str = "auto", flame_dir: str | os.PathLike | None = None) -> LoadedRun:
    """load_run on the device a --device option names (auto: CUDA when available); RunError / OptionError
    on bad input."""
    from geoavatar.runtime import resolve_device

    try:
        torch_device = resolve_device(device)
    except ValueError as err:  # resolve_device's messages name --device
        raise OptionError(str(err)) from err
    return load_run(run_dir, torch_device, flame_dir=flame_dir)


def _head_options(info: RunInfo, flame_dir: str | os.PathLike | None) -> dict:
    """The head model's options of a dataset opened for the run: a FLAME run's FLAME folder."""
    return {"flame_dir": flame_dir or info.run_options.get("flame_dir")} if info.head_model == "flame" else {}


def open_clip_dataset(run: LoadedRun, data: str | os.PathLike,
                      flame_dir: str | os.PathLike | None = None) -> HeadAvatarDataset:
    """Every frame of another dataset of the run's person (a new clip, or the run's own without its split) at the
    run's resolution, decoded on demand: what `geoavatar track --avatar` fits."""
    return HeadAvatarDataset(open_subject(data), "all", DataConfig(resolution=run.info.resolution, cache="none"),
                             head_options=_head_options(run.info, flame_dir))


def open_run_dataset(run: LoadedRun, split: str, data: str | os.PathLike | None = None,
                     flame_dir: str | os.PathLike | None = None, resolution: int | None = None) -> HeadAvatarDataset:
    """A split of the dataset the run trained on, loaded as training loaded it (resolution, split rule).

    `data` overrides the dataset folder recorded in the run (a moved dataset); `resolution` the training
    resolution (longer side; images are never enlarged beyond their stored size). RunError when the folder
    is gone, belongs to another head model, or its frames no longer match the run."""
    info = run.info
    root = Path(data) if data is not None else info.data_root
    if not root.is_dir():
        raise RunError(f"{info.run_dir}: its dataset folder {root} is not found; pass --data DIR to point at it")
    config = DataConfig(resolution=resolution or info.resolution, test_frames=info.run_options.get("test_frames"))
    head_options = _head_options(info, flame_dir)
    try:
        subject = open_subject(root)
        dataset = HeadAvatarDataset(subject, split, config, head_options=head_options)
    except DatasetError as err:
        raise RunError(f"{info.run_dir}: cannot open its dataset: {err}") from err
    if subject.head_model != info.head_model:
        raise RunError(f"{root}: tracked with head model '{subject.head_model}', the run {info.run_dir} with "
                       f"'{info.head_model}'")
    if list(subject.timesteps) != info.timesteps["all"]:
        raise RunError(f"{root}: has {subject.num_timesteps} timesteps, the run {info.run_dir} was trained on "
                       f"{len(info.timesteps['all'])} different ones; the dataset changed since training")
    expected = info.timesteps.get(split) if split != "all" else info.timesteps["all"]
    if expected is not None and sorted(set(dataset.timesteps)) != sorted(set(expected)):
        raise RunError(f"{root}: its '{split}' split ({len(set(dataset.timesteps))} timesteps) differs from the one "
                       f"the run {info.run_dir} recorded ({len(set(expected))}); the dataset changed since training")
    return dataset


__all__ = [
    "APS_FILE", "CHECKPOINT_DIR", "CONFIG_FILE", "FINAL_CHECKPOINT", "LAST_CHECKPOINT", "LOG_FILE", "VAL_DIR",
    "FIELDS_ADDED_LATER", "FIELDS_REMOVED", "LoadedRun", "RemovedOptionWarning", "RunError", "RunInfo",
    "config_from_json", "config_to_dict", "dataclass_from_dict", "drop_removed_fields", "last_good_checkpoint",
    "load_checkpoint", "load_head_for", "load_run", "open_clip_dataset", "open_run", "open_run_dataset", "restore_state", "run_checkpoint_path",
    "save_checkpoint", "saved_step", "state_payload", "write_aps_report",
]
