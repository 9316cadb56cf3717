"""Generate a complete synthetic monocular dataset of a ground-truth actor (VHAP layout).

    generate_dataset(Path("data/synth0"), SynthConfig(subject=0, frames=300, size=512, seed=0))

Output (written through `geoavatar.data.layout.LayoutWriter`, so it appears atomically):

    transforms{,_train,_val,_test}.json, images/, fg_masks/, flame_param/, canonical_flame_param.npz,
    geoavatar.json   head_model "openhead", mouth "geoavatar", background = the plain background
                     colour (exact: a multiple of 1/255), source "geoavatar synth subject=K seed=S"
    flame_param_gt/  the exact ground-truth parameters, same npz layout as flame_param/
                     (flame_param/ = ground truth + tracker error unless tracking noise is off)
    synth.json       generator metadata: subject, motion segments, test start, noise model, timing
    transforms_novel.json  with novel_views: test timesteps (every `novel_every`-th) seen from extra
                     cameras (NOVEL_VIEWS: yaw +-30, +-60, pitch +-20 deg, turned about the head centre
                     of the frame, render.camera.orbit_viewmat), camera indices 1..6, images
                     images/<t>_<camera>.png, plus the dataset's own view of those timesteps (camera 0,
                     "front", the same files as the test split) as the reference; each frame carries
                     "view": {"name", "yaw", "pitch"}. The split `geoavatar eval --split novel` scores.
                     The lights stay in the room (fixed to the dataset camera) as in a capture rig: a
                     novel camera sees the shading the training frames show, from another side.
    preview.png      contact sheet (with --preview)

The written static_offset is zero: the hair, ears, glasses and beard of the actor are NOT in the
parameters (that is what the avatar has to learn).
"""

from __future__ import annotations

import json
import logging
import math
import multiprocessing
import time
import warnings
from concurrent.futures import ProcessPoolExecutor
from contextlib import closing
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from PIL import Image
from scipy.spatial.transform import Rotation

from geoavatar.data.layout import INFO_FILE, LayoutWriter, read_info
from geoavatar.data.splits import ShortVideoWarning
from geoavatar.data.synth.actor import HEAD_MODEL, MOUTH_KIND, Actor, actor_for_subject
from geoavatar.data.synth.motion import Motion, script_motion
from geoavatar.data.synth.render import ActorRenderer, Camera, frontal_camera, orbit_camera
from geoavatar.data.synth.subjects import Subject, get_subject
from geoavatar.data.synth.tracking import TrackingNoise, apply_tracking_noise
from geoavatar.errors import OptionError, disk_full_error, is_disk_full
from geoavatar.head.base import FLAME_EXPR_DIM, FLAME_SHAPE_DIM
from geoavatar.head.regions import skull_centre
from geoavatar.imaging import to_uint8
from geoavatar.runtime import num_threads

log = logging.getLogger(__name__)

SOURCE_PREFIX = "geoavatar synth"
META_FILE = "synth.json"
GT_DIR = "flame_param_gt"
PREVIEW_FILE = "preview.png"

# How the motion's share of head rotation is split between the root and the neck joint.
ROOT_SHARE = 0.4

# Semantic motion channels -> candidate expression-mode names of the head model (first match wins).
CHANNEL_NAMES: dict[str, tuple[str, ...]] = {
    "smile": ("smile",),
    "cheek_raise": ("cheek_raise", "eye_squint", "cheek_squint", "squint"),
    "brow_raise": ("brow_raise", "brows_raise", "brow_up", "surprise"),
    "eyes_wide": ("eyes_wide", "eye_wide", "eyes_open", "lids_raise"),
    "pucker": ("pucker", "lip_pucker", "kiss"),
    "brow_lower": ("brow_lower", "brows_lower", "frown", "brow_down"),
    "mouth_frown": ("mouth_frown", "frown", "lip_corner_down"),
    "mouth_stretch": ("mouth_stretch", "lip_stretch", "stretch", "grimace"),
    "nose_wrinkle": ("nose_wrinkle", "sneer", "disgust"),
    "upper_lip_raise": ("upper_lip_raise", "upper_lip_up", "lip_raise_upper"),
    "lip_funnel": ("lip_funnel", "funnel", "pucker"),
    "mouth_left": ("mouth_left", "mouth_pull_left"),
    "mouth_right": ("mouth_right", "mouth_pull_right"),
    "smile_left": ("smile_left", "mouth_smile_left"),
    "smile_right": ("smile_right", "mouth_smile_right"),
    "cheek_puff": ("cheek_puff", "puff"),
    "lip_press": ("lip_press", "lips_press", "mouth_press"),
    "brow_inner_raise": ("brow_inner_raise", "brow_inner_up"),
    "blink_left": ("blink_left", "eye_close_left", "left_blink"),
    "blink_right": ("blink_right", "eye_close_right", "right_blink"),
}
REQUIRED_CHANNELS = ("smile", "blink_left", "blink_right")

