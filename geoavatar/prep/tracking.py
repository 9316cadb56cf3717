"""Fit a head model to 2D landmarks over a whole video: batched, robust, temporally smooth, on CPU.

    model = landmark_head(load_head_data("openhead"))         # only the vertices landmarks need
    result = track(model, landmarks [T, 478, 2], confidence [T], K0 [T, 3, 3], TrackingConfig())

Unknowns: one identity `shape` (the model's leading modes), per frame `rotation`, `translation`,
`neck_pose`, `jaw_pose`, `eyes_pose`, `expr`, one focal length shared by the video, and (with an
`offset_map`) one smooth static offset of the mesh (geoavatar.head.smooth_offset), VHAP's
`static_offset`: the identity modes of a head model do not reach every face. The camera is
fixed (VHAP's monocular convention: a fixed camera, a moving head): it sits at (0, 0, D) on the +z
axis looking at the origin (OpenCV axes: image x = world +x, image y = world -y), D being the median
head distance found at initialisation, so translations stay small.

Loss (all terms are means over frames, residuals in units of the per-frame face size):
- data: pseudo-Huber (delta = `huber`) of the 2D reprojection error of every embedded landmark,
  weighted per landmark group (face oval and brows lower: their MediaPipe points slide along the
  contour) and per frame by the landmark confidence;
- priors: L2 on shape, expression, neck, eyes and the jaw's sideways components, L2 and membrane
  energy of the static offset; the jaw's opening
  angle is kept in [0, `jaw_max`] by a squared hinge; both eyes look alike (L2 of their difference);
  a weak log-normal prior on the focal length (it trades off with distance in a monocular video);
- temporal smoothness: first and second differences of pose, jaw, eyes and expression.

Coarse to fine: (1) rigid pose from the stable landmarks (eye corners, nose, brows, upper face
oval) with the neutral head, (2) everything. Adam over all frames at once; MediaPipe's z is not used.
The model is reduced to the vertices the landmark faces touch plus five virtual vertices that
carry the joint regressor (linear in the shape and expression coefficients), and posed with
HeadModel's batched vertex-subset mode (`forward(..., vertex_ids=model.landmark_vertex_ids)`), so
the forward pass is exact and costs O(landmarks), not O(mesh).
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from geoavatar.head import landmarks_mediapipe as mpids
from geoavatar.head.base import HeadModel, HeadModelData
from geoavatar.head.params import HeadParams
from geoavatar.head.smooth_offset import SmoothOffset
from geoavatar.workers import split_range
from geoavatar.render.camera import focal_length, project

# Landmark groups: weight in the data term, and whether the rigid stage uses them.
GROUP_WEIGHTS = {
    "lips": 1.0, "eyes": 1.0, "irises": 0.5, "nose": 1.0, "brows": 0.5, "face_oval_upper": 0.3, "face_oval_lower": 0.3,
}
RIGID_GROUPS = ("eyes", "nose", "brows", "face_oval_upper")
# Frames whose data term is differentiated at once (the same energy and step; a long video's graph stays bounded).
DATA_CHUNK = 1024


def _group_of() -> dict[int, str]:
    groups: dict[int, str] = {}
    for name, ids in mpids.CONTOURS.items():
        for i in ids:
            if name.startswith("lips"):
                groups[i] = "lips"
            elif "iris" in name:
                groups[i] = "irises"
            elif "eye" in name:
                groups[i] = "eyes"
            elif "brow" in name:
                groups[i] = "brows"
            elif name.startswith("nose"):
                groups[i] = "nose"
    oval = list(mpids.FACE_OVAL)
    for i in oval:  # upper = above the ear line (the oval's widest points 234 / 454), ids from the reference face
        groups[i] = "face_oval_upper" if mpids.REFERENCE_FACE.get(i, (0, 0, 0))[1] > -150 else "face_oval_lower"
    return groups


GROUP_OF = _group_of()


@dataclass
class TrackingConfig:
    """Weights and schedule of the landmark fitter (defaults tuned on real talking-head videos)."""

    rigid_steps: int = 100
    full_steps: int = 300
    lr: float = 0.02
    rigid_lr: float = 0.05  # the rigid stage starts from a frontal pose: large turns need large steps
    huber: float = 0.005  # pseudo-Huber delta, in face sizes
    fov_deg: float = 25.0  # initial / prior field of view across the crop's longer side (before the crop: see pipeline)
    focal_prior: float = 1e-4  # weight of (log f - log f0)^2
    fit_focal: bool = True
    num_shape: int | None = None  # leading identity modes to fit (None: all of the model's, at most 100)
    num_expr: int | None = None  # leading expression modes to fit (None: all, at most 100)
    w_shape: float = 1e-5
    w_expr: float = 2e-5
    w_neck: float = 1e-2
    w_eyes: float = 1e-4
    w_eyes_equal: float = 1e-2
    w_jaw_side: float = 1e-2
    w_jaw_range: float = 1.0
    jaw_max: float = 0.5  # rad
    w_smooth_pose: float = 1e-3  # first differences of rotation (rad) and translation (in head sizes)
    w_smooth_expr: float = 1e-4
    w_smooth_jaw: float = 1e-2
    w_smooth_eyes: float = 1e-3
    w_accel: float = 1e-2  # second differences of rotation / translation
    head_size: float = 0.2  # m: translation differences are measured in this unit
    # Smooth static offset of the mesh (one per video, see geoavatar.head.smooth_offset): the
    # person's face is not the head model's; without it, errors grow with the head's yaw.
    fit_static_offset: bool = True
    w_static_offset: float = 1e-6  # weight of the mean squared offset, in cm^2
    w_static_smooth: float = 2e-7  # weight of the offset field's membrane energy (sum over edges), in cm^2
    offset_decay: float = 0.05  # fade of the offset away from the landmarks (see smooth_offset)


@dataclass
class TrackingResult:
    params: dict[str, np.ndarray]  # shape [S]; expr [T,E]; rotation, neck_pose, jaw_pose, translation [T,3]; eyes_pose [T,6];
    #                                static_offset [V, 3] (the full mesh's) when fitted
    focal: float  # pixels of the crop
    viewmat: np.ndarray  # [4, 4] world-to-camera (OpenCV), the same for every frame
    K: np.ndarray  # [T, 3, 3]
    projected: np.ndarray  # [T, L, 2] pixels of the model's landmarks
    landmark_ids: np.ndarray  # [L] MediaPipe ids of the embedded landmarks
    errors: np.ndarray  # [T] median over landmarks of the 2D error / face width
    log: list[str] = field(default_factory=list)
    model_static_offset: np.ndarray | None = None  # [U + J, 3] the static offset of the fitted (landmark) model's vertices


def landmark_head(data: HeadModelData) -> HeadModel:
    """A HeadModel holding only the vertices of the landmark faces plus 5 joint-carrier vertices.

    Its landmarks equal the full model's exactly: joints are linear in the shaped vertices, so the
    virtual vertex j carries row j of the joint regressor applied to template, shape and expression
    bases, and the reduced j_regressor picks those vertices.
    """
    if data.landmark_faces is None:
        raise ValueError(f"head model '{data.name}' has no landmark embedding")
    used = np.unique(data.faces[data.landmark_faces].ravel())  # [U]
    remap = np.full(data.num_vertices, -1, np.int64)
    remap[used] = np.arange(len(used))
    jr = data.j_regressor  # [J, V]
    num_joints = jr.shape[0]

    def with_joints(vertex_array: np.ndarray) -> np.ndarray:  # [V, 3, K] or [V, 3] -> [U + J, ...]
        joint_rows = np.tensordot(jr, vertex_array, axes=(1, 0))  # [J, 3, K]
        return np.concatenate([vertex_array[used], joint_rows], 0).astype(np.float32)

    lbs = np.concatenate([data.lbs_weights[used], np.eye(num_joints, dtype=np.float32)[[0] * num_joints]], 0)
    posedirs = None
    if data.posedirs is not None:
        posedirs = np.concatenate([data.posedirs[used], np.zeros((num_joints, *data.posedirs.shape[1:]), np.float32)], 0)
    reduced_jr = np.zeros((num_joints, len(used) + num_joints), np.float32)
    reduced_jr[:, len(used):] = np.eye(num_joints)
    faces = remap[data.faces[data.landmark_faces]]  # [L, 3]
    reduced = HeadModelData(
        name=data.name, v_template=with_joints(data.v_template), faces=faces,
        shapedirs=with_joints(data.shapedirs), exprdirs=with_joints(data.exprdirs), j_regressor=reduced_jr,
        lbs_weights=lbs.astype(np.float32), posedirs=posedirs, landmark_ids=data.landmark_ids,
        landmark_faces=np.arange(len(faces)), landmark_bary=data.landmark_bary,
        metadata={"reduced_from": data.name, "vertex_ids": used},  # mesh ids of the first U vertices
    )
    return HeadModel(reduced)


def _rigid_only(params: HeadParams) -> HeadParams:
    """Only rotation and translation: every other parameter zero (and cut from the graph)."""
    return params.map(lambda value: value.detach() * 0).replace(rotation=params.rotation, translation=params.translation)


def camera_viewmat(distance: float) -> np.ndarray:
    """World-to-camera [4, 4] (OpenCV) of the fixed camera at (0, 0, distance) looking at the origin."""
    viewmat = np.diag([1.0, -1.0, -1.0, 1.0])
    viewmat[2, 3] = distance
    return viewmat


def _pseudo_huber(x: Tensor, delta: float) -> Tensor:
    return delta * delta * (torch.sqrt(1.0 + (x / delta) ** 2) - 1.0)


class _Fit(torch.nn.Module):
    def __init__(self, frames: int, num_shape: int, num_expr: int, focal: float, translation: Tensor,
                 offset_rows: Tensor | None, offset_energy: Tensor | None):
        super().__init__()
        # Free static offsets theta [P, 3] in cm (Adam's steps are ~lr in the parameter's unit) and
        # their map to the reduced model's vertices [U + J, P]; the field's membrane energy [P, P].
        self.offset_rows, self.offset_energy = offset_rows, offset_energy
        self.offset_theta = None if offset_rows is None else torch.nn.Parameter(torch.zeros(offset_rows.shape[1], 3))
        z = lambda *s: torch.nn.Parameter(torch.zeros(*s, dtype=torch.float32))  # noqa: E731
        self.shape, self.expr = z(num_shape), z(frames, num_expr)
        self.rotation, self.neck_pose, self.jaw_pose, self.eyes_pose = z(frames, 3), z(frames, 3), z(frames, 3), z(frames, 6)
        self.translation = torch.nn.Parameter(translation.clone().float())
        self.log_focal = torch.nn.Parameter(torch.tensor(math.log(focal), dtype=torch.float32))

    def params(self) -> HeadParams:
        static = None
        if self.offset_theta is not None:
            static = (0.01 * (self.offset_rows @ self.offset_theta))[None]  # [1, U + J, 3] metres
        return HeadParams(shape=self.shape, expr=self.expr, rotation=self.rotation, neck_pose=self.neck_pose,
                          jaw_pose=self.jaw_pose, eyes_pose=self.eyes_pose, translation=self.translation,
                          static_offset=static)


def _intrinsics(focal: Tensor, principal: Tensor) -> Tensor:
    """K [T, 3, 3] from a shared focal (scalar tensor) and per-frame principal points [T, 2]."""
    T = principal.shape[0]
    K = torch.zeros(T, 3, 3, dtype=principal.dtype)
    K[:, 0, 0] = focal
    K[:, 1, 1] = focal
    K[:, :2, 2] = principal
    K[:, 2, 2] = 1.0
    return K


def _diff_penalty(x: Tensor, order: int = 1) -> Tensor:
    for _ in range(order):
        x = x[1:] - x[:-1]
    return (x ** 2).sum(-1).mean() if x.shape[0] > 0 else x.new_zeros(())


def _data_residuals(model: HeadModel, params: HeadParams, viewmat: Tensor, K: Tensor, target: Tensor,
                    size: Tensor) -> Tensor:
    """[T, L, 2] the 2D reprojection residuals of the embedded landmarks in face sizes.

    target [T, L, 2] pixels, size [T] face sizes (pixels), K [T, 3, 3]."""
    landmarks = model.forward_params(params, vertex_ids=model.landmark_vertex_ids).landmarks  # [T, L, 3]
    pixels, _ = project(landmarks, viewmat, K)  # [T, L, 2]
    return (pixels - target) / size[:, None, None]


def _data_term(model: HeadModel, params: HeadParams, viewmat: Tensor, K: Tensor, target: Tensor, size: Tensor,
               weights: Tensor, conf: Tensor, huber: float) -> Tensor:
    """Confidence-weighted mean over frames of the per-landmark-weighted pseudo-Huber 2D reprojection error.

    target [T, L, 2] pixels, size [T] face sizes (pixels), weights [L], conf [T], K [T, 3, 3]."""
    residual = _data_residuals(model, params, viewmat, K, target, size).norm(dim=-1)  # [T, L]
    data = (_pseudo_huber(residual, huber) * weights).sum(1) / weights.sum()  # [T]
    return (data * conf).sum() / conf.sum()


def _pose_smoothness(p: HeadParams, config: TrackingConfig) -> dict[str, Tensor]:
    """First and second differences of the head's rotation and translation over the frames of `p`."""
    unit = config.head_size
    return {
        "smooth_pose": config.w_smooth_pose * (_diff_penalty(p.rotation) + _diff_penalty(p.translation / unit)),
        "accel": config.w_accel * (_diff_penalty(p.rotation, 2) + _diff_penalty(p.translation / unit, 2)),
    }


