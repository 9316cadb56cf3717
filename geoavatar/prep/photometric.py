"""Photometric tracking on CPU: refine a video's head parameters against its images.

    targets = PhotometricTargets.from_arrays(images [T,H,W,3] u8, masks [T,H,W] u8, viewmat, K [T,3,3])
    result = fit_photometric(head, init: HeadParams [T], targets, PhotometricConfig(), landmarks=None)
    result.params          # HeadParams [T] (shape / static_offset of `init`, per-frame keys refined)
    result.residual        # [T] masked L1 per frame after the fit (NaN: no pixel to compare); residual_before: with `init`

The appearance model is bound to the posed mesh: one isotropic Gaussian per face of the *weighted*
faces (the face, eyes, nose, lips and the mouth structure; never scalp, neck, ears: hair, beard and
clothes the head model cannot express live there), at the face's centroid, of a size following the
face's area, opaque. Its colour is a per-face albedo shared by all frames times second-order SH
shading of the face normal with one lighting [9, 3] per video:

    colour_f = albedo_f * (Y(n_f) @ L)            Y: the 9 real SH basis functions of the unit normal

Rendered with the native CPU rasterizer (`geoavatar.render.rasterize`, differentiable). The image loss
is an L1 over the pixels inside the dataset's mask, weighted by the render's own (detached) coverage,
so only pixels the weighted faces explain count:

    photo_t = sum_p m_p a_p |rgb_p - a_p I_p| / sum_p m_p a_p      (rgb over a black background)

Energy per chunk of frames (all terms means over the chunk's frames):
    photo + landmark_weight * (landmark term of prep.tracking, when landmarks are given)
          + prior_weight * (prep.tracking's per-frame priors + smoothness of expression, jaw, eyes, neck)
          + pose_smooth_weight * (prep.tracking's smoothness of the head's rotation and translation)
The temporal terms see the neighbouring frames of the adjacent chunks (fixed), so chunk borders are
smooth too. A frame whose mask is empty (prepare empties the masks of frames where no face was found, whose
landmarks are interpolated) has no image term: the mean `photo` is over the chunk's frames with pixels, and
such a frame follows its weak landmark term, the priors and the temporal smoothness with its refined
neighbours; its residual is NaN ("nothing compared"), never 0. Unknowns: per frame rotation, translation, neck, jaw, eyes, expression; shared albedo and
lighting (and the identity shape with `fit_shape`). Schedule: albedo initialised by projecting each
face centroid into the frames that see it; one appearance-only epoch; then epochs over chunks at each
pyramid level (64 -> 128 px by default), Adam per chunk (its moments kept across epochs), learning
rates decaying within each level. Coarse levels are rendered at the finest size and area-downsampled
(`supersample`), the way their frames are made: rendered at their own size, the many sub-pixel Gaussians
give an image term whose minimum lies 1-2 cm behind the true depth (tests/test_photometric.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Iterable

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from geoavatar.avatar.fused import surface_splats
from geoavatar.head.base import HeadModel
from geoavatar.head.params import FRAME_KEYS, HeadParams
from geoavatar.prep.tracking import TrackingConfig, _data_term, _frame_priors, _motion_smoothness, _pose_smoothness
from geoavatar.render.camera import scale_intrinsics
from geoavatar.render.rasterize import rasterize

# Vertex groups whose faces the appearance model renders (and the photometric term sees).
WEIGHTED_REGIONS = ("face", "lips", "nose", "eye_region", "left_eye_region", "right_eye_region", "left_eyeball",
                    "right_eyeball")
SH_C0, SH_C1 = 0.28209479177387814, 0.4886025119029199
SH_C2 = (1.0925484305920792, 0.31539156525252005, 0.5462742152960396)


@dataclass
class PhotometricConfig:
    """Schedule and weights of the photometric fit (the defaults cost ~12 ms of one core per frame and epoch, 36 epochs in
    all; BENCHMARKS.md, photometric tracking)."""

    sizes: tuple[int, ...] = (64, 128)  # pyramid levels: image side in pixels (the longer side)
    # passes over all frames at each level: one Adam step per chunk per pass, so the fit's progress is bound by these
    # (generated subject 0, session 6's rates: face error 6.3 -> 5.6 / 5.3 / 4.4 / 3.8 mm with (4, 3) / (8, 6) / (16, 12) /
    # (24, 18); the rates below reach 3.3 mm at (16, 12))
    epochs: tuple[int, ...] = (16, 12)
    appearance_epochs: int = 8  # albedo / lighting only, at the first level, before the pose moves
    chunk: int = 8  # frames per optimiser step
    # Adam moves a parameter by about its rate per step, and each frame gets one step per epoch: the head pose's
    # rates are what lets 28 steps cover a centimetre (generated subject 0: 3x the rates of session 6 took the test face
    # error 8.3 -> 5.6 mm, 2x 6.3, 4x 5.8, 6x 6.7; BENCHMARKS.md, photometric tracking)
    lr_rotation: float = 1.2e-2  # rad
    lr_translation: float = 3e-3  # m
    lr_neck: float = 1.2e-2
    lr_jaw: float = 1.2e-2
    lr_eyes: float = 1e-2
    lr_expr: float = 3e-2
    lr_shape: float = 1e-2
    lr_albedo: float = 0.1  # appearance-only epochs
    lr_albedo_pose: float = 0.005  # while the pose moves: slow, so that the albedo cannot absorb misalignment
    lr_light: float = 1e-2
    lr_decay: float = 0.2  # the learning rate falls to this fraction over each level
    fit_shape: bool = False  # refine the identity shape shared by all frames too
    landmark_weight: float = 20.0  # relative to the photometric L1 (landmark term of prep.tracking)
    prior_weight: float = 1.0  # multiplies prep.tracking's priors and temporal smoothness
    # multiplies prep.tracking's head-pose smoothness (first and second differences of rotation and translation).
    # At 1 the per-chunk Adam steps left frame-to-frame jitter on a real video whose landmark fit is smooth (wojtek:
    # mean |second difference| of depth 0.09 -> 1.14 mm). At the rates above, 100 held generated subject 0's test
    # frames far from the truth (face 5.0 mm against 3.1 at 30; BENCHMARKS.md, photometric tracking)
    pose_smooth_weight: float = 30.0
    gaussian_size: float = 0.6  # Gaussian std / sqrt(face area)
    opacity: float = 0.98
    # Gaussians per face: 1 (centroid) or 4. 1 is 1.8-2.5x cheaper and as accurate at 128 px (BENCHMARKS.md)
    per_face: int = 1
    render_rings: int = 3  # faces rendered around the weighted ones (vertex rings)
    crop_margin: float = 1.25  # fitted crop side / the weighted faces' largest projected extent
    # Coarse levels render at the finest size and area-downsample, as the frames are: a render of sub-pixel
    # Gaussians at the coarse size is not the downsampled frame, and its image term prefers a head 1-2 cm
    # farther away (BENCHMARKS.md, photometric tracking). The renderer's cost barely depends on the size.
    supersample: bool = True
    tracking: TrackingConfig = field(default_factory=TrackingConfig)  # prior / smoothness weights, huber

    def __post_init__(self):
        if len(self.sizes) == 0 or len(self.sizes) != len(self.epochs):
            raise ValueError(f"photometric: sizes {self.sizes} and epochs {self.epochs} must be non-empty and of one length")
        if self.per_face not in (1, 4):
            raise ValueError(f"photometric: per_face must be 1 or 4, got {self.per_face}")
        if self.chunk < 1 or min(self.sizes) < 8:
            raise ValueError(f"photometric: chunk must be >= 1 and sizes >= 8, got {self.chunk}, {self.sizes}")


@dataclass
class PhotometricTargets:
    """What the frames show, at the finest pyramid level: images [T,H,W,3] and masks [T,H,W,1] in [0,1],
    cameras viewmat [T,4,4] and K [T,3,3] (for the images at `scale` times the stored camera's pixels)."""

    images: Tensor
    masks: Tensor
    viewmat: Tensor
    K: Tensor
    K_source: Tensor  # [T,3,3] the cameras' own intrinsics (landmarks are in those pixels)

    @classmethod
    def from_arrays(cls, images: np.ndarray, masks: np.ndarray | None, viewmat: np.ndarray, K: np.ndarray,
                    size: int, boxes: np.ndarray | None = None) -> "PhotometricTargets":
        """images [T,H,W,3] uint8, masks [T,H,W(,1)] uint8 or None, viewmat [4,4] or [T,4,4], K [3,3] or [T,3,3]
        (for the images), boxes [T, 3] square crops (x0, y0, side) in image pixels or None (whole frames);
        each crop is resampled (area) to `size` x `size` (whole frames: the longer side to `size`)."""
        T, H, W = images.shape[:3]
        masks = np.full((T, H, W), 255, np.uint8) if masks is None else np.asarray(masks).reshape(T, H, W)
        return cls.from_frames(zip(images, masks), T, viewmat, K, size, boxes)

    @classmethod
    def from_frames(cls, frames: Iterable[tuple[np.ndarray, np.ndarray]], count: int, viewmat: np.ndarray,
                    K: np.ndarray, size: int, boxes: np.ndarray | None = None) -> "PhotometricTargets":
        """from_arrays over `count` (image [H,W,3] uint8, mask [H,W] uint8) pairs read one at a time: only the
        resampled crops are held, never the full-size frames (a long video's frames do not fit in memory)."""
        T = count
        K_source = torch.as_tensor(np.asarray(K), dtype=torch.float32).expand(T, 3, 3).clone()
        view = torch.as_tensor(np.asarray(viewmat), dtype=torch.float32).expand(T, 4, 4).clone()
        K_out = K_source.clone()
        rgb_out = mask_out = None
        for t, (image, mask) in enumerate(frames):
            H, W = image.shape[:2]
            if boxes is None:
                scale = min(1.0, size / max(H, W))
                box, out_w, out_h = (0.0, 0.0, max(H, W)), max(1, round(W * scale)), max(1, round(H * scale))
            else:
                box, out_w, out_h = boxes[t], size, size
            if rgb_out is None:
                rgb_out = np.zeros((T, out_h, out_w, 3), np.float32)
                mask_out = np.zeros((T, out_h, out_w, 1), np.float32)
            x0, y0, side = (float(v) for v in box)
            region = (x0, y0, x0 + side * out_w / max(out_w, out_h), y0 + side * out_h / max(out_w, out_h))
            rgb_out[t] = _resample(image, region, (out_w, out_h))
            mask_out[t, ..., 0] = _resample(np.asarray(mask).reshape(H, W), region, (out_w, out_h))
            s = max(out_w, out_h) / side
            K_out[t, 0, :] = s * (K_source[t, 0, :] - x0 * K_source[t, 2, :])
            K_out[t, 1, :] = s * (K_source[t, 1, :] - y0 * K_source[t, 2, :])
        if rgb_out is None or t + 1 != T:
            raise ValueError(f"photometric: {count} frames announced, {0 if rgb_out is None else t + 1} given")
        return cls(torch.as_tensor(rgb_out) / 255.0, torch.as_tensor(mask_out) / 255.0, view, K_out, K_source)

    @property
    def frames(self) -> int:
        return int(self.images.shape[0])

    def level(self, size: int) -> "PhotometricTargets":
        """The same frames with the longer side `size` pixels (area downsampling; never upsampled)."""
        H, W = self.images.shape[1:3]
        scale = min(1.0, size / max(H, W))
        h, w = max(1, round(H * scale)), max(1, round(W * scale))
        if (h, w) == (H, W):
            return self
        images = F.interpolate(self.images.permute(0, 3, 1, 2), size=(h, w), mode="area").permute(0, 2, 3, 1)
        masks = F.interpolate(self.masks.permute(0, 3, 1, 2), size=(h, w), mode="area").permute(0, 2, 3, 1)
        return PhotometricTargets(images.contiguous(), masks.contiguous(), self.viewmat,
                                  scale_intrinsics(self.K, w / W, h / H), self.K_source)


@dataclass
class LandmarkTargets:
    """Detected 2D landmarks for prep.tracking's landmark term: points [T, L, 2] in the cameras' own pixels
    (the model's embedded landmarks, in the order of `head.landmark_ids`), face size [T] (pixels),
    per-landmark weights [L], per-frame confidence [T]."""

    points: Tensor
    size: Tensor
    weights: Tensor
    confidence: Tensor


@dataclass
class PhotometricResult:
    params: HeadParams  # [T] refined (detached)
    residual: np.ndarray  # [T] masked L1 per frame after the fit (finest level)
    residual_before: np.ndarray  # [T] the same with the initial parameters
    albedo: np.ndarray  # [F, 3] per rendered face
    light: np.ndarray  # [9, 3]
    face_ids: np.ndarray  # [F] the head's faces the appearance model renders
    log: list[str] = field(default_factory=list)


def _resample(image: np.ndarray, region: tuple[float, float, float, float], size: tuple[int, int]) -> np.ndarray:
    """The box `region` (x0, y0, x1, y1; may reach outside: edge pixels repeat) of a uint8 image, area-resampled
    to `size` (w, h), as float32 [h, w(, 3)] in 0..255."""
    from PIL import Image

    return np.asarray(Image.fromarray(image).resize(size, Image.Resampling.BOX, box=region), np.float32) \
        if _inside(image, region) else _resample_padded(image, region, size)


def _inside(image: np.ndarray, region) -> bool:
    return region[0] >= 0 and region[1] >= 0 and region[2] <= image.shape[1] and region[3] <= image.shape[0]


def _resample_padded(image: np.ndarray, region, size) -> np.ndarray:
    """_resample for a box reaching outside the image: the image is padded with its edge first."""
    pad = int(math.ceil(max(0.0, -region[0], -region[1], region[2] - image.shape[1], region[3] - image.shape[0]))) + 1
    widths = ((pad, pad), (pad, pad)) + (((0, 0),) if image.ndim == 3 else ())
    padded = np.pad(image, widths, mode="edge")
    return _resample(padded, (region[0] + pad, region[1] + pad, region[2] + pad, region[3] + pad), size)


def crop_boxes(head: HeadModel, params: HeadParams, viewmat: Tensor, K: Tensor, vertex_ids: Tensor,
               margin: float = 1.25, chunk: int = 32) -> np.ndarray:
    """[T, 3] square crops (x0, y0, side) around the projected vertices `vertex_ids` of every frame: centred on
    each frame's projected box, one side for the video (the largest box side x `margin`), in K's pixels."""
    from geoavatar.render.camera import project

    centres, sides = [], []
    with torch.no_grad():
        for start in range(0, params.batch, chunk):
            rows = torch.arange(start, min(start + chunk, params.batch))
            vertices = head.forward_params(params.rows(rows), vertex_ids=vertex_ids).vertices  # [B, K, 3]
            pixels, _ = project(vertices, viewmat[rows], K[rows])  # [B, K, 2]
            low, high = pixels.amin(1), pixels.amax(1)  # [B, 2]
            centres.append((low + high) / 2)
            sides.append((high - low).amax(-1))
    centre, side = torch.cat(centres).numpy(), float(torch.cat(sides).max()) * margin
    return np.concatenate([centre - side / 2, np.full((len(centre), 1), side)], 1)


def weighted_faces(head: HeadModel, regions=WEIGHTED_REGIONS) -> np.ndarray:
    """[F] ids of the head's faces whose three vertices all lie in `regions`, plus every face of the mouth
    structure (teeth, mouth interior) when the head has one."""
    keep = np.zeros(head.num_vertices, bool)
    for name in regions:
        if name in head.regions:
            keep[np.asarray(head.regions[name])] = True
    faces = head.faces.cpu().numpy()
    chosen = keep[faces].all(1)
    for ids in head.face_groups.values():  # the mouth structure's face sets
        chosen[np.asarray(ids)] = True
    if not chosen.any():
        raise ValueError(f"head model '{head.name}' has none of the regions {', '.join(regions)}")
    return np.flatnonzero(chosen)


def grow_faces(head: HeadModel, face_ids: np.ndarray, rings: int) -> np.ndarray:
    """[F'] `face_ids` plus every face within `rings` vertex rings of them (the border the fixed pixel
    weights may reach when the head moves a little)."""
    faces = head.faces.cpu().numpy()
    chosen = np.zeros(len(faces), bool)
    chosen[face_ids] = True
    for _ in range(rings):
        near = np.zeros(head.num_vertices, bool)
        near[faces[chosen].ravel()] = True
        chosen = near[faces].any(1)
    return np.flatnonzero(chosen)


def weighted_vertex_ids(head: HeadModel) -> Tensor:
    """[K] the vertices of `weighted_faces` (what the crops are framed on)."""
    return torch.as_tensor(np.unique(head.faces.cpu().numpy()[weighted_faces(head)]), dtype=torch.long)


def sh_basis(normals: Tensor) -> Tensor:
    """[..., 9] real SH basis (bands 0-2) of unit normals [..., 3]."""
    x, y, z = normals.unbind(-1)
    return torch.stack([
        torch.full_like(x, SH_C0), -SH_C1 * y, SH_C1 * z, -SH_C1 * x,
        SH_C2[0] * x * y, -SH_C2[0] * y * z, SH_C2[1] * (3 * z * z - 1), -SH_C2[0] * x * z, SH_C2[2] * (x * x - y * y),
    ], -1)


class SurfaceAppearance(torch.nn.Module):
    """Gaussians bound to the faces `face_ids` of `head`: geometry from the posed mesh, colour from a shared
    albedo [F, 3] and SH lighting [9, 3]. Poses only the vertices those faces use (`vertex_ids`)."""

    def __init__(self, head: HeadModel, face_ids: np.ndarray, config: PhotometricConfig, weighted: np.ndarray | None = None):
        super().__init__()
        weighted = np.ones(len(face_ids), bool) if weighted is None else np.isin(face_ids, weighted)
        faces = head.faces.cpu().numpy()[face_ids]  # [F, 3] head vertex ids
        used, local = np.unique(faces, return_inverse=True)
        self.register_buffer("vertex_ids", torch.as_tensor(used, dtype=torch.long))  # [K]
        self.register_buffer("faces", torch.as_tensor(local.reshape(-1, 3), dtype=torch.long))  # [F, 3] rows of vertex_ids
        self.face_ids = np.asarray(face_ids)
        self.size, self.opacity = config.gaussian_size, config.opacity
        # Gaussians per face: the centroid, or (per_face 4) the centroid and the centroids of the corner sub-triangles.
        bary = [[1 / 3, 1 / 3, 1 / 3]] + ([[2 / 3, 1 / 6, 1 / 6], [1 / 6, 2 / 3, 1 / 6], [1 / 6, 1 / 6, 2 / 3]]
                                          if config.per_face == 4 else [])
        self.register_buffer("bary", torch.tensor(bary))  # [S, 3]
        weighted = np.repeat(weighted, len(bary))
        self.albedo = torch.nn.Parameter(torch.full((len(face_ids) * len(bary), 3), 0.5))
        light = torch.zeros(9, 3)
        light[0] = 1.0 / SH_C0  # shading 1 everywhere
        self.light = torch.nn.Parameter(light)
        self.register_buffer("weighted", torch.as_tensor(weighted, dtype=torch.float32))  # [F * S] 1: the loss sees it

    def geometry(self, vertices: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """vertices [B, K, 3] -> centroids [B, F, 3], unit normals [B, F, 3], Gaussian std [B, F]."""
        corners = torch.stack([vertices[:, self.faces[:, i]] for i in range(3)], -2)  # [B, F, 3 corners, 3]
        v0, v1, v2 = corners.unbind(-2)
        cross = torch.linalg.cross(v1 - v0, v2 - v0, dim=-1)  # [B, F, 3], |cross| = 2 area
        double_area = cross.square().sum(-1).clamp_min(1e-16).sqrt()
        S = self.bary.shape[0]
        centres = torch.einsum("sc,bfcd->bfsd", self.bary, corners).flatten(1, 2)  # [B, F * S, 3]
        normals = (cross / double_area[..., None]).repeat_interleave(S, dim=1)
        std = (self.size / math.sqrt(S) * (0.5 * double_area).sqrt()).repeat_interleave(S, dim=1)
        return centres, normals, std

    def colours(self, normals: Tensor) -> Tensor:
        """normals [..., F, 3] -> colours [..., F, 3]."""
        return self.albedo * (sh_basis(normals) @ self.light)

    def render(self, vertices: Tensor, viewmat: Tensor, K: Tensor, width: int, height: int, coverage: bool = False):
        """One frame: vertices [K, 3] -> RasterizeResult (rgb over black, alpha); `coverage`: colour 1 on the
        weighted faces, 0 elsewhere (the face-region map) instead of the appearance."""
        fused = None if coverage or self.bary.shape[0] != 1 else surface_splats(
            vertices, self.albedo, self.light, self.faces, self.size)
        if fused is not None:  # the same maths in one native loop each way (~6 of a frame's ~18 ms in PyTorch ops)
            centre, std, colours = fused
        else:
            centre, normal, std = (x[0] for x in self.geometry(vertices[None]))
            colours = self.weighted[:, None].expand(centre.shape[0], 3) if coverage else self.colours(normal)
        count = centre.shape[0]
        quats = centre.new_zeros(count, 4)
        quats[:, 0] = 1.0
        return rasterize(centre, quats, std[:, None].expand(count, 3), centre.new_full((count,), self.opacity),
                         colours, viewmat, K, width, height, background=centre.new_zeros(3),
                         check_values=False)


def render_at(appearance: SurfaceAppearance, vertices: Tensor, viewmat: Tensor, K: Tensor, width: int, height: int,
              factor: int = 1, coverage: bool = False) -> tuple[Tensor, Tensor]:
    """SurfaceAppearance.render at `factor` times the size, area-downsampled: rgb [H, W, 3], alpha [H, W, 1]."""
    if factor <= 1:
        result = appearance.render(vertices, viewmat, K, width, height, coverage=coverage)
        return result.rgb, result.alpha
    result = appearance.render(vertices, viewmat, scale_intrinsics(K, factor, factor), width * factor, height * factor,
                               coverage=coverage)
    both = F.avg_pool2d(torch.cat([result.rgb, result.alpha], -1).permute(2, 0, 1)[None], factor)[0].permute(1, 2, 0)
    return both[..., :3], both[..., 3:]


def level_factor(config: "PhotometricConfig", size: int) -> int:
    """The supersampling factor of the pyramid level `size` (1 at the finest or without supersampling)."""
    return max(1, max(config.sizes) // size) if config.supersample else 1


def photometric_loss(rgb: Tensor, image: Tensor, weight: Tensor) -> Tensor:
    """Weighted L1: rgb, image [H, W, 3], weight [H, W, 1] (the mask times the fixed face-region map)."""
    return (weight * (rgb - image).abs()).sum() / (3.0 * weight.sum().clamp_min(1.0))


def region_weights(appearance: "SurfaceAppearance", head: HeadModel, params: HeadParams, level: "PhotometricTargets",
                   chunk: int, factor: int = 1) -> Tensor:
    """[T, H, W, 1] the pixels the photometric term sees: inside the mask and covered (> 0.5) by the weighted
    faces rendered at `params`, eroded by one pixel; fixed during a level so that the fit cannot choose its pixels."""
    H, W = level.images.shape[1:3]
    out = torch.zeros(level.frames, H, W, 1)
    with torch.no_grad():
        for start in range(0, level.frames, chunk):
            rows = torch.arange(start, min(start + chunk, level.frames))
            vertices = head.forward_params(params.rows(rows), vertex_ids=appearance.vertex_ids).vertices
            for i, row in enumerate(rows.tolist()):
                out[row] = render_at(appearance, vertices[i], level.viewmat[row], level.K[row], W, H, factor, coverage=True)[0][..., :1]
    inside = (out > 0.5).float().permute(0, 3, 1, 2)
    eroded = -F.max_pool2d(-inside, 3, stride=1, padding=1)
    return eroded.permute(0, 2, 3, 1) * level.masks


def _init_albedo(appearance: SurfaceAppearance, head: HeadModel, params: HeadParams, targets: PhotometricTargets,
                 chunk: int) -> None:
    """Albedo = mean over frames of the image colour under each face centroid, weighted by the mask and
    by how squarely the face looks at the camera (faces never seen: the mean colour)."""
    total = torch.zeros(appearance.albedo.shape[0], 3)
    weight = torch.zeros(appearance.albedo.shape[0], 1)
    H, W = targets.images.shape[1:3]
    with torch.no_grad():
        for start in range(0, targets.frames, chunk):
            rows = torch.arange(start, min(start + chunk, targets.frames))
            vertices = head.forward_params(params.rows(rows), vertex_ids=appearance.vertex_ids).vertices
            centre, normal, _ = appearance.geometry(vertices)  # [B, F, 3]
            view = targets.viewmat[rows]  # [B, 4, 4]
            cam = centre @ view[:, :3, :3].transpose(1, 2) + view[:, None, :3, 3]  # [B, F, 3]
            cam_normal = normal @ view[:, :3, :3].transpose(1, 2)
            facing = (-(cam_normal * F.normalize(cam, dim=-1)).sum(-1)).clamp_min(0.0) ** 2  # [B, F]
            uv = cam @ targets.K[rows].transpose(1, 2)
            pixels = uv[..., :2] / uv[..., 2:3].clamp_min(1e-6)  # [B, F, 2]
            grid = torch.stack([pixels[..., 0] / W * 2 - 1, pixels[..., 1] / H * 2 - 1], -1)[:, :, None]  # [B, F, 1, 2]
            sample = lambda x: F.grid_sample(x[rows].permute(0, 3, 1, 2), grid, align_corners=False)[..., 0].transpose(1, 2)  # noqa: E731
            w = facing[..., None] * sample(targets.masks)  # [B, F, 1]
            total += (w * sample(targets.images)).sum(0)
            weight += w.sum(0)
    mean = (total.sum(0) / weight.sum().clamp_min(1e-6)).clamp(0.05, 1.0)
    albedo = torch.where(weight > 1e-3, total / weight.clamp_min(1e-6), mean)
    appearance.albedo.data.copy_(albedo.clamp(0.0, 1.0))


class _Chunk:
    """The per-frame unknowns of frames [start, stop) and their own Adam."""

    LR_KEYS = {"rotation": "lr_rotation", "translation": "lr_translation", "neck_pose": "lr_neck",
               "jaw_pose": "lr_jaw", "eyes_pose": "lr_eyes", "expr": "lr_expr"}

    def __init__(self, init: HeadParams, start: int, stop: int, config: PhotometricConfig):
        self.start, self.stop = start, stop
        self.values = {key: torch.nn.Parameter(getattr(init, key)[start:stop].detach().clone().float())
                       for key in FRAME_KEYS}
        self.base_lr = {key: getattr(config, self.LR_KEYS[key]) for key in FRAME_KEYS}
        self.optimizer = torch.optim.Adam([{"params": [self.values[k]], "lr": self.base_lr[k], "key": k}
                                           for k in FRAME_KEYS])

    def set_lr(self, factor: float) -> None:
        for group in self.optimizer.param_groups:
            group["lr"] = self.base_lr[group["key"]] * factor


def _start_appearance(appearance: SurfaceAppearance, head: HeadModel, init: HeadParams, finest: PhotometricTargets,
                      config: PhotometricConfig, appearance_start: tuple[np.ndarray, np.ndarray] | None) -> None:
    """The albedo projected from the frames (_init_albedo), or an earlier fit's (albedo [F, 3], light [9, 3])."""
    if appearance_start is None:
        _init_albedo(appearance, head, init, finest, config.chunk)
        return
    for parameter, value in zip((appearance.albedo, appearance.light), appearance_start):
        if tuple(value.shape) != tuple(parameter.shape):
            raise ValueError(f"photometric: a start appearance of shape {tuple(value.shape)}, the model has "
                             f"{tuple(parameter.shape)}")
        parameter.data.copy_(torch.as_tensor(value, dtype=torch.float32))


def _shared_optimizer(appearance: SurfaceAppearance, shape: Tensor, config: PhotometricConfig) -> torch.optim.Adam:
    """Adam over what every frame shares: albedo, lighting (and the identity shape with fit_shape). Each group's
    "base" is its rate (appearance-only epochs, epochs that move the pose)."""
    shared = [{"params": [appearance.albedo], "lr": config.lr_albedo, "base": (config.lr_albedo, config.lr_albedo_pose)},
              {"params": [appearance.light], "lr": config.lr_light, "base": (config.lr_light, config.lr_light)}]
    if config.fit_shape:
        shared.append({"params": [shape], "lr": config.lr_shape, "base": (0.0, config.lr_shape)})
    return torch.optim.Adam(shared)


def _schedule(config: PhotometricConfig, appearance_start: bool) -> list[tuple[int, int, bool]]:
    """(size, epochs, appearance_only) of every stage: the appearance-only epochs at the first level (none when
    the fit starts from a given appearance), then each pyramid level's epochs that move the pose."""
    schedule = [(config.sizes[0], 0 if appearance_start else config.appearance_epochs, True)]
    return schedule + [(size, epochs, False) for size, epochs in zip(config.sizes, config.epochs)]


class _PhotometricFit:
    """One fit's unknowns and optimisers: the appearance and shape shared by all frames, the per-frame keys in
    chunks (_Chunk); `run_stage` runs the epochs of one stage of the schedule, `result` reads the fit out."""

    def __init__(self, head: HeadModel, init: HeadParams, targets: PhotometricTargets, config: PhotometricConfig,
                 landmarks: LandmarkTargets | None, appearance_start: tuple[np.ndarray, np.ndarray] | None):
        self.head, self.init, self.targets, self.config, self.landmarks = head, init, targets, config, landmarks
        weighted = weighted_faces(head)
        self.appearance = SurfaceAppearance(head, grow_faces(head, weighted, config.render_rings), config,
                                            weighted=weighted)
        self.finest = targets.level(max(config.sizes))
        _start_appearance(self.appearance, head, init, self.finest, config, appearance_start)
        self.shape = torch.nn.Parameter(init.shape.clone())
        self.shared_optimizer = _shared_optimizer(self.appearance, self.shape, config)
        T = targets.frames
        self.chunks = [_Chunk(init, s, min(s + config.chunk, T), config) for s in range(0, T, config.chunk)]
        self.log: list[str] = []

    def frame_params(self, chunk: _Chunk, frozen: bool = False) -> HeadParams:
        values = {k: (v.detach() if frozen else v) for k, v in chunk.values.items()}
        return HeadParams(shape=self.shape.detach() if frozen else self.shape, static_offset=self.init.static_offset,
                          **values)

    def window(self, index: int) -> HeadParams:
        """The chunk's frames with the last frame of the chunk before and the first after (fixed)."""
        chunks = self.chunks
        parts = {k: [v] for k, v in chunks[index].values.items()}
        if index > 0:
            for k, v in chunks[index - 1].values.items():
                parts[k].insert(0, v[-1:].detach())
        if index + 1 < len(chunks):
            for k, v in chunks[index + 1].values.items():
                parts[k].append(v[:1].detach())
        return HeadParams(shape=self.shape, static_offset=self.init.static_offset,
                          **{k: torch.cat(v) for k, v in parts.items()})

    def photo_term(self, params: HeadParams, chunk: _Chunk, level: PhotometricTargets, weights: Tensor,
                   has_pixels: list[bool], factor: int) -> Tensor:
        """The image term: the mean photometric_loss over the chunk's frames that have pixels to compare."""
        vertices = self.head.forward_params(params, vertex_ids=self.appearance.vertex_ids).vertices  # [B, K, 3]
        H, W = level.images.shape[1:3]
        photo, seen = vertices.new_zeros(()), 0
        for i, row in enumerate(range(chunk.start, chunk.stop)):
            if not has_pixels[row]:  # no face in this frame: nothing to compare, no render
                continue
            rgb, _ = render_at(self.appearance, vertices[i], level.viewmat[row], level.K[row], W, H, factor)
            photo = photo + photometric_loss(rgb, level.images[row], weights[row])
            seen += 1
        return photo / max(seen, 1)

    def pose_terms(self, index: int, params: HeadParams, level: PhotometricTargets) -> dict[str, Tensor]:
        """The terms of epochs that move the pose: landmarks, priors, temporal smoothness over the chunk's window."""
        config, landmarks, prior_config = self.config, self.landmarks, self.config.tracking
        chunk = self.chunks[index]
        rows = torch.arange(chunk.start, chunk.stop)
        terms = {}
        if landmarks is not None and config.landmark_weight > 0:
            terms["landmark"] = config.landmark_weight * _data_term(
                self.head, params, level.viewmat[rows], level.K_source[rows], landmarks.points[rows],
                landmarks.size[rows], landmarks.weights, landmarks.confidence[rows], prior_config.huber)
        around = self.window(index)
        priors = _frame_priors(params, prior_config)
        priors["smooth"] = _motion_smoothness(around, prior_config)
        terms["prior"] = config.prior_weight * sum(priors.values())
        terms["pose_smooth"] = config.pose_smooth_weight * sum(_pose_smoothness(around, prior_config).values())
        return terms

    def chunk_loss(self, index: int, level: PhotometricTargets, weights: Tensor, has_pixels: list[bool],
                   appearance_only: bool, factor: int) -> tuple[Tensor, dict[str, float]]:
        chunk = self.chunks[index]
        params = self.frame_params(chunk, frozen=appearance_only)
        terms = {"photo": self.photo_term(params, chunk, level, weights, has_pixels, factor)}
        if not appearance_only:
            terms.update(self.pose_terms(index, params, level))
        total = sum(terms.values())
        return total, {k: float(v.detach()) for k, v in terms.items()}

    def step(self, index: int, level: PhotometricTargets, weights: Tensor, has_pixels: list[bool],
             appearance_only: bool, factor: int, lr_factor: float) -> dict[str, float]:
        """One Adam step of chunk `index` (and of the shared unknowns); returns its terms."""
        chunk = self.chunks[index]
        chunk.set_lr(lr_factor)
        for group in self.shared_optimizer.param_groups:
            group["lr"] = group["base"][0 if appearance_only else 1] * lr_factor
        chunk.optimizer.zero_grad(set_to_none=True)
        self.shared_optimizer.zero_grad(set_to_none=True)
        total, terms = self.chunk_loss(index, level, weights, has_pixels, appearance_only, factor)
        if total.requires_grad:  # not so for an appearance step over frames that all lack a face
            total.backward()
            if not appearance_only:
                chunk.optimizer.step()
            self.shared_optimizer.step()
        with torch.no_grad():
            self.appearance.albedo.clamp_(0.0, 1.0)
        return terms

    def run_stage(self, size: int, epochs: int, appearance_only: bool, progress) -> None:
        """`epochs` passes over the chunks at pyramid level `size`, the rate decaying over the stage; logs the
        last epoch's mean terms."""
        config, chunks = self.config, self.chunks
        level = self.targets.level(size)
        factor = level_factor(config, size)
        weights = region_weights(self.appearance, self.head, self.init, level, config.chunk, factor)
        has_pixels = (weights.flatten(1).sum(1) > 0).tolist()  # [T] frames with an image term at this level
        steps, done = epochs * len(chunks), 0
        sums: dict[str, float] = {}
        for epoch in range(epochs):
            for index in range(len(chunks)):
                lr_factor = config.lr_decay ** (done / max(steps - 1, 1))
                terms = self.step(index, level, weights, has_pixels, appearance_only, factor, lr_factor)
                done += 1
                if epoch == epochs - 1:
                    for k, v in terms.items():
                        sums[k] = sums.get(k, 0.0) + v / len(chunks)
                if progress is not None:
                    progress(chunks[index].stop - chunks[index].start)
        stage = "appearance" if appearance_only else "pose"
        self.log.append(f"{stage} {size}px: {epochs} epoch(s), last epoch "
                        + ", ".join(f"{k} {v:.4g}" for k, v in sums.items()))

    def residuals(self, params_of, weights: Tensor) -> np.ndarray:
        """[T] photometric_loss per frame at the finest level with the parameters `params_of(chunk)`."""
        finest = self.finest
        out = np.full(finest.frames, np.nan)  # NaN: a frame without pixels to compare
        H, W = finest.images.shape[1:3]
        with torch.no_grad():
            for chunk in self.chunks:
                vertices = self.head.forward_params(params_of(chunk), vertex_ids=self.appearance.vertex_ids).vertices
                for i, row in enumerate(range(chunk.start, chunk.stop)):
                    if not bool(weights[row].sum() > 0):
                        continue
                    result = self.appearance.render(vertices[i], finest.viewmat[row], finest.K[row], W, H)
                    out[row] = float(photometric_loss(result.rgb, finest.images[row], weights[row]))
        return out

    def result(self) -> PhotometricResult:
        """The fitted parameters with the residuals before and after (on the initial parameters' face region)."""
        config, init, appearance = self.config, self.init, self.appearance
        weights = region_weights(appearance, self.head, init, self.finest, config.chunk)
        before = self.residuals(lambda c: init.rows(slice(c.start, c.stop)), weights)
        after = self.residuals(lambda c: self.frame_params(c, frozen=True), weights)
        fitted = HeadParams(shape=self.shape.detach().clone(), static_offset=init.static_offset,
                            **{k: torch.cat([c.values[k].detach() for c in self.chunks]) for k in FRAME_KEYS})
        blank = int(np.isnan(after).sum())
        self.log.append(f"residual (masked L1, {max(config.sizes)}px): {_nanmean(before):.4f} -> {_nanmean(after):.4f}"
                        + (f" ({blank} frame(s) without pixels to compare: no image term)" if blank else ""))
        return PhotometricResult(params=fitted, residual=after, residual_before=before,
                                 albedo=appearance.albedo.detach().numpy().copy(),
                                 light=appearance.light.detach().numpy().copy(), face_ids=appearance.face_ids,
                                 log=self.log)


def fit_photometric(head: HeadModel, init: HeadParams, targets: PhotometricTargets,
                    config: PhotometricConfig = PhotometricConfig(), landmarks: LandmarkTargets | None = None,
                    progress=None, appearance_start: tuple[np.ndarray, np.ndarray] | None = None) -> PhotometricResult:
    """Refine the per-frame parameters `init` [T] against the frames; see the module docstring.

    progress: callable(frames_done) after each chunk step, or None (total = frames x all epochs).
    appearance_start: (albedo [F, 3], light [9, 3]) of an earlier fit to start from (a long video's segments share the
    appearance fitted on a sample of all its frames): no albedo initialisation and no appearance-only epochs."""
    if init.batch != targets.frames:
        raise ValueError(f"photometric: {init.batch} frames of parameters but {targets.frames} images")
    fit = _PhotometricFit(head, init.detach().map(lambda x: x.float()), targets, config, landmarks, appearance_start)
    for size, epochs, appearance_only in _schedule(config, appearance_start is not None):
        if epochs > 0:
            fit.run_stage(size, epochs, appearance_only, progress)
    return fit.result()


def _nanmean(values: np.ndarray) -> float:
    """Mean over the finite entries (NaN when there is none), without numpy's empty-slice warning."""
    finite = values[np.isfinite(values)]
    return float(finite.mean()) if finite.size else float("nan")


def residual_report(residual: np.ndarray, residual_before: np.ndarray) -> dict:
    """The JSON summary of a fit's residuals [T] (prepare's report.json, track.json): means over the frames
    that had pixels to compare, per-frame values with null for the others."""
    listed = lambda values: [None if not np.isfinite(e) else round(float(e), 5) for e in values]  # noqa: E731
    return {"mean": _nanmean(residual), "mean_before": _nanmean(residual_before),
            "per_frame": listed(residual), "per_frame_before": listed(residual_before)}


def total_steps(config: PhotometricConfig, frames: int, appearance_start: bool = False) -> int:
    """Frames the progress callback will count: frames x every epoch of the schedule (no appearance-only epochs when
    the fit starts from a given appearance)."""
    return frames * ((0 if appearance_start else config.appearance_epochs) + sum(config.epochs))


__all__ = ["LandmarkTargets", "PhotometricConfig", "PhotometricResult", "PhotometricTargets", "SurfaceAppearance",
           "WEIGHTED_REGIONS", "fit_photometric", "photometric_loss", "sh_basis", "total_steps",
           "weighted_faces", "weighted_vertex_ids", "crop_boxes", "grow_faces", "region_weights", "render_at",
           "level_factor", "residual_report"]