# Novel views (camera index, name, yaw, pitch in degrees about the head centre; + yaw: toward the camera's
# right = the subject's left, + pitch: from above). Camera 0 is the dataset's own camera.
NOVEL_SPLIT = "novel"
FRONT_VIEW = "front"
NOVEL_VIEWS: tuple[tuple[int, str, float, float], ...] = (
    (1, "yaw+30", 30.0, 0.0), (2, "yaw-30", -30.0, 0.0), (3, "yaw+60", 60.0, 0.0), (4, "yaw-60", -60.0, 0.0),
    (5, "pitch+20", 0.0, 20.0), (6, "pitch-20", 0.0, -20.0),
)


@dataclass
class SynthConfig:
    """What to generate. The subject is fixed by its index; the seed drives motion and tracker error."""

    subject: int = 0
    frames: int = 300
    size: int = 512
    seed: int = 0
    fps: float = 25.0
    fov_deg: float = 30.0  # vertical field of view (a webcam / phone front camera)
    ssaa: int = 2  # supersampling factor of the anti-aliasing
    tracking_noise: TrackingNoise = field(default_factory=TrackingNoise)
    png_compress_level: int = 1
    workers: int = field(default_factory=lambda: default_workers())  # rendering processes (1: inline)
    novel_views: bool = False  # also render test timesteps from the NOVEL_VIEWS cameras (transforms_novel.json)
    novel_every: int = 2  # every this many test timesteps get the novel views
    still_head: bool = False  # the head never turns or nods (motion.script_motion's still_head)
    sound: bool = False  # a voice whose sound is a known function of the mouth (synth/sound.py)


def check_output_folder(out: Path) -> bool:
    """Refuse to write over anything but an empty folder or an earlier synthetic dataset.

    Returns True when `out` exists and may be replaced. Raises OptionError naming --out otherwise.
    """
    out = Path(out)
    if not out.exists():
        return False
    if not out.is_dir():
        raise OptionError(f"--out {out} exists and is not a folder; choose another --out")
    if not any(out.iterdir()):
        return True
    if is_synth_dataset(out):
        return True
    raise OptionError(
        f"--out {out} is a non-empty folder that is not a dataset made by `geoavatar synth`; "
        "refusing to overwrite it. Choose an empty or new folder."
    )


def is_synth_dataset(root: Path) -> bool:
    root = Path(root)
    if not (root / INFO_FILE).is_file() or not (root / META_FILE).is_file():
        return False
    try:
        info = read_info(root)
    except ValueError:
        return False
    return info is not None and (info.source or "").startswith(SOURCE_PREFIX)


def expression_channels(head_expression_names: list[str] | tuple[str, ...]) -> dict[str, int]:
    """Semantic channel -> expression mode index of the head model (channels it lacks are left out)."""
    index = {name: i for i, name in enumerate(head_expression_names)}
    mapping = {}
    for channel, candidates in CHANNEL_NAMES.items():
        for name in candidates:
            if name in index:
                mapping[channel] = index[name]
                break
    missing = [c for c in REQUIRED_CHANNELS if c not in mapping]
    if missing:
        raise ValueError(f"the head model's expression modes lack {', '.join(missing)} "
                         f"(have: {', '.join(head_expression_names)}); the synthetic motion needs them")
    return mapping