def _frame_priors(p: HeadParams, config: TrackingConfig) -> dict[str, Tensor]:
    """Per-frame priors (means over frames): expression, neck, eyes (and alike), jaw (sideways, opening range)."""
    jaw, eyes = p.jaw_pose, p.eyes_pose
    return {
        "expr": config.w_expr * (p.expr ** 2).sum(-1).mean(),
        "neck": config.w_neck * (p.neck_pose ** 2).sum(-1).mean(),
        "eyes": config.w_eyes * (eyes ** 2).sum(-1).mean() + config.w_eyes_equal * ((eyes[:, :3] - eyes[:, 3:]) ** 2).sum(-1).mean(),
        "jaw": config.w_jaw_side * (jaw[:, 1:] ** 2).sum(-1).mean()
        + config.w_jaw_range * (torch.relu(-jaw[:, 0]) ** 2 + torch.relu(jaw[:, 0] - config.jaw_max) ** 2).mean(),
    }


def _motion_smoothness(p: HeadParams, config: TrackingConfig) -> Tensor:
    """First differences of expression, jaw, eyes and neck over the frames of `p`."""
    return (config.w_smooth_expr * _diff_penalty(p.expr) + config.w_smooth_jaw * _diff_penalty(p.jaw_pose)
            + config.w_smooth_eyes * _diff_penalty(p.eyes_pose) + config.w_smooth_pose * _diff_penalty(p.neck_pose))


