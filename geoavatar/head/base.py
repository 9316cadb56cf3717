"""HeadModel: the one interface every head model (FLAME, OpenHead) is served through.

A head model is plain arrays (`HeadModelData`) plus one function, linear blend skinning with
identity, expression and pose-corrective blend shapes, exactly as FLAME defines it. Both FLAME and
OpenHead produce `HeadModelData`; the mouth structure is added by appending to it
(`geoavatar.head.mouth`), so everything downstream sees one kind of object.

Parameter names and shapes follow the FLAME npz layout of VHAP / GaussianAvatars:
shape [300], expr [B,100], rotation [B,3], neck_pose [B,3], jaw_pose [B,3], eyes_pose [B,6],
translation [B,3], static_offset [B,V,3]. A model with fewer modes uses the leading entries.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Mapping, NamedTuple

import numpy as np
import torch
from torch import Tensor, nn

from geoavatar.geometry import axis_angle_to_matrix
from geoavatar.head.params import HeadParams, as_head_params

JOINT_NAMES = ("root", "neck", "jaw", "left_eye", "right_eye")
PARENTS = (-1, 0, 1, 1, 1)

# The 14 region names of FLAME_masks.pkl; OpenHead provides the same names.
REGION_NAMES = (
    "eye_region", "neck", "left_eyeball", "right_eyeball", "right_ear", "right_eye_region",
    "forehead", "lips", "nose", "scalp", "boundary", "face", "left_ear", "left_eye_region",
)

# Sizes of the FLAME npz layout (what datasets store).
FLAME_SHAPE_DIM = 300
FLAME_EXPR_DIM = 100


@dataclass
class HeadModelData:
    """Everything that defines a head model, as numpy arrays (float32 / int64).

    Coordinates are metres in a head-centred frame: +x to the subject's left, +y up, +z forward
    (out of the face), as FLAME.
    """

    name: str
    v_template: np.ndarray  # [V, 3]
    faces: np.ndarray  # [F, 3] int64
    shapedirs: np.ndarray  # [V, 3, S] identity basis
    exprdirs: np.ndarray  # [V, 3, E] expression basis
    j_regressor: np.ndarray  # [J, V] joints = J_reg @ shaped vertices
    lbs_weights: np.ndarray  # [V, J]
    posedirs: np.ndarray | None = None  # [V, 3, 9*(J-1)] pose correctives, or None
    regions: dict[str, np.ndarray] = field(default_factory=dict)  # region name -> vertex ids
    lip_ring_upper: np.ndarray | None = None  # [15] vertex ids, subject's right -> left (image left -> right)
    lip_ring_lower: np.ndarray | None = None  # [15] vertex ids, same order
    landmark_ids: np.ndarray | None = None  # [L] landmark ids in `landmark_convention`
    landmark_faces: np.ndarray | None = None  # [L] face index per landmark
    landmark_bary: np.ndarray | None = None  # [L, 3] barycentric coordinates in that face
    landmark_convention: str = "mediapipe478"
    vertex_groups: dict[str, np.ndarray] = field(default_factory=dict)  # e.g. mouth_upper, mouth_lower
    face_groups: dict[str, np.ndarray] = field(default_factory=dict)  # e.g. mouth -> face ids (F_m)
    metadata: dict = field(default_factory=dict)

    @property
    def num_vertices(self) -> int:
        return int(self.v_template.shape[0])

    def validate(self) -> "HeadModelData":
        """Check shapes and index ranges; raise ValueError naming the offending array."""
        v = self.num_vertices
        j = len(JOINT_NAMES)
        checks = [
            ("v_template", self.v_template.shape == (v, 3)),
            ("faces", self.faces.ndim == 2 and self.faces.shape[1] == 3),
            ("faces (index range)", self.faces.size == 0 or (self.faces.min() >= 0 and self.faces.max() < v)),
            ("shapedirs", self.shapedirs.ndim == 3 and self.shapedirs.shape[:2] == (v, 3)),
            ("exprdirs", self.exprdirs.ndim == 3 and self.exprdirs.shape[:2] == (v, 3)),
            ("j_regressor", self.j_regressor.shape == (j, v)),
            ("lbs_weights", self.lbs_weights.shape == (v, j)),
            ("posedirs", self.posedirs is None or self.posedirs.shape == (v, 3, 9 * (j - 1))),
        ]
        for ring_name in ("lip_ring_upper", "lip_ring_lower"):
            ring = getattr(self, ring_name)
            checks.append((ring_name, ring is None or (ring.shape == (15,) and ring.min() >= 0 and ring.max() < v)))
        if self.landmark_faces is not None:
            n = self.landmark_faces.shape[0]
            checks.append(("landmark_ids", self.landmark_ids is not None and self.landmark_ids.shape == (n,)))
            checks.append(("landmark_bary", self.landmark_bary is not None and self.landmark_bary.shape == (n, 3)))
            checks.append(("landmark_faces (index range)", n == 0 or self.landmark_faces.max() < len(self.faces)))
        for name, ok in checks:
            if not ok:
                raise ValueError(f"head model '{self.name}': array '{name}' has an invalid shape or range")
        return self

    def copy_with(self, **changes) -> "HeadModelData":
        return replace(self, **changes)


class HeadOutput(NamedTuple):
    vertices: Tensor  # [B, V, 3] posed vertices (or [V, 3] for an unbatched call)
    landmarks: Tensor | None  # [B, L, 3] (or [L, 3]); None without a landmark embedding
    joints: Tensor  # [B, J, 3] posed joint locations (or [J, 3])


class HeadModel(nn.Module):
    """A FLAME-style parametric head: LBS over 5 joints with identity/expression/pose blend shapes.

    Works on CPU or GPU (`.to(device)`), batched, differentiable in every parameter.
    """

    def __init__(self, data: HeadModelData):
        super().__init__()
        data.validate()
        self.data = data
        self.name = data.name
        f32 = lambda a: torch.as_tensor(np.asarray(a, dtype=np.float32))  # noqa: E731
        i64 = lambda a: torch.as_tensor(np.asarray(a, dtype=np.int64))  # noqa: E731
        self.register_buffer("v_template", f32(data.v_template), persistent=False)  # [V, 3]
        self.register_buffer("faces", i64(data.faces), persistent=False)  # [F, 3]
        self.register_buffer("shapedirs", f32(data.shapedirs), persistent=False)  # [V, 3, S]
        self.register_buffer("exprdirs", f32(data.exprdirs), persistent=False)  # [V, 3, E]
        self.register_buffer("j_regressor", f32(data.j_regressor), persistent=False)  # [J, V]
        self.register_buffer("lbs_weights", f32(data.lbs_weights), persistent=False)  # [V, J]
        posedirs = data.posedirs if data.posedirs is not None else np.zeros((data.num_vertices, 3, 0), np.float32)
        self.register_buffer("posedirs", f32(posedirs), persistent=False)  # [V, 3, P]
        self.parents = PARENTS
        if data.landmark_faces is not None:
            self.register_buffer("landmark_faces", i64(data.landmark_faces), persistent=False)  # [L]
            self.register_buffer("landmark_bary", f32(data.landmark_bary), persistent=False)  # [L, 3]
            self.register_buffer("landmark_ids", i64(data.landmark_ids), persistent=False)  # [L]
        else:
            self.landmark_faces = None
            self.landmark_bary = None
            self.landmark_ids = None
        # The joint regressor applied to the template and the bases (joints are linear in them): the
        # vertex-subset mode of forward() gets exact joints without shaping every vertex.
        self.register_buffer("joint_template", self.j_regressor @ self.v_template, persistent=False)  # [J, 3]
        self.register_buffer("joint_shapedirs", torch.einsum("jv,vcs->jcs", self.j_regressor, self.shapedirs),
                             persistent=False)  # [J, 3, S]
        self.register_buffer("joint_exprdirs", torch.einsum("jv,vce->jce", self.j_regressor, self.exprdirs),
                             persistent=False)  # [J, 3, E]

    # --- sizes and metadata -------------------------------------------------------------------
    @property
    def num_vertices(self) -> int:
        return int(self.v_template.shape[0])

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    @property
    def num_shape(self) -> int:
        return int(self.shapedirs.shape[-1])

    @property
    def num_expr(self) -> int:
        return int(self.exprdirs.shape[-1])

    @property
    def regions(self) -> dict[str, np.ndarray]:
        return self.data.regions

    @property
    def lip_ring_upper(self) -> np.ndarray | None:
        return self.data.lip_ring_upper

    @property
    def lip_ring_lower(self) -> np.ndarray | None:
        return self.data.lip_ring_lower

    @property
    def vertex_groups(self) -> dict[str, np.ndarray]:
        return self.data.vertex_groups

    @property
    def face_groups(self) -> dict[str, np.ndarray]:
        return self.data.face_groups

    def zero_params(self, batch: int = 1, device=None) -> dict[str, Tensor]:
        """Neutral parameters in the FLAME npz layout (the model's own mode counts)."""
        device = device or self.v_template.device
        z = lambda *s: torch.zeros(*s, device=device)  # noqa: E731
        return {
            "shape": z(self.num_shape),
            "expr": z(batch, self.num_expr),
            "rotation": z(batch, 3),
            "neck_pose": z(batch, 3),
            "jaw_pose": z(batch, 3),
            "eyes_pose": z(batch, 6),
            "translation": z(batch, 3),
        }

    # --- the model -----------------------------------------------------------------------------
    def forward(
        self,
        shape: Tensor,  # [S'] or [B, S'] identity coefficients (leading S used)
        expr: Tensor,  # [B, E'] or [E'] expression coefficients (leading E used)
        rotation: Tensor,  # [B, 3] or [3] global rotation, axis-angle
        neck_pose: Tensor,  # [B, 3] or [3]
        jaw_pose: Tensor,  # [B, 3] or [3]
        eyes_pose: Tensor,  # [B, 6] or [6] left eye then right eye, axis-angle
        translation: Tensor,  # [B, 3] or [3]
        static_offset: Tensor | None = None,  # [B|1, V', 3] or [V', 3]; V' <= V, missing vertices get 0
        vertex_ids: Tensor | None = None,  # [K] long: pose only these vertices (the batched subset mode)
    ) -> HeadOutput:
        """The posed head. With `vertex_ids`, `vertices` holds only those vertices ([B, K, 3]), the
        joints are exact, and `landmarks` is given when the ids cover every landmark face; the skinning
        is then applied with broadcast products and GEMMs (on CPU 10-20x faster than the per-vertex
        3x3 matmuls of the full mode for the [frames x ~400] vertex batches of landmark tracking)."""
        unbatched = rotation.dim() == 1
        if unbatched:
            expr, rotation, neck_pose, jaw_pose, eyes_pose, translation = (
                t[None] for t in (expr, rotation, neck_pose, jaw_pose, eyes_pose, translation)
            )
            if static_offset is not None and static_offset.dim() == 2:
                static_offset = static_offset[None]
        if vertex_ids is not None:
            output = self._forward_subset(shape, expr, rotation, neck_pose, jaw_pose, eyes_pose, translation,
                                          static_offset, vertex_ids)
            if unbatched:
                return HeadOutput(*(None if t is None else t[0] for t in output))
            return output
        batch = rotation.shape[0]
        dtype = self.v_template.dtype

        shape = _fit_modes(shape, self.num_shape, "shape").to(dtype)
        if shape.dim() == 1:
            shape = shape[None]
        expr = _fit_modes(expr, self.num_expr, "expr").to(dtype)

        v_shaped = (
            self.v_template[None]
            + torch.einsum("bs,vcs->bvc", shape, self.shapedirs)
            + torch.einsum("be,vce->bvc", expr, self.exprdirs)
        )  # [B, V, 3] (broadcast over B when shape is [1, S])
        if v_shaped.shape[0] != batch:
            v_shaped = v_shaped.expand(batch, -1, -1)
        if static_offset is not None:
            v_shaped = v_shaped + _pad_vertices(static_offset.to(dtype), self.num_vertices)

        joints = torch.einsum("jv,bvc->bjc", self.j_regressor, v_shaped)  # [B, J, 3]
        rot_mats = _joint_rotations(rotation, neck_pose, jaw_pose, eyes_pose, dtype)  # [B, J, 3, 3]

        v_posed = v_shaped
        if self.posedirs.shape[-1] > 0:
            v_posed = v_posed + torch.einsum("bp,vcp->bvc", _pose_feature(rot_mats), self.posedirs)

        posed_joints, rel_transforms = _rigid_chain(rot_mats, joints, self.parents)  # [B,J,3], [B,J,4,4]
        per_vertex = torch.einsum("vj,bjmn->bvmn", self.lbs_weights, rel_transforms)  # [B, V, 4, 4]
        vertices = (per_vertex[..., :3, :3] @ v_posed[..., None]).squeeze(-1) + per_vertex[..., :3, 3]
        offset = translation.to(dtype)[:, None, :]  # [B, 1, 3]
        vertices = vertices + offset
        posed_joints = posed_joints + offset

        landmarks = None
        if self.landmark_faces is not None:
            landmarks = _barycentric(vertices, self.faces[self.landmark_faces], self.landmark_bary)  # [B, L, 3]

        if unbatched:
            return HeadOutput(vertices[0], None if landmarks is None else landmarks[0], posed_joints[0])
        return HeadOutput(vertices, landmarks, posed_joints)

    def _forward_subset(self, shape, expr, rotation, neck_pose, jaw_pose, eyes_pose, translation, static_offset,
                        vertex_ids: Tensor) -> HeadOutput:
        """forward() for the vertices `vertex_ids` only (batched inputs); see forward's docstring.

        The joints come from the joint-regressed bases (`joint_template`, ...) stacked under the
        vertex rows, so one GEMM shapes both."""
        batch, dtype = rotation.shape[0], self.v_template.dtype
        vertex_ids = vertex_ids.to(self.v_template.device)
        count, num_joints = int(vertex_ids.numel()), self.joint_template.shape[0]
        rows = count + num_joints
        template = torch.cat([self.v_template[vertex_ids], self.joint_template])  # [K + J, 3]
        shapedirs = torch.cat([self.shapedirs[vertex_ids], self.joint_shapedirs])  # [K + J, 3, S]
        exprdirs = torch.cat([self.exprdirs[vertex_ids], self.joint_exprdirs])  # [K + J, 3, E]

        shape = _fit_modes(shape, self.num_shape, "shape").to(dtype).reshape(-1, self.num_shape)
        expr = _fit_modes(expr, self.num_expr, "expr").to(dtype)
        if shape.shape[0] == 1:
            identity = template + (shapedirs @ shape[0])  # [K + J, 3]
        else:
            identity = template[None] + torch.einsum("bs,vcs->bvc", shape, shapedirs)  # [B, K + J, 3]
        expression = (expr @ exprdirs.reshape(rows * 3, -1).T).reshape(batch, rows, 3)  # GEMM, [B, K + J, 3]
        v_shaped = identity + expression  # [B, K + J, 3]
        if static_offset is not None:
            offset = _pad_vertices(static_offset.to(dtype), self.num_vertices)  # [B|1, V, 3] (or [V, 3])
            offset = offset[None] if offset.dim() == 2 else offset
            joint_offset = torch.einsum("jv,bvc->bjc", self.j_regressor, offset)  # [B|1, J, 3]
            v_shaped = v_shaped + torch.cat([offset[:, vertex_ids], joint_offset], dim=1)
        joints = v_shaped[:, count:]  # [B, J, 3]
        v_shaped = v_shaped[:, :count]  # [B, K, 3]

        rot_mats = _joint_rotations(rotation, neck_pose, jaw_pose, eyes_pose, dtype)  # [B, J, 3, 3]
        if self.posedirs.shape[-1] > 0:
            posedirs = self.posedirs[vertex_ids].reshape(count * 3, -1)  # [K * 3, P]
            v_shaped = v_shaped + (_pose_feature(rot_mats) @ posedirs.T).reshape(batch, count, 3)
        posed_joints, transforms = _rigid_chain(rot_mats, joints, self.parents)  # [B, J, 3], [B, J, 4, 4]
        blended = (self.lbs_weights[vertex_ids] @ transforms[:, :, :3, :].reshape(batch, num_joints, 12))
        blended = blended.reshape(batch, count, 3, 4)  # per-vertex [R | t]
        # R v + t per vertex; einsum (a batched GEMV) is ~7x faster on CPU than a broadcast product summed over its
        # last axis of 3, with the same sums
        vertices = torch.einsum("bkij,bkj->bki", blended[..., :3], v_shaped) + blended[..., 3]  # [B, K, 3]
        offset = translation.to(dtype)[:, None, :]  # [B, 1, 3]
        vertices = vertices + offset

        landmarks = None
        if self.landmark_faces is not None:
            position = torch.full((self.num_vertices,), -1, dtype=torch.long, device=vertex_ids.device)
            position[vertex_ids] = torch.arange(count, device=vertex_ids.device)
            local_faces = position[self.faces[self.landmark_faces]]  # [L, 3] rows of `vertices`
            if bool((local_faces >= 0).all()):
                landmarks = _barycentric(vertices, local_faces, self.landmark_bary)  # [B, L, 3]
        return HeadOutput(vertices, landmarks, posed_joints + offset)

    @property
    def landmark_vertex_ids(self) -> Tensor:
        """[K] sorted ids of the vertices of the landmark faces: forward(..., vertex_ids=...) of these
        gives the landmarks at the cost of K vertices."""
        if self.landmark_faces is None:
            raise ValueError(f"head model '{self.name}' has no landmark embedding")
        return torch.unique(self.faces[self.landmark_faces])

    def forward_params(self, params: "HeadParams | Mapping[str, Tensor]", vertex_ids: Tensor | None = None) -> HeadOutput:
        """forward() from HeadParams or a dict in the FLAME npz layout (extra keys are ignored)."""
        p = as_head_params(params)
        return self(p.shape, p.expr, p.rotation, p.neck_pose, p.jaw_pose, p.eyes_pose, p.translation,
                    p.static_offset, vertex_ids=vertex_ids)

    def template_output(self) -> HeadOutput:
        """The neutral head (all parameters zero)."""
        return self.forward_params(self.zero_params(1))


def _joint_rotations(rotation: Tensor, neck_pose: Tensor, jaw_pose: Tensor, eyes_pose: Tensor, dtype) -> Tensor:
    """[B, J, 3, 3] rotation of every joint from the axis-angle pose parameters ([B, 3] ... [B, 6])."""
    full_pose = torch.cat([rotation, neck_pose, jaw_pose, eyes_pose], dim=-1).to(dtype)  # [B, 15]
    return axis_angle_to_matrix(full_pose.reshape(full_pose.shape[0], -1, 3))


def _pose_feature(rot_mats: Tensor) -> Tensor:
    """[B, 9*(J-1)]: the joint rotations below the root minus identity (what the pose correctives weigh)."""
    eye = torch.eye(3, dtype=rot_mats.dtype, device=rot_mats.device)
    return (rot_mats[:, 1:] - eye).reshape(rot_mats.shape[0], -1)


def _barycentric(vertices: Tensor, faces: Tensor, bary: Tensor) -> Tensor:
    """[B, L, 3] points at barycentric coordinates bary [L, 3] in faces [L, 3] of vertices [B, V, 3]."""
    tri = vertices[:, faces]  # [B, L, 3, 3]
    # the three corners' terms added in turn: the sum over a middle axis of 3 was ~3x slower on CPU (same sums)
    return tri[:, :, 0] * bary[:, 0:1] + tri[:, :, 1] * bary[:, 1:2] + tri[:, :, 2] * bary[:, 2:3]


def _fit_modes(coeffs: Tensor, modes: int, name: str) -> Tensor:
    """Use the leading `modes` coefficients; zero-pad when fewer are given."""
    have = coeffs.shape[-1]
    if have >= modes:
        return coeffs[..., :modes]
    pad = torch.zeros(*coeffs.shape[:-1], modes - have, dtype=coeffs.dtype, device=coeffs.device)
    return torch.cat([coeffs, pad], dim=-1)


def _pad_vertices(offset: Tensor, num_vertices: int) -> Tensor:
    """static_offset written for the model without its mouth structure: the appended vertices get 0."""
    have = offset.shape[-2]
    if have > num_vertices:
        raise ValueError(f"static_offset has {have} vertices but the head model has {num_vertices}")
    if have == num_vertices:
        return offset
    pad = torch.zeros(*offset.shape[:-2], num_vertices - have, 3, dtype=offset.dtype, device=offset.device)
    return torch.cat([offset, pad], dim=-2)


def _rigid_chain(rot_mats: Tensor, joints: Tensor, parents: tuple[int, ...]) -> tuple[Tensor, Tensor]:
    """Forward kinematics.

    rot_mats [B, J, 3, 3], joints [B, J, 3] (rest pose) ->
    posed joints [B, J, 3] and transforms [B, J, 4, 4] that map rest-pose points to posed points.
    """
    batch, num_joints = joints.shape[:2]
    rel_joints = joints.clone()
    rel_joints[:, 1:] = joints[:, 1:] - joints[:, list(parents[1:])]
    local = torch.zeros(batch, num_joints, 4, 4, dtype=joints.dtype, device=joints.device)
    local[..., :3, :3] = rot_mats
    local[..., :3, 3] = rel_joints
    local[..., 3, 3] = 1.0
    chain = [local[:, 0]]
    for i in range(1, num_joints):
        chain.append(chain[parents[i]] @ local[:, i])
    world = torch.stack(chain, dim=1)  # [B, J, 4, 4]
    posed_joints = world[..., :3, 3]
    # Remove the rest-pose joint location so the transform acts on rest-pose vertices.
    correction = (world[..., :3, :3] @ joints[..., None]).squeeze(-1)  # [B, J, 3]
    rel = world.clone()
    rel[..., :3, 3] = world[..., :3, 3] - correction
    return posed_joints, rel