def motion_to_params(motion: Motion, actor: Actor) -> tuple[dict[str, np.ndarray], dict[str, int]]:
    """Ground-truth parameters [N, ...] in the FLAME npz layout (model mode counts) from a motion."""
    n = motion.num_frames
    names = list(actor.head.metadata.get("expression_names", []))
    mapping = expression_channels(names)
    num_expr = actor.head.exprdirs.shape[-1]
    expr = np.zeros((n, num_expr), np.float32)
    channels = dict(motion.expressions)
    channels["blink_left"] = motion.blink_left
    channels["blink_right"] = motion.blink_right
    for channel, values in channels.items():
        if channel in mapping:
            expr[:, mapping[channel]] += values.astype(np.float32)
    euler = np.stack([motion.yaw, motion.pitch, motion.roll], axis=-1)  # [N, 3]
    rotation = Rotation.from_euler("YXZ", ROOT_SHARE * euler).as_rotvec()
    neck = Rotation.from_euler("YXZ", (1.0 - ROOT_SHARE) * euler).as_rotvec()
    jaw = np.zeros((n, 3))
    jaw[:, 0] = motion.jaw
    eye = Rotation.from_euler("YX", motion.gaze).as_rotvec()  # [N, 3]
    params = {
        "shape": actor.shape.copy(),
        "expr": expr,
        "rotation": rotation.astype(np.float32),
        "neck_pose": neck.astype(np.float32),
        "jaw_pose": jaw.astype(np.float32),
        "eyes_pose": np.concatenate([eye, eye], axis=1).astype(np.float32),
        "translation": motion.translation.astype(np.float32),
    }
    return params, mapping


def _frame_params(params: dict[str, np.ndarray], t: int) -> dict[str, np.ndarray]:
    return {k: (v if k == "shape" else v[t : t + 1]) for k, v in params.items()}


def _npz_arrays(params: dict[str, np.ndarray], t: int, static_offset: np.ndarray) -> dict[str, np.ndarray]:
    """One timestep in the VHAP npz layout (padded to FLAME sizes, as the writer pads flame_param/)."""
    out = {k: params[k][t : t + 1].astype(np.float32) for k in ("translation", "rotation", "neck_pose", "jaw_pose", "eyes_pose")}
    expr = np.zeros((1, FLAME_EXPR_DIM), np.float32)
    expr[0, : params["expr"].shape[1]] = params["expr"][t]
    shape = np.zeros(FLAME_SHAPE_DIM, np.float32)
    shape[: params["shape"].shape[0]] = params["shape"]
    out.update(expr=expr, shape=shape, static_offset=static_offset)
    return out


def _posed_vertices(actor: Actor, params: dict[str, np.ndarray], start: int, stop: int) -> torch.Tensor:
    batch = {k: torch.from_numpy(np.ascontiguousarray(v if k == "shape" else v[start:stop])) for k, v in params.items()}
    with torch.no_grad():
        return actor.model.forward_params(batch).vertices  # [B, V, 3]


def preview_frames(motion: Motion, count: int = 10) -> list[int]:
    """Frames for the contact sheet: spread over the sequence plus the widest-open mouths and the extremes."""
    n = motion.num_frames
    picks = set(np.linspace(0, n - 1, max(count - 4, 2)).round().astype(int).tolist())
    train, test = slice(0, motion.test_start), slice(motion.test_start, n)
    picks.add(int(np.argmax(motion.jaw[train])))
    picks.add(motion.test_start + int(np.argmax(motion.jaw[test])))
    picks.add(int(np.argmax(np.abs(motion.yaw[train]))))
    picks.add(motion.test_start + int(np.argmin(motion.yaw[test])))
    return sorted(picks)[:count + 2]


@dataclass
class _Scene:
    """What one dataset shows: the actor before its camera, the motion and the parameters it becomes."""

    actor: Actor
    camera: Camera  # the dataset's camera (camera 0)
    renderer: ActorRenderer
    motion: Motion
    gt: dict[str, np.ndarray]  # exact ground-truth parameters [N, ...] (flame_param_gt/)
    mapping: dict[str, int]  # motion channel -> expression mode of the head model
    written: dict[str, np.ndarray]  # ground truth + tracker error (flame_param/)
    static_offset: np.ndarray  # [1, V, 3] zeros: what the head model lacks is not in the parameters