def crop_principal_point(box: np.ndarray, frame_size: tuple[int, int], crop_size: int) -> np.ndarray:
    """[2] the source frame's centre (the principal point) in the pixels of the square crop `box` (cx, cy, side)
    of a frame of `frame_size` (w, h), resized to `crop_size`."""
    from geoavatar.prep.video import crop_intrinsics

    scale, ox, oy = crop_intrinsics(box, crop_size)
    return np.array([scale * (frame_size[0] / 2 - ox), scale * (frame_size[1] / 2 - oy)])


def track_crops(
    model: HeadModel,
    data: HeadModelData,  # the full head model (the smooth static offset lives on its mesh)
    landmarks: np.ndarray,  # [T, 478, >=2] filtered landmarks, crop pixels
    confidence: np.ndarray,  # [T]
    boxes: np.ndarray,  # [T, 3] the square crops (cx, cy, side; one side for the video) in source pixels
    frame_size: tuple[int, int],  # (w, h) of the source frames
    crop_size: int,
    config: TrackingConfig,
    progress=None,
) -> TrackingResult:
    """`track` on frames cut from a video with square crops: principal points from the crops, the initial
    focal (fov_deg across the source frame's longer side, in crop pixels), the smooth static offset's
    handles (the mesh vertices under the landmarks, the ones the landmark-only model keeps). Prepare's
    tracking stage and drive's identity stage."""
    from geoavatar.head.smooth_offset import smooth_offset
    from geoavatar.prep.video import crop_intrinsics

    principal = np.array([crop_principal_point(box, frame_size, crop_size) for box in boxes])  # [T, 2]
    scale = crop_intrinsics(boxes[-1], crop_size)[0]
    focal = focal_length(math.radians(config.fov_deg), scale * max(frame_size))
    offset_map = None
    if config.fit_static_offset:
        offset_map = smooth_offset(data, model.data.metadata["vertex_ids"], decay=config.offset_decay)
    with torch.enable_grad():
        return track(model, landmarks, confidence, principal, crop_size, config, focal_init=focal, progress=progress,
                     offset_map=offset_map)


