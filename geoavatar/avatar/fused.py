"""The per-Gaussian maths of binding.py as autograd Functions with hand-written backwards.

Why: written as ordinary PyTorch ops, placing N Gaussians on their faces (gather the face frame,
rotate, scale, compose quaternions) and their polar coordinates cost some 60 ops forward and as many
backward nodes over [N, ...] tensors, and the gradient of every face gather was an
index_put_(accumulate=True), the slowest op of the training step after the rasterizer. Here the face
data is gathered once from one [F, 17] table and the face gradients go back with one index_add_; the
backward is plain PyTorch, so it runs on any device. The formulas are documented in binding.py;
tests/test_avatar.py checks both Functions with gradcheck and against autograd of the plain ops.

On CPU the same maths runs as loops of this layer's native extension (csrc/binding_cpu.cpp, built on first use
by geoavatar.native), when it builds: tests/test_fused.py checks them against the Functions here.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from geoavatar.native import ExtensionSpec, load_extension as load_native_extension, new_state
from geoavatar.geometry import quaternion_multiply

_EPS = 1e-12  # F.normalize's and vector_norm's floor, as the plain-op code used
NORMAL_AXIS = 1  # local axis along the face normal (a1)
TABLE_WIDTH = 17  # per-face row: R row-major (9), C (3), k (1), face quaternion (4)
_CONJ = (1.0, -1.0, -1.0, -1.0)

_EXTENSION = ExtensionSpec(
    name="binding_cpu", source=Path(__file__).with_name("csrc") / "binding_cpu.cpp",
    what="the avatar's native CPU loops (face placement, polar coordinates, surface splats)",
    instead="the avatar places its Gaussians on CPU with PyTorch ops (slower)")
_state = new_state()


def load_extension():
    """The compiled module of csrc/binding_cpu.cpp (built on first use), or None with one warning."""
    return load_native_extension(_EXTENSION, _state)


def native_loops_available() -> bool:
    """True when the native placement and polar-coordinate loops are built and loaded (builds them first)."""
    return load_extension() is not None


def _conj(q: Tensor) -> Tensor:
    """Conjugate of component-major quaternions [4, ...]."""
    return q * q.new_tensor(_CONJ).view(4, *([1] * (q.dim() - 1)))


def _qmul(a: Tensor, b: Tensor) -> Tensor:
    return quaternion_multiply(a, b, dim=0)


def _rows(rows: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """[17, ...] -> R [3, 3, ...], C [3, ...], k [...], face quaternion [4, ...] (views)."""
    return rows[:9].unflatten(0, (3, 3)), rows[9:12], rows[12], rows[13:17]


def _rotate(rot: Tensor, v: Tensor) -> Tensor:
    """R v for component-major R [3, 3, ...], v [3, ...] -> [3, ...] (as 3-term sums: long inner loops)."""
    return rot[:, 0] * v[0] + rot[:, 1] * v[1] + rot[:, 2] * v[2]


def _norm(x: Tensor) -> Tensor:
    """Euclidean norm over the component axis of [C, ...] (vector_norm over dim 0 runs a slow strided loop on CPU)."""
    return sum(c * c for c in x.unbind(0)).sqrt()


def _aos(x: Tensor) -> Tensor:
    """Component-major [C, ...] -> contiguous [..., C]."""
    return x.movedim(0, -1).contiguous()


def _soa(x: Tensor) -> Tensor:
    """[..., C] -> contiguous component-major [C, ...]."""
    return x.movedim(-1, 0).contiguous()


class _PlaceGaussians(torch.autograd.Function):
    """mu_g = k R mu + C, q_g = q_face (x) normalize(q), s_g = k exp(s) for every (batch, Gaussian).

    Inside, tensors are component-major ([3, B, N]: every component a contiguous row), so each op runs
    one long loop; an [N, 3] layout would give TensorIterator inner loops of 3 elements."""

    @staticmethod
    def forward(ctx, table: Tensor, means: Tensor, quats: Tensor, log_scales: Tensor, index: Tensor):
        # table [17, M] face columns (M = B * F); index [B, N] column of each placed Gaussian; locals [N, ...]
        rows = table.index_select(1, index.reshape(-1)).view(TABLE_WIDTH, *index.shape)  # [17, B, N]
        rot, centre, k, face_q = _rows(rows)
        mu = _soa(means)[:, None]  # [3, 1, N]
        q = _soa(quats)  # [4, N]
        norm = _norm(q).clamp_min(_EPS)  # [N]
        unit_q = q / norm  # [4, N]
        exp_s = torch.exp(_soa(log_scales))[:, None]  # [3, 1, N]
        ctx.save_for_backward(rows, mu, unit_q, norm, exp_s, index)
        ctx.table_columns = table.shape[1]
        means_g = k * _rotate(rot, mu) + centre  # [3, B, N]
        quats_g = _qmul(face_q, unit_q[:, None].expand_as(face_q))  # [4, B, N]
        return _aos(means_g), _aos(quats_g), _aos(k * exp_s)

    @staticmethod
    @once_differentiable
    def backward(ctx, g_means: Tensor, g_quats: Tensor, g_scales: Tensor):
        rows, mu, unit_q, norm, exp_s, index = ctx.saved_tensors
        rot, _, k, face_q = _rows(rows)
        g_means, g_quats, g_scales = _soa(g_means), _soa(g_quats), _soa(g_scales)  # [3|4, B, N]
        k_g_means = k * g_means  # [3, B, N]
        g_table = None
        if ctx.needs_input_grad[0]:
            b, n = index.shape
            per_gaussian = torch.cat([
                (k_g_means[:, None] * mu[None]).reshape(9, b * n),  # dR = k g mu^T
                g_means.reshape(3, b * n),  # dC
                ((g_means * _rotate(rot, mu)).sum(0) + (g_scales * exp_s).sum(0)).reshape(1, b * n),  # dk
                # d(a (x) b)/da = g (x) conj(b)
                _qmul(g_quats, _conj(unit_q)[:, None].expand_as(g_quats)).reshape(4, b * n),
            ])  # [17, B * N]
            g_table = rows.new_zeros(TABLE_WIDTH, ctx.table_columns).index_add_(1, index.reshape(-1), per_gaussian)
        # R^T (k g), summed over the batch
        g_mu = (rot[0] * k_g_means[0] + rot[1] * k_g_means[1] + rot[2] * k_g_means[2]).sum(1)  # [3, N]
        g_unit = _qmul(_conj(face_q), g_quats).sum(1)  # d(a (x) b)/db = conj(a) (x) g  [4, N]
        # normalize's backward: (g - u (u . g)) / |q|, and g / eps where the norm was clamped
        radial = torch.where(norm > _EPS, (unit_q * g_unit).sum(0), 0.0)  # [N]
        g_q = (g_unit - unit_q * radial) / norm  # [4, N]
        g_s = (g_scales * k).sum(1) * exp_s[:, 0]  # [3, N]
        return g_table, g_mu.t(), g_q.t(), g_s.t(), None


class _PlaceGaussiansCPU(torch.autograd.Function):
    """_PlaceGaussians in the native CPU extension (place_forward / place_backward in
    csrc/binding_cpu.cpp): one loop over the Gaussians each way instead of some 70 PyTorch ops
    (15 % of a 1-thread training step at 100k Gaussians). The table is [M, 17] here, not [17, M]."""

    @staticmethod
    def forward(ctx, table: Tensor, means: Tensor, quats: Tensor, log_scales: Tensor, index: Tensor):
        args = [t.detach().contiguous() for t in (table, means, quats, log_scales)]
        index = index.reshape(-1).contiguous()
        means_g, quats_g, scales_g, aux = load_extension().place_forward(*args, index)
        ctx.save_for_backward(*args, index, aux)  # aux: q / |q|, exp(s), |q| per Gaussian
        return means_g, quats_g, scales_g

    @staticmethod
    @once_differentiable
    def backward(ctx, g_means: Tensor, g_quats: Tensor, g_scales: Tensor):
        table, means, quats, log_scales, index, aux = ctx.saved_tensors
        dtype = means.dtype
        g_table, g_mu, g_q, g_s = load_extension().place_backward(
            table, means, quats, log_scales, index, aux, g_means.to(dtype).contiguous(), g_quats.to(dtype).contiguous(),
            g_scales.to(dtype).contiguous(), ctx.needs_input_grad[0])
        return g_table if ctx.needs_input_grad[0] else None, g_mu, g_q, g_s, None


def _native_placement(*tensors: Tensor) -> bool:
    """CPU float tensors of one dtype and the native extension loaded (or loadable: as rasterize's "auto" builds
    the rasterizer): the native loops (placement, polar coordinates, surface splats) run."""
    dtype = tensors[0].dtype
    if dtype not in (torch.float32, torch.float64) or any(t.device.type != "cpu" or t.dtype != dtype for t in tensors):
        return False
    return native_loops_available()


def place_gaussians(
    rotation: Tensor,  # [..., F, 3, 3] face frames (columns a0, a1, a2)
    centre: Tensor,  # [..., F, 3]
    scale: Tensor,  # [..., F]
    face_quat: Tensor,  # [..., F, 4] quaternion of `rotation`
    means: Tensor,  # [N, 3] local means
    quats: Tensor,  # [N, 4] local rotations, any norm
    log_scales: Tensor,  # [N, 3]
    binding: Tensor,  # [N] face of each Gaussian
    native: bool | None = None,  # the native CPU loops (_PlaceGaussiansCPU); None: where they run
) -> tuple[Tensor, Tensor, Tensor]:
    """Global means [..., N, 3], quats [..., N, 4], scales [..., N, 3] (see binding.local_to_global)."""
    batch = rotation.shape[:-3]
    faces = rotation.shape[-3]
    table = torch.cat([rotation.flatten(-2), centre, scale[..., None], face_quat], dim=-1)  # [..., F, 17]
    count = int(torch.Size(batch).numel())
    binding = binding.to(device=means.device, dtype=torch.long)
    index = torch.arange(count, device=means.device)[:, None] * faces + binding  # [B, N] table column
    if native is None:
        native = _native_placement(table, means, quats, log_scales)
    if native:
        means_g, quats_g, scales_g = _PlaceGaussiansCPU.apply(table.reshape(-1, TABLE_WIDTH), means, quats, log_scales,
                                                              index)
    else:
        means_g, quats_g, scales_g = _PlaceGaussians.apply(table.reshape(-1, TABLE_WIDTH).t(), means, quats,
                                                           log_scales, index)
    n = means.shape[0]
    return means_g.view(*batch, n, 3), quats_g.view(*batch, n, 4), scales_g.view(*batch, n, 3)


class _PolarCoordinates(torch.autograd.Function):
    """r = |mu|, phi = atan2(|mu_tangent|, mu_normal) (|mu_normal| when two-sided); phi = 0 at the origin."""

    @staticmethod
    def forward(ctx, means: Tensor, two_sided: bool):
        mu = _soa(means)  # [3, N]
        r = _norm(mu)  # [N]
        tiny = r <= _EPS
        tangent_axes = [a for a in range(3) if a != NORMAL_AXIS]
        normal = mu[NORMAL_AXIS]
        tangent = _norm(mu[tangent_axes])  # [N]
        normal = torch.where(tiny, 1.0, normal.abs() if two_sided else normal)
        tangent = torch.where(tiny, 0.0, tangent)
        ctx.save_for_backward(mu, r, tangent, normal)
        ctx.two_sided = two_sided
        return r, torch.atan2(tangent, normal)

    @staticmethod
    @once_differentiable
    def backward(ctx, g_r: Tensor, g_phi: Tensor):
        mu, r, tangent, normal = ctx.saved_tensors
        grad = torch.where(r > 0, g_r / r, 0.0) * mu  # d r = mu / r (vector_norm's zero subgradient at 0)  [3, N]
        # atan2(t, n): d t = n / (t^2 + n^2), d n = -t / (t^2 + n^2); no gradient at the origin
        live = r > _EPS
        g = torch.where(live, g_phi, 0.0) / torch.where(live, tangent * tangent + normal * normal, 1.0)  # [N]
        g_t = torch.where(tangent > 0, g * normal / torch.where(tangent > 0, tangent, 1.0), 0.0)  # d t = mu_t / t
        g_n = -g * tangent
        if ctx.two_sided:
            g_n = g_n * torch.sign(mu[NORMAL_AXIS])
        for axis in range(3):
            if axis != NORMAL_AXIS:
                grad[axis] += g_t * mu[axis]
        grad[NORMAL_AXIS] += g_n
        return grad.t(), None


class _PolarCoordinatesCPU(torch.autograd.Function):
    """_PolarCoordinates in the native CPU extension (polar_forward / polar_backward in
    csrc/binding_cpu.cpp): one loop each way instead of ~25 PyTorch ops."""

    @staticmethod
    def forward(ctx, means: Tensor, two_sided: bool):
        mu = means.detach().contiguous()
        ctx.save_for_backward(mu)
        ctx.two_sided = two_sided
        r, phi = load_extension().polar_forward(mu, two_sided)
        return r, phi

    @staticmethod
    @once_differentiable
    def backward(ctx, g_r: Tensor, g_phi: Tensor):
        (mu,) = ctx.saved_tensors
        grad = load_extension().polar_backward(mu, g_r.to(mu.dtype).contiguous(), g_phi.to(mu.dtype).contiguous(),
                                               ctx.two_sided)
        return grad, None


def polar_coordinates(local_means: Tensor, two_sided: bool = False,
                      native: bool | None = None) -> tuple[Tensor, Tensor]:
    """r [N], phi [N] of local means [N, 3], phi measured from the face normal (see binding.polar_coordinates);
    `native`: the CPU loops (_PolarCoordinatesCPU), None: where they run."""
    if native is None:
        native = _native_placement(local_means)
    if native:
        return _PolarCoordinatesCPU.apply(local_means, two_sided)
    return _PolarCoordinates.apply(local_means, two_sided)


class _SurfaceSplatsCPU(torch.autograd.Function):
    """A mesh's faces as one Gaussian each (centroid, std from the area, SH-shaded albedo) in the native CPU extension
    (surface_forward / surface_backward in csrc/binding_cpu.cpp): what prep's photometric appearance model computes
    with ~25 PyTorch ops forward and ~40 backward per frame (prep/photometric.SurfaceAppearance, one Gaussian per
    face)."""

    @staticmethod
    def forward(ctx, vertices: Tensor, albedo: Tensor, light: Tensor, faces: Tensor, size: float):
        args = [t.detach().contiguous() for t in (vertices, faces, albedo, light)]
        centres, std, colours, frames = load_extension().surface_forward(*args, size)
        ctx.save_for_backward(*args, frames)
        ctx.size = size
        if not ctx.needs_input_grad[0]:  # fixed vertices (an appearance-only step): no gradient through the geometry
            ctx.mark_non_differentiable(centres, std)
        return centres, std, colours

    @staticmethod
    @once_differentiable
    def backward(ctx, g_centres: Tensor, g_std: Tensor, g_colours: Tensor):
        vertices, faces, albedo, light, frames = ctx.saved_tensors
        count = faces.shape[0]

        def rows(grad: Tensor | None, *shape: int) -> Tensor:  # an output without a gradient counts as zeros
            return vertices.new_zeros(count, *shape) if grad is None else grad.to(vertices.dtype).contiguous()

        g_vertices, g_albedo, g_light = load_extension().surface_backward(
            vertices, faces, albedo, light, frames, rows(g_centres, 3), rows(g_std), rows(g_colours, 3), ctx.size)
        needs = ctx.needs_input_grad
        return (g_vertices if needs[0] else None, g_albedo if needs[1] else None, g_light if needs[2] else None,
                None, None)


def surface_splats(vertices: Tensor, albedo: Tensor, light: Tensor, faces: Tensor,
                   size: float) -> tuple[Tensor, Tensor, Tensor] | None:
    """centres [F, 3], std [F], colours [F, 3] of one Gaussian per face of `faces` [F, 3] (rows of vertices [K, 3]):
    at the centroid, std = size * sqrt(area), colour = albedo [F, 3] * (SH basis of the face normal @ light [9, 3]);
    None where the native loops do not run (not CPU float tensors of one dtype, or no compiler): the caller's
    PyTorch ops then do it."""
    if not _native_placement(vertices, albedo, light):
        return None
    return _SurfaceSplatsCPU.apply(vertices, albedo, light, faces, size)