def _check_config(config: SynthConfig) -> None:
    """OptionError naming the option for a config that cannot make a dataset."""
    if config.frames < 2:
        raise OptionError(f"--frames must be at least 2 (training and test frames), got {config.frames}")
    if config.size < 16:
        raise OptionError(f"--size must be at least 16 pixels, got {config.size}")
    if config.workers < 1:
        raise OptionError(f"workers must be at least 1, got {config.workers}")
    if config.novel_every < 1:
        raise OptionError(f"--novel-every must be at least 1, got {config.novel_every}")


def _stage_scene(subject: Subject, config: SynthConfig) -> _Scene:
    """The subject's actor, its camera and renderer, the scripted motion and its true and tracked parameters."""
    actor = actor_for_subject(subject.index)
    camera = frontal_camera(actor, config.size, config.fov_deg)
    renderer = ActorRenderer(actor, camera, subject.background_rgb, ssaa=config.ssaa)
    motion = script_motion(config.frames, config.seed, config.fps, still_head=config.still_head)
    gt, mapping = motion_to_params(motion, actor)
    written = apply_tracking_noise(gt, config.tracking_noise, config.fps, config.seed,
                                   num_expr_used=actor.head.exprdirs.shape[-1],
                                   num_shape_used=actor.head.shapedirs.shape[-1])
    static_offset = np.zeros((1, actor.num_model_vertices, 3), np.float32)
    return _Scene(actor, camera, renderer, motion, gt, mapping, written, static_offset)


def _layout_writer(out: Path, subject: Subject, config: SynthConfig, scene: _Scene, replace: bool) -> LayoutWriter:
    """The writer of the dataset's folder (its files appear at `out` on finish)."""
    return LayoutWriter(
        out, head_model=HEAD_MODEL, image_size=(config.size, config.size), shape=scene.written["shape"],
        static_offset=scene.static_offset, background=subject.background_rgb, mouth=MOUTH_KIND,
        source=f"{SOURCE_PREFIX} subject={config.subject} seed={config.seed}", overwrite=replace,
        png_compress_level=config.png_compress_level,
    )


def generate_dataset(out: Path, config: SynthConfig, preview: bool = False, progress: bool = True) -> Path:
    """Render and write the dataset to `out` (see the module docstring). Returns `out`."""
    started = time.perf_counter()
    out = Path(out)
    subject = get_subject(config.subject)
    _check_config(config)
    replace = check_output_folder(out)
    scene = _stage_scene(subject, config)
    writer = _layout_writer(out, subject, config, scene, replace)
    try:
        _write_contents(writer, subject, config, scene, preview, progress, started)
        with warnings.catch_warnings():
            # A short video holds out its last 25 %: expected here, the motion script is built for it.
            warnings.simplefilter("ignore", ShortVideoWarning)
            writer.finish()
    except OSError as err:  # the files beside LayoutWriter's (ground truth, preview, meta) on a full disk
        writer.abort()
        if is_disk_full(err):
            raise disk_full_error(out, err, f"{out} is unchanged" if out.exists() else "nothing was written") from err
        raise
    except BaseException:
        writer.abort()
        raise
    log.info("synthetic dataset written to %s in %.1f s", out, time.perf_counter() - started)
    return out


def _write_contents(writer: LayoutWriter, subject: Subject, config: SynthConfig, scene: _Scene, preview: bool,
                    progress: bool, started: float) -> None:
    """Everything of the dataset into the writer's folder, before it finishes: the frames, the novel views,
    synth.json, preview.png and the voice. `started`: perf_counter at the start (synth.json's render_seconds)."""
    (writer.tmp / GT_DIR).mkdir()
    novel = (novel_jobs(scene.actor, scene.camera, scene.gt, scene.motion.test_start, config)
             if config.novel_views else [])
    seen = set(preview_frames(scene.motion)) if preview else set()
    bar = _progress(config.frames + len(novel), progress)
    try:
        kept = _write_dataset_frames(writer, config, scene, seen, bar)
        _write_novel_frames(writer, config, scene, novel, bar)
    finally:
        bar.close()
    meta = _synth_meta(subject, config, scene, novel, time.perf_counter() - started)
    if preview:
        sheet = contact_sheet(scene.actor, scene.renderer, scene.motion, scene.gt, kept)
        sheet.save(writer.tmp / PREVIEW_FILE, optimize=True)
    if config.sound:
        meta["sound"] = _write_sound(writer.tmp, scene.motion, config)
    (writer.tmp / META_FILE).write_text(json.dumps(meta, indent=2) + "\n")