@dataclass
class _LandmarkData:
    """What `track` fits to, as tensors: the embedded landmarks' detections and their weights."""

    ids: np.ndarray  # [L] MediaPipe ids of the model's embedded landmarks
    target: Tensor  # [T, L, 2] detected pixels (crop)
    size: Tensor  # [T] face size in pixels (forehead to chin), >= 1
    confidence: Tensor  # [T] in [0.05, 1]: a low weight, never zero
    weights: Tensor  # [L] per landmark group (GROUP_WEIGHTS)
    rigid_mask: Tensor  # [L] 1 for the groups the rigid stage uses (RIGID_GROUPS)

    @classmethod
    def of(cls, model: HeadModel, landmarks: np.ndarray, confidence: np.ndarray) -> "_LandmarkData":
        ids = model.landmark_ids.cpu().numpy()  # [L]
        target = torch.as_tensor(landmarks[:, ids, :2], dtype=torch.float32)
        size = torch.as_tensor(np.linalg.norm(landmarks[:, 10, :2] - landmarks[:, 152, :2], axis=-1), dtype=torch.float32)
        groups = [GROUP_OF.get(int(i), "face_oval_lower") for i in ids]
        return cls(ids, target, size.clamp_min(1.0), torch.as_tensor(confidence, dtype=torch.float32).clamp(0.05, 1.0),
                   torch.tensor([GROUP_WEIGHTS[g] for g in groups], dtype=torch.float32),
                   torch.tensor([g in RIGID_GROUPS for g in groups], dtype=torch.float32))


def _initial_translation(model: HeadModel, target: Tensor, principal: Tensor, focal: float) -> tuple[Tensor, float]:
    """(translation [T, 3], camera distance): the neutral head placed under each frame's landmarks, its depth from
    the ratio of the model's and the image's landmark spread; the camera at the median depth."""
    with torch.no_grad():
        neutral = model.template_output().landmarks[0]  # [L, 3] (unbatched call gives [1, L, 3])
        neutral = neutral.reshape(-1, 3)
        model_xy = neutral[:, :2] - neutral[:, :2].mean(0)
        model_spread = model_xy.norm(dim=-1).mean()
        image_centroid = target.mean(1)  # [T, 2]
        image_spread = (target - image_centroid[:, None]).norm(dim=-1).mean(1)  # [T]
        depth = focal * model_spread / image_spread  # [T] camera distance of the head
        distance = float(depth.median())
        xy = (image_centroid - principal) * depth[:, None] / focal  # camera-frame x, y (y down)
        centre = neutral.mean(0)
        translation = torch.stack([xy[:, 0] - centre[0], -xy[:, 1] - centre[1], distance - depth - centre[2]], -1)
    return translation, distance


@dataclass
class _TrackingEnergy:
    """`track`'s energy over the unknowns `fit` (see the module docstring) and the Adam stages that lower it."""

    model: HeadModel
    fit: _Fit
    data: _LandmarkData
    principal: Tensor  # [T, 2]
    viewmat: Tensor  # [4, 4]
    focal_init: float
    config: TrackingConfig
    chunks: list[slice]  # the frames whose data term is differentiated at once (DATA_CHUNK)
    log: list[str] = field(default_factory=list)

    def data_term(self, stage: str, rows: slice) -> Tensor:
        """The data term's share of the frames `rows`: their confidence-weighted sum over all frames' confidence."""
        data, config = self.data, self.config
        p = self.fit.params().rows(rows)
        posed = _rigid_only(p) if stage == "rigid" else p
        K = _intrinsics(self.fit.log_focal.exp(), self.principal[rows])
        w = data.weights * (data.rigid_mask if stage == "rigid" else 1.0)
        share = data.confidence[rows].sum() / data.confidence.sum()
        return _data_term(self.model, posed, self.viewmat, K, data.target[rows], data.size[rows], w,
                          data.confidence[rows], config.huber) * share

    def loss_terms(self, stage: str, data: bool = True) -> dict[str, Tensor]:
        fit, config = self.fit, self.config
        p = fit.params()
        terms = {"data": self.data_term(stage, slice(None))} if data else {}
        terms.update(_pose_smoothness(p, config))
        if stage == "rigid":
            return terms
        terms.update({
            "shape": config.w_shape * (p.shape ** 2).sum(),
            **_frame_priors(p, config),
            "focal": config.focal_prior * (fit.log_focal - math.log(self.focal_init)) ** 2,
            "static_offset": config.w_static_offset * (fit.offset_theta ** 2).sum(-1).mean()
            + config.w_static_smooth * (fit.offset_theta * (fit.offset_energy @ fit.offset_theta)).sum()
            if fit.offset_theta is not None else torch.zeros(()),
            "smooth": _motion_smoothness(p, config),
        })
        return terms

    def backward(self, stage: str) -> dict[str, Tensor]:
        """The energy's gradient into the unknowns; returns its terms."""
        if len(self.chunks) == 1:
            terms = self.loss_terms(stage)
            sum(terms.values()).backward()
            return terms
        # the data term's graph chunk by chunk: over a long video's frames at once it would take gigabytes
        data = torch.zeros(())
        for rows in self.chunks:
            term = self.data_term(stage, rows)
            term.backward()
            data = data + term.detach()
        terms = self.loss_terms(stage, data=False)
        sum(terms.values()).backward()
        return {"data": data, **terms}

    def run(self, stage: str, steps: int, parameters: list[Tensor], lr: float, progress) -> None:
        """`steps` Adam steps on `parameters`, the rate decaying to a tenth; logs the last step's terms."""
        if steps <= 0:
            return
        optimizer = torch.optim.Adam(parameters, lr=lr)
        schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda s: 0.1 ** (s / steps))
        for _ in range(steps):
            optimizer.zero_grad(set_to_none=True)
            terms = self.backward(stage)
            optimizer.step()
            schedule.step()
            if progress is not None:
                progress(1, stage)
        self.log.append(f"{stage}: {steps} steps, " + ", ".join(f"{k} {float(v.detach()):.3e}" for k, v in terms.items()))


def _tracking_result(energy: _TrackingEnergy, landmarks: np.ndarray, offset_map: SmoothOffset | None) -> TrackingResult:
    """The fit read out: parameters (the static offset on the full mesh), camera, reprojected landmarks, errors."""
    fit, model, data = energy.fit, energy.model, energy.data
    with torch.no_grad():
        params = fit.params()
        K = _intrinsics(fit.log_focal.exp(), energy.principal)
        posed = model.forward_params(params, vertex_ids=model.landmark_vertex_ids).landmarks
        pixels, _ = project(posed, energy.viewmat, K)  # [T, L, 2]
        width = np.linalg.norm(landmarks[:, 234, :2] - landmarks[:, 454, :2], axis=-1)  # [T] cheek to cheek
        err = (pixels - data.target).norm(dim=-1).numpy()  # [T, L]
        errors = np.median(err, axis=1) / np.maximum(width, 1e-6)
    model_static_offset = None if params.static_offset is None else params.static_offset[0].detach().numpy().copy()
    values = {k: v.detach().numpy().copy() for k, v in params.to_npz().items()}
    if fit.offset_theta is not None:
        values["static_offset"] = offset_map.extend(0.01 * fit.offset_theta.detach().numpy()).astype(np.float32)  # [V, 3]
    return TrackingResult(params=values, focal=float(fit.log_focal.detach().exp()),
                          viewmat=energy.viewmat.numpy().astype(np.float64), K=K.numpy().astype(np.float64),
                          projected=pixels.numpy(), landmark_ids=data.ids, errors=errors, log=energy.log,
                          model_static_offset=model_static_offset)


def track(
    model: HeadModel,
    landmarks: np.ndarray,  # [T, 478, >=2] detected landmarks, crop pixels
    confidence: np.ndarray,  # [T] in [0, 1]
    principal: np.ndarray,  # [T, 2] principal point per frame (crop pixels)
    image_size: int,  # crop side in pixels
    config: TrackingConfig = TrackingConfig(),
    focal_init: float | None = None,
    progress=None,  # callable(steps_done, stage_name) after each step, or None
    offset_map: SmoothOffset | None = None,  # the full model's smooth offsets (fitted when config says so)
) -> TrackingResult:
    """Fit `model` to the landmarks of all frames at once; see the module docstring."""
    T = landmarks.shape[0]
    if T == 0:
        raise ValueError("track: no frames")
    data = _LandmarkData.of(model, landmarks, confidence)
    principal_t = torch.as_tensor(principal, dtype=torch.float32)  # [T, 2]
    f0 = focal_init or focal_length(math.radians(config.fov_deg), image_size)
    translation, distance = _initial_translation(model, data.target, principal_t, f0)
    rows = energy = None
    if config.fit_static_offset and offset_map is not None:
        rows = torch.as_tensor(offset_rows(offset_map, model), dtype=torch.float32)
        energy = torch.as_tensor(offset_map.energy, dtype=torch.float32)
    fit = _Fit(T, min(model.num_shape, config.num_shape or 100), min(model.num_expr, config.num_expr or 100), f0,
               translation, rows, energy)
    chunks = [slice(a, b) for a, b in split_range(T, math.ceil(T / DATA_CHUNK))]
    viewmat = torch.as_tensor(camera_viewmat(distance), dtype=torch.float32)
    problem = _TrackingEnergy(model, fit, data, principal_t, viewmat, f0, config, chunks)
    # Translation steps are ~1 cm per unit lr at lr 0.02: scale translation by head size via its lr.
    problem.run("rigid", config.rigid_steps, [fit.rotation, fit.translation], config.rigid_lr, progress)
    full = [fit.shape, fit.expr, fit.rotation, fit.neck_pose, fit.jaw_pose, fit.eyes_pose, fit.translation]
    if config.fit_focal:
        full.append(fit.log_focal)
    if fit.offset_theta is not None:
        full.append(fit.offset_theta)
    problem.run("full", config.full_steps, full, config.lr, progress)
    return _tracking_result(problem, landmarks, offset_map)