def _write_dataset_frames(writer: LayoutWriter, config: SynthConfig, scene: _Scene, seen: set[int],
                          bar) -> dict[int, np.ndarray]:
    """Render every timestep with the dataset camera and write it, its parameters and its ground truth.

    Returns the images (uint8 [H, W, 3]) of the timesteps in `seen`, for the contact sheet.
    """
    kept: dict[int, np.ndarray] = {}
    viewmat, K = scene.camera.viewmat, scene.camera.K
    jobs = [(t, 0, None) for t in range(config.frames)]
    with closing(_render_frames(scene.actor, scene.renderer, scene.gt, jobs, config.workers)) as frames:
        for t, _, image_u8, mask_u8 in frames:
            if t in seen:
                kept[t] = image_u8
            _write_frame(writer, t, image_u8, mask_u8, _frame_params(scene.written, t), viewmat, K,
                         _npz_arrays(scene.gt, t, scene.static_offset))
            bar.update(1)
    return kept


def _write_novel_frames(writer: LayoutWriter, config: SynthConfig, scene: _Scene,
                        novel: list[tuple[int, int, Camera]], bar) -> None:
    """List the novel split: each timestep of `novel` as the dataset camera sees it (the test split's image, as the
    front reference), then render and write its views from the novel cameras."""
    views = {index: (name, yaw, pitch) for index, name, yaw, pitch in NOVEL_VIEWS}
    for t in sorted({t for t, _, _ in novel}):
        writer.list_frame(NOVEL_SPLIT, t, 0, view={"name": FRONT_VIEW, "yaw": 0.0, "pitch": 0.0})
    cameras = {(t, index): cam for t, index, cam in novel}
    with closing(_render_frames(scene.actor, scene.renderer, scene.gt, novel, config.workers)) as frames:
        for t, index, image_u8, mask_u8 in frames:
            name, yaw, pitch = views[index]
            cam = cameras[(t, index)]
            writer.add_frame(t, image_u8, _frame_params(scene.written, t), cam.viewmat, cam.K, mask=mask_u8,
                             camera=index, split=NOVEL_SPLIT, view={"name": name, "yaw": yaw, "pitch": pitch})
            bar.update(1)


def _synth_meta(subject: Subject, config: SynthConfig, scene: _Scene, novel: list[tuple[int, int, Camera]],
                render_seconds: float) -> dict:
    """synth.json (without its "sound" entry): what was generated, how, and where the ground truth is."""
    motion, mapping = scene.motion, scene.mapping
    meta = {
        "generator": SOURCE_PREFIX,
        "subject": subject.summary(),
        "seed": config.seed,
        "frames": config.frames,
        "still_head": config.still_head,
        "fps": config.fps,
        "size": config.size,
        "fov_deg_vertical": config.fov_deg,
        "ssaa": config.ssaa,
        "test_start": motion.test_start,
        "segments": [{"start": a, "stop": b, "label": label} for a, b, label in motion.segments],
        "tracking_noise": config.tracking_noise.to_dict(),
        "expression_channels": {k: int(v) for k, v in mapping.items()},
        "channels_unmapped": sorted(set(motion.expressions) - set(mapping)),
        "actor": scene.actor.info,
        "ground_truth": f"{GT_DIR}/<timestep>.npz (flame_param/ = ground truth + tracker error)",
        "render_seconds": round(render_seconds, 2),
    }
    if config.novel_views:
        meta["novel_views"] = {
            "file": "transforms_novel.json", "timesteps": sorted({t for t, _, _ in novel}),
            "every": config.novel_every, "pivot": "head.regions.skull_centre of the true posed head, per frame",
            "lights": "fixed to the room (the dataset camera's axes), not to the novel camera",
            "views": [{"camera": i, "name": n, "yaw": y, "pitch": p} for i, n, y, p in NOVEL_VIEWS],
        }
    return meta


def _write_sound(folder: Path, motion: Motion, config: SynthConfig) -> dict:
    """The subject's voice into the dataset (data/sound.py's files): frame t shown at t / fps of it."""
    from geoavatar.data.sound import write_dataset_sound
    from geoavatar.data.synth.sound import speech_sound

    sound, activity = speech_sound(motion, config.seed)
    write_dataset_sound(folder, sound, {t: t / config.fps for t in range(config.frames)}, activity,
                        source=f"{SOURCE_PREFIX} voice subject={config.subject} seed={config.seed}")
    return {"file": "audio.wav", "speech_seconds": round(activity.speech_seconds, 2),
            "model": "source-filter voice: loudness and F1 from the jaw, F2 from the lips (data/synth/sound.py)"}


def novel_jobs(actor: Actor, camera: Camera, params: dict[str, np.ndarray], test_start: int,
               config: SynthConfig) -> list[tuple[int, int, Camera]]:
    """(timestep, camera index, camera) of every novel view: every `novel_every`-th test timestep seen by
    the dataset camera turned about the frame's head centre (head.regions.skull_centre of the true pose)."""
    out = []
    for t in range(test_start, config.frames, config.novel_every):
        centre = skull_centre(_posed_vertices(actor, params, t, t + 1)[0], actor.head)  # [3]
        for index, _, yaw, pitch in NOVEL_VIEWS:
            out.append((t, index, orbit_camera(camera, yaw, pitch, centre)))
    return out


def _write_frame(writer: LayoutWriter, t: int, image: np.ndarray, mask: np.ndarray, params: dict,
                 viewmat: torch.Tensor, K: torch.Tensor, gt_arrays: dict) -> None:
    writer.add_frame(t, image, params, viewmat, K, mask=mask)
    np.savez(writer.tmp / GT_DIR / f"{t:05d}.npz", **gt_arrays)


# --- frame rendering, in worker processes ----------------------------------------------------------
#
# Frames are independent, so they are rendered in parallel by forked worker processes, each with one
# torch thread (many small tensor ops parallelise poorly inside a frame, and OpenMP threads spin
# badly on a busy machine). Every frame is rendered single-threaded, in a worker or inline, so the
# bytes do not depend on the number of workers.

_STATE: dict = {}  # actor, renderer, ground truth: inherited by forked workers


def default_workers() -> int:
    """Worker processes for rendering: the cores this process may use (at most 8)."""
    from geoavatar.runtime import available_cores

    return max(1, min(8, available_cores()))


def _render_one(job: tuple[int, int, Camera | None]) -> tuple[int, int, np.ndarray, np.ndarray]:
    actor, renderer, params = _STATE["actor"], _STATE["renderer"], _STATE["params"]
    t, index, camera = job
    vertices = _posed_vertices(actor, params, t, t + 1)[0]  # [V, 3], one frame per forward pass
    image, mask = renderer.render(vertices, camera)
    return t, index, to_uint8(image), to_uint8(mask)


def _worker_init() -> None:
    torch.set_num_threads(1)


def _render_frames(actor: Actor, renderer: ActorRenderer, params: dict[str, np.ndarray],
                   jobs: list[tuple[int, int, Camera | None]], workers: int):
    """Yield (t, camera index, image uint8 [H, W, 3], mask uint8 [H, W]) for each job (timestep, camera
    index, camera; None: the dataset camera), in order."""
    _STATE.update(actor=actor, renderer=renderer, params=params)
    try:
        if workers > 1 and len(jobs) > 1 and "fork" in multiprocessing.get_all_start_methods():
            context = multiprocessing.get_context("fork")
            pool = ProcessPoolExecutor(max_workers=min(workers, len(jobs)), mp_context=context, initializer=_worker_init)
            try:
                yield from pool.map(_render_one, jobs, chunksize=1)
            finally:  # on an error or Ctrl-C, drop the frames not started yet
                pool.shutdown(wait=True, cancel_futures=True)
        else:
            with num_threads(1):
                for job in jobs:
                    yield _render_one(job)
    finally:
        _STATE.clear()