# Solvers of OnlineFit and their default iterations per frame (about the same time per frame; see OnlineFit).
ONLINE_SOLVERS = {"gauss_newton": 2, "lbfgs": 8}
ONLINE_KEYS = ("expr", "rotation", "neck_pose", "jaw_pose", "eyes_pose", "translation")  # what OnlineFit fits
FD_STEP = 1e-6  # forward-difference step of OnlineFit's Jacobian (float64; the unknowns are radians, metres, ~N(0, 1))


class OnlineFit:
    """Frame-by-frame continuation of `track` for live video: after `track` fitted a video's first frames
    (identity, static offset and focal, then frozen), each new frame's pose, jaw, eyes and expression
    are fitted warm-started from the previous frame. The energy is `track`'s full-stage energy restricted
    to the new frame: its data term and per-frame priors, and the temporal terms over the window of the
    last two fitted frames (fixed) and the new one. Causal: a frame never waits for later ones.

    Solvers (`solver=`):
    - "gauss_newton" (default): damped Gauss-Newton (Levenberg-Marquardt) on the same energy: the data term's
      Jacobian by forward differences in float64 (the ~40 unknowns each perturbed, posed as one batch of the
      head model: one pass), its gradient and Gauss-Newton curvature with the pseudo-Huber's IRLS weights, the
      exact gradient and Hessian of the priors and temporal terms (no head-model pass); a step is kept only when
      the energy drops. The Jacobian is taken once per frame, at the warm start, and kept for the frame's later
      iterations (a chord method; `refresh_jacobian=True` retakes it at each: on wojtek.mp4's live landmarks the
      same landmark error for a third more time, #28). The unknowns are few and the residuals many: 2 iterations land closer to
      the offline fit than 8 of L-BFGS, in less time (benchmarks/online_fit_bench.py).
    - "lbfgs": L-BFGS with a strong-Wolfe line search, curvature pairs carried over from frame to frame.

        online = OnlineFit(model, result)                  # or solver="lbfgs", iterations=8
        params, error = online(landmarks [478, >=2], principal [2])   # HeadParams [1, ...] (model's vertices)
    """

    def __init__(self, model: HeadModel, result: TrackingResult, config: TrackingConfig = TrackingConfig(),
                 iterations: int | None = None, lr: float = 1.0, solver: str = "gauss_newton",
                 refresh_jacobian: bool = False):
        if solver not in ONLINE_SOLVERS:
            raise ValueError(f"OnlineFit: solver must be one of {', '.join(ONLINE_SOLVERS)}, got {solver!r}")
        iterations = ONLINE_SOLVERS[solver] if iterations is None else iterations
        if iterations < 1:
            raise ValueError(f"OnlineFit: iterations must be >= 1, got {iterations}")
        self.model, self.config, self.iterations, self.solver = model, config, iterations, solver
        self.refresh_jacobian = refresh_jacobian
        values = {k: torch.as_tensor(v, dtype=torch.float32) for k, v in result.params.items() if k != "static_offset"}
        fitted = HeadParams.from_npz(values)  # [T, ...] of the frames `track` fitted
        static = result.model_static_offset
        self.shape = fitted.shape.detach()
        self.static_offset = None if static is None else torch.as_tensor(static, dtype=torch.float32)[None]
        self.focal = float(result.focal)
        self.viewmat = torch.as_tensor(result.viewmat, dtype=torch.float32)
        self.ids = torch.as_tensor(result.landmark_ids, dtype=torch.long)
        groups = [GROUP_OF.get(int(i), "face_oval_lower") for i in result.landmark_ids]
        self.weights = torch.tensor([GROUP_WEIGHTS[g] for g in groups], dtype=torch.float32)
        self.history = [fitted.frame(-2 if fitted.batch > 1 else -1).detach(), fitted.frame(-1).detach()]  # t-2, t-1
        last = self.history[-1]
        self.current = {key: torch.nn.Parameter(getattr(last, key).clone()) for key in ONLINE_KEYS}
        self.sizes = [self.current[key].shape[-1] for key in ONLINE_KEYS]  # widths of the flat unknown vector
        if solver == "gauss_newton":
            from torch.func import hessian

            self.damping = 1e-3  # Levenberg-Marquardt's, carried from frame to frame
            # The Jacobian by forward differences: the P + 1 points (x and x + h e_i) posed as one batch of the head
            # model, in float64 (h = FD_STEP: the error of the difference quotient is ~1e-8 of the derivative).
            self.model64 = copy.deepcopy(model).to(torch.float64)
            self.vertex_ids = self.model64.landmark_vertex_ids  # (a property that sorts; taken once)
            self.viewmat64 = self.viewmat.double()
            self.shape64 = self.shape.double()
            self.static_offset64 = None if self.static_offset is None else self.static_offset.double()
            # The priors and temporal terms are quadratic in x but for the jaw's range hinge (`_jaw_range`): the
            # quadratic's Hessian [P, P] is one constant, taken here (with the jaw inside its range, so without the
            # hinge's curvature) so that the first live frame does not wait for it (and for torch.func's set-up).
            self.jaw_index = sum(self.sizes[:ONLINE_KEYS.index("jaw_pose")])  # x[jaw_index]: the jaw's opening
            inside = self._flat().detach().double()
            inside[self.jaw_index] = 0.5 * config.jaw_max
            self.regulariser_hessian = hessian(self._regularisers)(inside)
        if solver == "lbfgs":
            # a handful of iterations reach what Adam needs hundreds for, from a warm start
            self.optimizer = torch.optim.LBFGS(list(self.current.values()), lr=lr, max_iter=iterations,
                                               history_size=iterations, line_search_fn="strong_wolfe")

    # --- the energy of one frame, as a function of the flat unknowns x [P] ------------------------------
    def _flat(self) -> Tensor:
        """[P] the current unknowns (the graph to self.current kept, for L-BFGS)."""
        return torch.cat([self.current[key][0] for key in ONLINE_KEYS])

    def _split(self, x: Tensor) -> dict[str, Tensor]:
        return {key: part[None] for key, part in zip(ONLINE_KEYS, torch.split(x, self.sizes))}  # each [1, D]

    def _frame(self, x: Tensor) -> HeadParams:
        return HeadParams(shape=self.shape, static_offset=self.static_offset, **self._split(x))

    def _regularisers(self, x: Tensor) -> Tensor:
        """Priors and temporal terms of the frame (no head-model pass)."""
        past, p = self.history, self._frame(x)
        window = HeadParams(shape=self.shape, static_offset=self.static_offset, **{
            key: torch.cat([getattr(past[0], key).to(x.dtype), getattr(past[1], key).to(x.dtype), getattr(p, key)], 0)
            for key in ONLINE_KEYS})  # [3, ...]: t-2, t-1 fixed; t free
        terms = _pose_smoothness(window, self.config)
        terms.update(_frame_priors(p, self.config))
        terms["smooth"] = _motion_smoothness(window, self.config)
        return sum(terms.values())

    def _jaw_range(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The jaw's range hinge of `_frame_priors` at x [P]: its value, slope and curvature in the jaw's opening."""
        jaw, weight = x[self.jaw_index], self.config.w_jaw_range
        below, above = torch.relu(-jaw), torch.relu(jaw - self.config.jaw_max)
        curvature = 2.0 * weight * ((below > 0) | (above > 0)).to(x.dtype)
        return weight * (below ** 2 + above ** 2), 2.0 * weight * (above - below), curvature

    def _energy(self, x: Tensor, K: Tensor, target: Tensor, size: Tensor) -> Tensor:
        data = _data_term(self.model, self._frame(x), self.viewmat, K, target, size, self.weights, torch.ones(1),
                          self.config.huber)
        return data + self._regularisers(x)

    def _residuals_batch(self, X: Tensor, K: Tensor, target: Tensor, size: Tensor) -> Tensor:
        """[B, L, 2] the data term's 2D residuals in face sizes (`_data_residuals`) at B unknown vectors X [B, P]
        at once, in float64."""
        parts = dict(zip(ONLINE_KEYS, torch.split(X, self.sizes, dim=1)))  # each [B, D]
        params = HeadParams(shape=self.shape64, static_offset=self.static_offset64, **parts)
        landmarks = self.model64.forward_params(params, vertex_ids=self.vertex_ids).landmarks  # [B, L, 3]
        pixels, _ = project(landmarks, self.viewmat64, K)  # [B, L, 2]
        return (pixels - target) / size[:, None, None]

    def _gauss_newton(self, x: Tensor, K: Tensor, target: Tensor, size: Tensor) -> tuple[Tensor, Tensor]:
        """Damped Gauss-Newton from x [P]: (the solution [P] (float32), its residuals [L, 2] (float64)).

        The data term's Jacobian [L, 2, P] comes from forward differences, the P + 1 points posed as one batch of the
        head model (one model pass; torch.func.jacfwd's took 4x the time, most of it per-op overhead); a candidate
        step costs one more pass of one frame, whose residuals are the next iteration's."""
        x, K, target, size = x.double(), K.double(), target.double(), size.double()
        delta = self.config.huber
        weights = (self.weights / self.weights.sum()).double()  # [L]
        steps = FD_STEP * torch.eye(x.shape[0], dtype=x.dtype)  # [P, P]

        def data_energy(r: Tensor) -> Tensor:  # _data_term of one frame from its residuals r [L, 2]
            return (_pseudo_huber(r.norm(dim=-1), delta) * weights).sum()

        # The priors and temporal terms: quadratic in x but for the jaw's range hinge, so from one autograd pass at the
        # start their value and gradient anywhere are the quadratic's (its constant Hessian) plus the hinge's.
        start = x
        with torch.enable_grad():
            v = x.detach().requires_grad_(True)
            value = self._regularisers(v)
            (gradient,) = torch.autograd.grad(value, v)
        hinge, hinge_slope, _ = self._jaw_range(x)
        quadratic, quadratic_grad = value.detach() - hinge, gradient.clone()
        quadratic_grad[self.jaw_index] -= hinge_slope

        def regularisers(v: Tensor) -> tuple[Tensor, Tensor, Tensor]:  # value, gradient [P], the hinge's curvature
            d = v - start
            moved = self.regulariser_hessian @ d  # [P]
            hinge, slope, curvature = self._jaw_range(v)
            grad = quadratic_grad + moved
            grad[self.jaw_index] += slope
            return quadratic + quadratic_grad @ d + 0.5 * (d @ moved) + hinge, grad, curvature

        both = self._residuals_batch(torch.cat([x[None], x[None] + steps]), K, target, size)  # [P + 1, L, 2]
        r = both[0]  # [L, 2]
        J = (both[1:] - r).permute(1, 2, 0) / FD_STEP  # [L, 2, P]
        reg_value, grad_reg, reg_curvature = regularisers(x)
        energy = data_energy(r) + reg_value
        eye = torch.eye(x.shape[0], dtype=x.dtype)
        for iteration in range(self.iterations):
            if iteration > 0 and self.refresh_jacobian:  # the Jacobian at the accepted point (its residuals r are known)
                J = (self._residuals_batch(x[None] + steps, K, target, size) - r).permute(1, 2, 0) / FD_STEP
            irls = weights / torch.sqrt(1.0 + (r.norm(dim=-1) / delta) ** 2)  # [L]: rho'(r) / r times the landmark weight
            grad = torch.einsum("l,lcp,lc->p", irls, J, r) + grad_reg  # [P] the energy's gradient
            H = torch.einsum("l,lcp,lcq->pq", irls, J, J) + self.regulariser_hessian  # [P, P]
            H[self.jaw_index, self.jaw_index] += reg_curvature
            for _attempt in range(4):  # Levenberg-Marquardt: raise the damping until the energy drops
                step = torch.linalg.solve(H + self.damping * (torch.diagonal(H).clamp_min(1e-9) * eye), -grad)
                candidate = x + step
                r_candidate = self._residuals_batch(candidate[None], K, target, size)[0]
                reg_candidate, grad_candidate, curvature_candidate = regularisers(candidate)
                candidate_energy = data_energy(r_candidate) + reg_candidate
                if candidate_energy < energy:
                    x, r, energy = candidate, r_candidate, candidate_energy
                    grad_reg, reg_curvature = grad_candidate, curvature_candidate
                    self.damping = max(self.damping / 3.0, 1e-7)
                    break
                self.damping = min(self.damping * 4.0, 1e4)
            else:
                break  # no step lowers the energy: at a minimum for this damping
        return x.float(), r

    def __call__(self, landmarks: np.ndarray, principal) -> tuple[HeadParams, float]:
        """Fit one frame: landmarks [478, >=2] in crop pixels, principal point [2] (crop pixels).

        Returns (HeadParams of the frame, per-frame keys [1, ...], the landmark model's static offset) and
        its median landmark error / face width (track's `errors` measure)."""
        target = torch.as_tensor(np.asarray(landmarks)[None, self.ids.numpy(), :2], dtype=torch.float32)  # [1, L, 2]
        size = torch.as_tensor(np.linalg.norm(landmarks[10, :2] - landmarks[152, :2]), dtype=torch.float32).clamp_min(1.0)[None]
        K = _intrinsics(torch.tensor(self.focal), torch.as_tensor(np.asarray(principal, np.float32))[None])
        residuals = None
        if self.solver == "gauss_newton":
            with torch.no_grad():
                x, residuals = self._gauss_newton(self._flat().detach(), K, target, size)
                for key, value in self._split(x).items():
                    self.current[key].copy_(value)
        else:
            with torch.enable_grad():
                def closure() -> Tensor:
                    self.optimizer.zero_grad(set_to_none=True)
                    total = self._energy(self._flat(), K, target, size)
                    total.backward()
                    return total

                self.optimizer.step(closure)
        with torch.no_grad():
            fitted = HeadParams(shape=self.shape, static_offset=self.static_offset,
                                **{key: self.current[key].detach().clone() for key in ONLINE_KEYS})
            self.history = [self.history[1], fitted]
            if residuals is None:
                pixels, _ = project(self.model.forward_params(fitted, vertex_ids=self.model.landmark_vertex_ids).landmarks,
                                    self.viewmat, K)
                offsets = pixels[0] - target[0]  # [L, 2]
            else:  # the solver's residuals at the solution, in pixels
                offsets = residuals * size.double()
            width = max(float(np.linalg.norm(landmarks[234, :2] - landmarks[454, :2])), 1e-6)
            error = float(offsets.norm(dim=-1).median()) / width
        return fitted, error


def offset_rows(offset_map: SmoothOffset, model: HeadModel) -> np.ndarray:
    """[U + J, P]: the static offset of a `landmark_head`'s vertices and joint carriers from theta."""
    used = model.data.metadata.get("vertex_ids")
    if used is None:
        raise ValueError("offset_rows: the model is not a landmark_head (no 'vertex_ids' in its metadata)")
    return np.concatenate([offset_map.matrix[used], offset_map.at_joints], 0)


def load_landmark_embedding(path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(mediapipe ids [L], face ids [L], barycentrics [L, 3]) from a FLAME MediaPipe embedding npz.

    The file is the one metrical-tracker and VHAP use (`mediapipe_landmark_embedding.npz`, keys
    landmark_indices, lmk_face_idx, lmk_b_coords), read without pickles.
    """
    from pathlib import Path

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(path)
    with np.load(path, allow_pickle=False) as npz:
        missing = [k for k in ("landmark_indices", "lmk_face_idx", "lmk_b_coords") if k not in npz.files]
        if missing:
            raise ValueError(f"{path}: not a MediaPipe landmark embedding, keys missing: {', '.join(missing)}")
        ids = np.asarray(npz["landmark_indices"]).astype(np.int64).ravel()
        faces = np.asarray(npz["lmk_face_idx"]).astype(np.int64).ravel()
        bary = np.asarray(npz["lmk_b_coords"], dtype=np.float32).reshape(-1, 3)
    if not (len(ids) == len(faces) == len(bary)) or ids.min() < 0 or ids.max() >= 478:
        raise ValueError(f"{path}: landmark_indices, lmk_face_idx and lmk_b_coords disagree in length or range")
    return ids, faces, bary


__all__ = ["GROUP_WEIGHTS", "GROUP_OF", "ONLINE_SOLVERS", "OnlineFit", "TrackingConfig", "TrackingResult", "landmark_head", "camera_viewmat", "track",
           "offset_rows", "load_landmark_embedding"]