class _NoBar:
    def update(self, n: int) -> None:
        pass

    def close(self) -> None:
        pass


def _progress(total: int, enabled: bool):
    if not enabled:
        return _NoBar()
    from tqdm import tqdm

    return tqdm(total=total, desc="synth", unit="frame")


# --- preview -------------------------------------------------------------------------------------


def contact_sheet(actor: Actor, renderer: ActorRenderer, motion: Motion, params: dict[str, np.ndarray],
                  frames: dict[int, np.ndarray]) -> Image.Image:
    """Frames across the sequence (labelled with segment, yaw, jaw) plus side views of the actor and of
    the bare head model with the same parameters (shows the hair volume, ears, glasses, beard)."""
    from PIL import ImageDraw

    from geoavatar.geometry import camera_centre
    from geoavatar.render.camera import intrinsics_from_fov, look_at
    from geoavatar.render.mesh import Lighting, render_mesh

    tiles: list[tuple[np.ndarray, str]] = []
    for t in sorted(frames):
        label = next((lab for a, b, lab in motion.segments if a <= t < b), "")
        tiles.append((frames[t], f"#{t} {label}  yaw {math.degrees(motion.yaw[t]):+.0f}  jaw {motion.jaw[t]:.2f}"))
    # A close-up of the widest-open mouth (teeth, tongue, palate).
    t_open = int(np.argmax(motion.jaw))
    posed = _posed_vertices(actor, params, t_open, t_open + 1)[0]
    lips = np.concatenate([np.asarray(actor.head.lip_ring_upper), np.asarray(actor.head.lip_ring_lower)])
    mouth = posed[torch.from_numpy(lips)].mean(0).double()  # [3]
    close = Camera(
        viewmat=look_at(mouth + torch.tensor([0.0, 0.03, 0.3], dtype=torch.float64), mouth).float(),
        K=intrinsics_from_fov(18.0, renderer.camera.width, renderer.camera.height), width=renderer.camera.width,
        height=renderer.camera.height,
    )
    image, _ = renderer.render(posed, close, lights_on_camera=True)
    tiles.append((to_uint8(image), f"#{t_open} mouth close-up, jaw {motion.jaw[t_open]:.2f}"))
    # Side views of the neutral actor vs the bare head model (hair volume, ears, glasses, beard).
    neutral = {k: (v if k == "shape" else np.zeros_like(v[:1])) for k, v in params.items()}
    neutral["shape"] = params["shape"]
    vertices = _posed_vertices(actor, neutral, 0, 1)[0]
    target_y = float(camera_centre(renderer.camera.viewmat.double())[1])  # the camera's height
    for yaw in (75.0, -110.0):
        side = orbit_camera(renderer.camera, yaw, 0.0, torch.tensor([0.0, target_y, 0.0]))
        image, _ = renderer.render(vertices, side, lights_on_camera=True)
        tiles.append((to_uint8(image), f"actor, side {yaw:+.0f} deg"))
        head = vertices[: actor.num_head_vertices]
        bare = render_mesh(head, torch.from_numpy(actor.head.faces), side.viewmat, side.K, side.width, side.height,
                           lighting=Lighting(), background=(0.85, 0.85, 0.85), ssaa=2)
        tiles.append((to_uint8(bare.image), "head model alone, same view"))
    size = 240
    columns = 5
    rows = math.ceil(len(tiles) / columns)
    sheet = Image.new("RGB", (columns * size, rows * (size + 14)), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    for i, (pixels, label) in enumerate(tiles):
        x, y = (i % columns) * size, (i // columns) * (size + 14)
        sheet.paste(Image.fromarray(pixels).resize((size, size), Image.LANCZOS), (x, y + 14))
        draw.text((x + 3, y + 1), label, fill=(0, 0, 0))
    return sheet


__all__ = [
    "SynthConfig", "generate_dataset", "check_output_folder", "is_synth_dataset", "motion_to_params",
    "expression_channels", "contact_sheet", "preview_frames", "META_FILE", "GT_DIR",
    "PREVIEW_FILE", "NOVEL_SPLIT", "NOVEL_VIEWS", "FRONT_VIEW", "novel_jobs",
]
