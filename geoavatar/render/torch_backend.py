"""Pure-PyTorch Gaussian rasterizer following gsplat 1.5.3's conventions (CPU and CUDA tensors).

Conventions (read from gsplat 1.5.3: ProjectionEWA3DGSFused.cu, Utils.cuh, RasterizeToPixels3DGS*.cu):

- Projection: camera-space mean x_c = R x + t; Gaussians with z < 0.01 (near plane) or z > 1e10 are
  culled. EWA: cov2d = J R Σ Rᵀ Jᵀ with the pinhole Jacobian J evaluated at (x, y) clamped to
  ±(1.3 × tan(fov/2)) around the principal point (the "frustum clamp"), then 0.3 px² added to the
  diagonal (low-pass dilation). det(cov2d) <= 0 culls.
- Box: extent = min(3.33, sqrt(2 ln(255 · opacity))) standard deviations per axis (gsplat's
  opacity-aware box); radius = ceil(extent · sqrt(cov2d_ii)) per axis; opacity < 1/255 culls, and so
  does a box entirely outside the image. Outside that box a Gaussian's alpha is < 1/255 for
  opacities <= 1, so it never contributes there.
- Pixels: centres at (j + 0.5, i + 0.5); sigma = ½ dᵀ Σ⁻¹ d with d = mean2d − pixel;
  alpha = min(0.999, o · exp(−sigma)) (gsplat 1.5.3 uses 0.999; the original 3DGS kernel 0.99);
  alpha < 1/255 is skipped; Gaussians are composited front to back in depth order and a pixel stops
  *before* the Gaussian that would bring its transmittance to <= 1e-4.
- Output: rgb = Σ c_k α_k T_k + T_final · background, alpha = 1 − T_final.

Implementation: (tile, Gaussian) rows. The image is cut into small square tiles (4 px by default).
Each visible Gaussian, taken in depth order, emits one row per tile its box touches; a stable sort by
tile groups the rows tile by tile while keeping depth order. A chunk of rows is a dense
[rows, tile_px] tensor (column = pixel of the tile): log(o) − sigma is one matrix product of per-row
coefficients with the tile's pixel monomials, and the per-pixel front-to-back product is a
column-wise segmented cumulative sum of log(1 − α) in float64 (no per-pixel sort). Rows that reach
no pixel (before the scan), or that lie behind saturated pixels (after it), are dropped. Compositing
is a custom autograd.Function with a hand-written backward; forward keeps alpha and T of the
surviving pairs when they fit in a budget (else backward recomputes them chunk by chunk), so memory
stays bounded by the chunk size and the number of overlaps, never [pixels × Gaussians].

Two details differ from gsplat's kernel without changing results: gsplat's `sigma < 0` test is
omitted (the conic is positive definite, so sigma >= 0; the matrix-product form can round to a tiny
negative value at the mean, where gsplat computes exactly 0), and the coverage is accumulated as
alpha = Σ α_k T_k, which equals gsplat's 1 − T_final up to rounding.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

# gsplat 1.5.3 constants (see the module docstring).
NEAR_PLANE = 0.01
FAR_PLANE = 1e10
EPS2D = 0.3
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.999
TRANSMITTANCE_MIN = 1e-4
MAX_EXTENT_SIGMA = 3.33
FOV_CLAMP_MARGIN = 0.3  # Jacobian clamp at (1 + 0.3) x the half field of view

DEFAULT_TILE_SIZE = 4
DEFAULT_CHUNK_PAIRS = 1 << 20  # (row, pixel) pairs processed at once: bounds peak memory
# Up to this many (row, pixel) pairs, forward keeps alpha and T of every pair (8 bytes/pair in float32)
# so backward need not recompute them; above it, backward recomputes chunk by chunk.
DEFAULT_KEEP_PAIRS = 1 << 25


class Projection(NamedTuple):
    """Screen-space Gaussians for one camera (culled ones: visible False, radii 0, means2d 0)."""

    means2d: Tensor  # [N, 2] pixels, differentiable
    conics: Tensor  # [N, 3] (a, b, c) of the inverse 2D covariance [[a, b], [b, c]], differentiable
    depths: Tensor  # [N] camera-space z
    radii: Tensor  # [N, 2] int32 half-extent of the box in pixels (x, y)
    visible: Tensor  # [N] bool


def quaternion_to_rotation(quats: Tensor) -> Tensor:
    """wxyz quaternions [N, 4] (normalised here, as gsplat does) -> rotation matrices [N, 3, 3]."""
    w, x, y, z = (quats / quats.norm(dim=-1, keepdim=True)).unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(-1, 3, 3)


def project_gaussians(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4] wxyz
    scales: Tensor,  # [N, 3] linear
    opacities: Tensor,  # [N]
    viewmat: Tensor,  # [4, 4] world-to-camera, OpenCV axes
    K: Tensor,  # [3, 3]
    width: int,
    height: int,
) -> Projection:
    """EWA projection with gsplat's frustum clamp, dilation, culling and opacity-aware boxes."""
    rotation, translation = viewmat[:3, :3], viewmat[:3, 3]
    means_cam = means @ rotation.T + translation  # [N, 3]
    m = quaternion_to_rotation(quats) * scales[:, None, :]  # [N, 3, 3] = R_q S
    m_cam = rotation @ m  # [N, 3, 3]; camera covariance = m_cam m_camᵀ
    x, y, z = means_cam.unbind(-1)
    in_range = (z >= NEAR_PLANE) & (z <= FAR_PLANE)
    z_safe = torch.where(in_range, z, torch.ones_like(z))  # keeps culled entries finite (and their grads)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    lim_x_pos = (width - cx) / fx + FOV_CLAMP_MARGIN * 0.5 * width / fx
    lim_x_neg = cx / fx + FOV_CLAMP_MARGIN * 0.5 * width / fx
    lim_y_pos = (height - cy) / fy + FOV_CLAMP_MARGIN * 0.5 * height / fy
    lim_y_neg = cy / fy + FOV_CLAMP_MARGIN * 0.5 * height / fy
    inv_z = 1.0 / z_safe
    tx = z_safe * torch.minimum(torch.maximum(x * inv_z, -lim_x_neg), lim_x_pos)
    ty = z_safe * torch.minimum(torch.maximum(y * inv_z, -lim_y_neg), lim_y_pos)
    # Rows of the Jacobian: J0 = (fx/z, 0, -fx tx/z²), J1 = (0, fy/z, -fy ty/z²); J Σ Jᵀ = (J m)(J m)ᵀ.
    j0 = torch.stack([fx * inv_z, torch.zeros_like(z), -fx * tx * inv_z * inv_z], -1)  # [N, 3]
    j1 = torch.stack([torch.zeros_like(z), fy * inv_z, -fy * ty * inv_z * inv_z], -1)  # [N, 3]
    u = (j0[:, :, None] * m_cam).sum(1)  # [N, 3] = J0 m
    v = (j1[:, :, None] * m_cam).sum(1)  # [N, 3] = J1 m
    cov_a = (u * u).sum(-1) + EPS2D
    cov_b = (u * v).sum(-1)
    cov_c = (v * v).sum(-1) + EPS2D
    det = cov_a * cov_c - cov_b * cov_b
    ok = in_range & (det > 0)
    det_safe = torch.where(ok, det, torch.ones_like(det))
    conics = torch.stack([cov_c / det_safe, -cov_b / det_safe, cov_a / det_safe], -1)  # [N, 3]
    means2d = torch.stack([fx * x * inv_z + cx, fy * y * inv_z + cy], -1)  # [N, 2]

    with torch.no_grad():  # the box is not differentiable (as in gsplat)
        ok = ok & (opacities >= ALPHA_MIN)
        opacity_safe = torch.where(ok, opacities, torch.ones_like(opacities))
        extent = torch.clamp(torch.sqrt(2.0 * torch.log(opacity_safe / ALPHA_MIN)), max=MAX_EXTENT_SIGMA)
        var = torch.stack([cov_a, cov_c], -1).clamp_min(0)  # [N, 2]
        radii_f = torch.ceil(extent[:, None] * torch.sqrt(var))  # [N, 2]
        ok = ok & ((radii_f[:, 0] > 0) | (radii_f[:, 1] > 0))
        mean_d = means2d.detach()
        ok = ok & (mean_d[:, 0] + radii_f[:, 0] > 0) & (mean_d[:, 0] - radii_f[:, 0] < width)
        ok = ok & (mean_d[:, 1] + radii_f[:, 1] > 0) & (mean_d[:, 1] - radii_f[:, 1] < height)
        radii = torch.where(ok[:, None], radii_f, torch.zeros_like(radii_f)).to(torch.int32)
    keep = ok[:, None]
    means2d = torch.where(keep, means2d, torch.zeros_like(means2d))
    conics = torch.where(keep, conics, torch.zeros_like(conics))
    return Projection(means2d, conics, z.detach(), radii, ok)


class RowPlan(NamedTuple):
    """(tile, Gaussian) rows sorted by tile then depth, and the chunk boundaries (non-differentiable)."""

    row_gaussian: Tensor  # [M] int64 index into the N Gaussians
    row_tile: Tensor  # [M] int64 tile index
    chunk_bounds: list  # [(row_start, row_end, tile_start, tile_end)], whole tiles per chunk
    tile_size: int
    tiles_x: int
    tiles_y: int
    keep_pairs: bool  # forward keeps per-pair alpha and T for backward (below the memory budget)


def plan_rows(
    means2d: Tensor,  # [N, 2]
    radii: Tensor,  # [N, 2] int32
    depths: Tensor,  # [N]
    visible: Tensor,  # [N] bool
    width: int,
    height: int,
    tile_size: int = DEFAULT_TILE_SIZE,
    chunk_pairs: int = DEFAULT_CHUNK_PAIRS,
    keep_pairs_limit: int = DEFAULT_KEEP_PAIRS,
) -> RowPlan:
    """List every (tile, Gaussian) overlap of the visible Gaussians' boxes, grouped by tile in depth order."""
    device = means2d.device
    tiles_x, tiles_y = math.ceil(width / tile_size), math.ceil(height / tile_size)
    ids = torch.nonzero(visible).squeeze(1)  # [G]
    ids = ids[torch.argsort(depths[ids], stable=True)]  # front to back; ties keep index order like gsplat
    centre = means2d.detach()[ids]  # [G, 2]
    radius = radii[ids].to(centre.dtype)  # [G, 2]
    lo = torch.floor((centre - radius) / tile_size).long()  # conservative: covers every pixel centre in the box
    hi = torch.floor((centre + radius) / tile_size).long()
    lo[:, 0].clamp_(0, tiles_x - 1), hi[:, 0].clamp_(0, tiles_x - 1)
    lo[:, 1].clamp_(0, tiles_y - 1), hi[:, 1].clamp_(0, tiles_y - 1)
    span = hi - lo + 1  # [G, 2]
    counts = span[:, 0] * span[:, 1]  # [G]
    total = int(counts.sum())
    owner = torch.repeat_interleave(torch.arange(ids.numel(), device=device), counts)  # [M]
    first = torch.cumsum(counts, 0) - counts
    local = torch.arange(total, device=device) - first[owner]
    tile_xy = lo[owner] + torch.stack([local % span[owner, 0], local // span[owner, 0]], -1)  # [M, 2]
    tile = tile_xy[:, 1] * tiles_x + tile_xy[:, 0]
    # stable: depth order survives inside each tile (int32 keys sort about twice as fast as int64)
    tile, order = torch.sort(tile.to(torch.int32), stable=True)
    tile = tile.long()
    row_gaussian = ids[owner[order]]

    # Chunks of whole tiles with about chunk_pairs (row, pixel) pairs each.
    tile_rows = torch.bincount(tile, minlength=tiles_x * tiles_y)  # [T]
    tile_end = torch.cumsum(tile_rows, 0).tolist()
    max_rows = max(1, chunk_pairs // (tile_size * tile_size))
    chunk_bounds, row_start, tile_start = [], 0, 0
    n_tiles = tiles_x * tiles_y
    while tile_start < n_tiles:
        # last tile whose end fits in the budget (at least one tile per chunk)
        lo_t, hi_t = tile_start, n_tiles - 1
        while lo_t < hi_t:
            mid = (lo_t + hi_t + 1) // 2
            if tile_end[mid] - row_start <= max_rows:
                lo_t = mid
            else:
                hi_t = mid - 1
        tile_stop = lo_t + 1
        row_stop = tile_end[tile_stop - 1]
        if row_stop > row_start:
            chunk_bounds.append((row_start, row_stop, tile_start, tile_stop))
        row_start, tile_start = row_stop, tile_stop
    keep = total * tile_size * tile_size <= keep_pairs_limit
    return RowPlan(row_gaussian, tile, chunk_bounds, tile_size, tiles_x, tiles_y, keep)


def _tile_basis(tile_size: int, dtype, device) -> Tensor:
    """[P, 6] monomials (1, u, v, u², v², uv) of the pixel-centre offsets (u, v) from the tile centre."""
    offs = torch.arange(tile_size * tile_size, device=device)
    u = (offs % tile_size).to(dtype) + 0.5 - tile_size / 2
    v = (offs // tile_size).to(dtype) + 0.5 - tile_size / 2
    return torch.stack([torch.ones_like(u), u, v, u * u, v * v, u * v], -1)


def _segment_exclusive_cumsum(values: Tensor, seg: Tensor, seg_first_row: Tensor) -> Tensor:
    """Column-wise sum over the earlier rows of the same tile ([m, P]; use float64 for precision)."""
    exclusive = torch.cumsum(values, 0) - values
    if values.shape[0] == 0:  # a chunk whose Gaussians all miss its pixel centres: no row to index
        return exclusive
    return exclusive - exclusive.index_select(0, seg_first_row).index_select(0, seg)


class _ChunkState(NamedTuple):
    gauss: Tensor  # [m] Gaussian of each row
    seg: Tensor  # [m] tile of each row, counted from the chunk's first tile
    offset: Tensor  # [m, 2] mean2d minus the centre of the row's tile
    alpha: Tensor  # [m, P] composited alpha (0 where skipped or after the transmittance stop)
    t_before: Tensor  # [m, P] transmittance in front of the row's Gaussian
    seg_first_row: Tensor  # [t] first row of each tile of the chunk (clamped for empty tiles)


def _evaluate_chunk(plan: RowPlan, chunk, basis, means2d, conics, opacities) -> _ChunkState:
    """alpha and transmittance of every (row, pixel) pair of one chunk of whole tiles.

    sigma is a quadratic in the pixel offset (u, v) from the tile centre, so log(o) - sigma for all
    pixels of all rows is one matrix product [m, 6] @ [6, P].
    """
    r0, r1, t0, t1 = chunk
    s = plan.tile_size
    gauss = plan.row_gaussian[r0:r1]
    tile = plan.row_tile[r0:r1]
    seg = tile - t0
    dtype = means2d.dtype
    centre = torch.stack([(tile % plan.tiles_x).to(dtype), (tile // plan.tiles_x).to(dtype)], -1) * s + s / 2
    offset = means2d.index_select(0, gauss) - centre  # [m, 2]
    a, b, c = conics.index_select(0, gauss).unbind(-1)
    ox, oy = offset.unbind(-1)
    # sigma(u, v) = ½a(ox-u)² + ½c(oy-v)² + b(ox-u)(oy-v), expanded in the monomials of _tile_basis
    coef = torch.stack(
        [
            torch.log(opacities.index_select(0, gauss)) - (0.5 * a * ox * ox + 0.5 * c * oy * oy + b * ox * oy),
            a * ox + b * oy,
            c * oy + b * ox,
            -0.5 * a,
            -0.5 * c,
            -b,
        ],
        -1,
    )  # [m, 6]
    alpha_raw = torch.exp(coef @ basis.T)  # [m, P] o·exp(-sigma)
    valid = alpha_raw >= ALPHA_MIN
    alpha = torch.where(valid, alpha_raw.clamp(max=ALPHA_MAX), 0.0)
    # rows whose Gaussian reaches no pixel of the tile (box corners) change nothing: drop them
    gauss, seg, offset, alpha = _compact_rows(valid.any(1), gauss, seg, offset, alpha)
    log_keep = torch.log1p(-alpha).double()  # float64: the scan runs over all rows of the chunk
    seg_first_row = _first_rows(seg, t1 - t0)
    log_t_before = _segment_exclusive_cumsum(log_keep, seg, seg_first_row)
    # a pixel stops before the pair that would take T to <= 1e-4; T only falls, so all later pairs stop too
    composited = log_t_before + log_keep > math.log(TRANSMITTANCE_MIN)
    alpha = torch.where(composited, alpha, 0.0)
    t_before = torch.exp(log_t_before).to(dtype)
    # rows hidden behind saturated pixels neither render nor receive gradient: drop them too
    gauss, seg, offset, alpha, t_before = _compact_rows((alpha > 0).any(1), gauss, seg, offset, alpha, t_before)
    return _ChunkState(gauss, seg, offset, alpha, t_before, _first_rows(seg, t1 - t0))


def _compact_rows(keep: Tensor, *row_tensors: Tensor) -> tuple[Tensor, ...]:
    """The rows where keep [m] is True of each [m, ...] tensor (no copy when all are kept)."""
    if bool(keep.all()):
        return row_tensors
    index = torch.nonzero(keep).squeeze(1)
    return tuple(t.index_select(0, index) for t in row_tensors)


def _first_rows(seg: Tensor, n_tiles: int) -> Tensor:
    """[n_tiles] index of the first row of each tile in tile-sorted rows (clamped for empty tiles)."""
    counts = torch.bincount(seg, minlength=n_tiles)
    return (torch.cumsum(counts, 0) - counts).clamp(max=max(seg.numel() - 1, 0))


def _tiles_to_image(tile_values: Tensor, plan: RowPlan, width: int, height: int) -> Tensor:
    """[T, P, D] values of every tile -> [H, W, D] image (tiles past the image edge are cropped)."""
    s, d = plan.tile_size, tile_values.shape[-1]
    grid = tile_values.reshape(plan.tiles_y, plan.tiles_x, s, s, d).permute(0, 2, 1, 3, 4)
    return grid.reshape(plan.tiles_y * s, plan.tiles_x * s, d)[:height, :width]


def _image_to_tiles(image: Tensor, plan: RowPlan) -> Tensor:
    """[H, W, D] image -> [T, P, D] (pixels outside the image, in the padding of edge tiles, are 0)."""
    s = plan.tile_size
    h, w, d = image.shape
    padded = image.new_zeros(plan.tiles_y * s, plan.tiles_x * s, d)
    padded[:h, :w] = image
    grid = padded.reshape(plan.tiles_y, s, plan.tiles_x, s, d).permute(0, 2, 1, 3, 4)
    return grid.reshape(plan.tiles_y * plan.tiles_x, s * s, d)


class _CompositeTiles(torch.autograd.Function):
    """Front-to-back compositing of the planned rows with a hand-written backward (per-pair alpha and T
    kept from forward within the budget, recomputed chunk by chunk beyond it)."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, background, plan, width, height):
        dtype, device = means2d.dtype, means2d.device
        pix = plan.tile_size * plan.tile_size
        basis = _tile_basis(plan.tile_size, dtype, device)
        colors_and_one = torch.cat([colors, torch.ones_like(colors[:, :1])], -1)  # [N, 4]: rgb and coverage
        tiles = torch.zeros(plan.tiles_x * plan.tiles_y, pix, 4, dtype=dtype, device=device)
        ctx.kept = []
        for chunk in plan.chunk_bounds:
            st = _evaluate_chunk(plan, chunk, basis, means2d, conics, opacities)
            weight = st.alpha * st.t_before
            rows = weight[:, :, None] * colors_and_one.index_select(0, st.gauss)[:, None, :]  # [m, P, 4]
            tiles[chunk[2]:chunk[3]].index_add_(0, st.seg, rows)
            if plan.keep_pairs:
                ctx.kept.append(st)
        image = _tiles_to_image(tiles, plan, width, height)  # [H, W, 4]
        rgb = image[..., :3]  # without background
        alpha = image[..., 3:].clamp(0.0, 1.0)  # Σ α T telescopes to 1 - T_final
        t_final = 1.0 - alpha
        ctx.save_for_backward(means2d, conics, opacities, colors, background, rgb, t_final)
        ctx.plan = plan
        return rgb + t_final * background, alpha

    @staticmethod
    def backward(ctx, grad_rgb, grad_alpha):
        means2d, conics, opacities, colors, background, rgb, t_final = ctx.saved_tensors
        plan = ctx.plan
        n = means2d.shape[0]
        dtype, device = means2d.dtype, means2d.device
        grad_rgb = grad_rgb.to(dtype)  # [H, W, 3]
        grad_alpha = grad_alpha.to(dtype)  # [H, W, 1]
        # d loss / d T_final, times T_final; and the total Σ_k (c_k · g) α_k T_k of each pixel
        tail = t_final * ((grad_rgb * background).sum(-1, keepdim=True) - grad_alpha)  # [H, W, 1]
        color_total = (rgb * grad_rgb).sum(-1, keepdim=True)  # [H, W, 1]
        per_pixel = _image_to_tiles(torch.cat([grad_rgb, tail + color_total], -1), plan)  # [T, P, 4]
        basis = _tile_basis(plan.tile_size, dtype, device)
        g_means2d = torch.zeros(n, 2, dtype=dtype, device=device)
        g_conics = torch.zeros(n, 3, dtype=dtype, device=device)
        g_opac = torch.zeros(n, dtype=dtype, device=device)
        g_colors = torch.zeros(n, 3, dtype=dtype, device=device)
        for index, chunk in enumerate(plan.chunk_bounds):
            if plan.keep_pairs:
                st = ctx.kept[index]
            else:
                st = _evaluate_chunk(plan, chunk, basis, means2d, conics, opacities)
            pix = per_pixel[chunk[2]:chunk[3]].index_select(0, st.seg)  # [m, P, 4]
            g_pix = pix[..., :3]
            col = colors.index_select(0, st.gauss)  # [m, 3]
            color_dot = torch.bmm(g_pix, col[:, :, None]).squeeze(-1)  # [m, P] c_k · dL/drgb
            weight = st.alpha * st.t_before
            contrib = (weight * color_dot).double()
            # Σ over the later pairs of the pixel of (c·g) α T, plus T_final · dL/dT_final
            behind = pix[..., 3].double() - _segment_exclusive_cumsum(contrib, st.seg, st.seg_first_row) - contrib
            # composited and below the 0.999 cap (a capped alpha is exactly ALPHA_MAX and has no gradient)
            live = (st.alpha > 0) & (st.alpha < ALPHA_MAX)
            grad_alpha_pair = st.t_before * color_dot - (behind / (1.0 - st.alpha.double())).to(dtype)
            grad_alpha_pair = torch.where(live, grad_alpha_pair, 0.0)
            grad_sigma = -st.alpha * grad_alpha_pair  # d alpha / d sigma = -alpha below the cap
            m0, m_u, m_v, m_uu, m_vv, m_uv = (grad_sigma @ basis).unbind(-1)  # moments over the tile's pixels
            ox, oy = st.offset.unbind(-1)
            s_dx = ox * m0 - m_u  # Σ gσ·dx with dx = ox - u
            s_dy = oy * m0 - m_v
            s_dxdx = ox * ox * m0 - 2 * ox * m_u + m_uu
            s_dydy = oy * oy * m0 - 2 * oy * m_v + m_vv
            s_dxdy = ox * oy * m0 - ox * m_v - oy * m_u + m_uv
            a, b, c = conics.index_select(0, st.gauss).unbind(-1)
            g_means2d.index_add_(0, st.gauss, torch.stack([a * s_dx + b * s_dy, b * s_dx + c * s_dy], -1))
            g_conics.index_add_(0, st.gauss, torch.stack([0.5 * s_dxdx, s_dxdy, 0.5 * s_dydy], -1))
            # d alpha / d o = exp(-sigma) = alpha / o below the cap
            g_opac.index_add_(0, st.gauss, (st.alpha * grad_alpha_pair).sum(1) / opacities.index_select(0, st.gauss))
            g_colors.index_add_(0, st.gauss, torch.bmm(weight[:, None, :], g_pix).squeeze(1))
        g_background = (t_final * grad_rgb).sum((0, 1))
        return g_means2d, g_conics, g_opac, g_colors, g_background, None, None, None


def composite(
    means2d: Tensor,  # [N, 2]
    conics: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    colors: Tensor,  # [N, 3]
    background: Tensor,  # [3]
    plan: RowPlan,
    width: int,
    height: int,
) -> tuple[Tensor, Tensor]:
    """rgb [H, W, 3] (background composited) and alpha [H, W, 1] of the planned rows."""
    return _CompositeTiles.apply(means2d, conics, opacities, colors, background, plan, width, height)


def composite_naive(
    means2d: Tensor,  # [N, 2]
    conics: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    colors: Tensor,  # [N, 3]
    background: Tensor,  # [3]
    radii: Tensor,  # [N, 2] int32
    depths: Tensor,  # [N]
    visible: Tensor,  # [N] bool
    width: int,
    height: int,
) -> tuple[Tensor, Tensor]:
    """The simple variant (benchmark baseline and cross-check): one (Gaussian, pixel) pair per pixel of
    each box, a stable sort by pixel, and plain autograd through every pair tensor (no chunking)."""
    device, dtype = means2d.device, means2d.dtype
    ids = torch.nonzero(visible).squeeze(1)
    ids = ids[torch.argsort(depths[ids], stable=True)]
    with torch.no_grad():
        centre, radius = means2d[ids], radii[ids].to(dtype)
        lo_x = torch.ceil(centre[:, 0] - radius[:, 0] - 0.5).long().clamp(0, width - 1)
        hi_x = torch.floor(centre[:, 0] + radius[:, 0] - 0.5).long().clamp(0, width - 1)
        lo_y = torch.ceil(centre[:, 1] - radius[:, 1] - 0.5).long().clamp(0, height - 1)
        hi_y = torch.floor(centre[:, 1] + radius[:, 1] - 0.5).long().clamp(0, height - 1)
        span_x, span_y = (hi_x - lo_x + 1).clamp_min(0), (hi_y - lo_y + 1).clamp_min(0)
        counts = span_x * span_y
        owner = torch.repeat_interleave(torch.arange(ids.numel(), device=device), counts)
        local = torch.arange(int(counts.sum()), device=device) - (torch.cumsum(counts, 0) - counts)[owner]
        pix_x = lo_x[owner] + local % span_x[owner]
        pix_y = lo_y[owner] + local // span_x[owner]
        pixel, order = torch.sort(pix_y * width + pix_x, stable=True)
        gauss = ids[owner[order]]
        pix_x, pix_y = pix_x[order], pix_y[order]
    dx = means2d[gauss, 0] - (pix_x.to(dtype) + 0.5)
    dy = means2d[gauss, 1] - (pix_y.to(dtype) + 0.5)
    conic = conics[gauss]
    sigma = 0.5 * (conic[:, 0] * dx * dx + conic[:, 2] * dy * dy) + conic[:, 1] * dx * dy
    alpha = (opacities[gauss] * torch.exp(-sigma)).clamp(max=ALPHA_MAX)
    valid = (sigma >= 0) & (alpha >= ALPHA_MIN)
    alpha = torch.where(valid, alpha, torch.zeros_like(alpha))
    log_keep = torch.log1p(-alpha.double())
    inclusive = torch.cumsum(log_keep, 0)
    exclusive = inclusive - log_keep
    counts_pix = torch.bincount(pixel, minlength=width * height)
    first = (torch.cumsum(counts_pix, 0) - counts_pix).clamp(max=max(pixel.numel() - 1, 0))
    log_t_before = exclusive - exclusive[first[pixel]] if pixel.numel() else exclusive
    composited = valid & (log_t_before + log_keep > math.log(TRANSMITTANCE_MIN)).detach()
    weight = torch.where(composited, alpha * torch.exp(log_t_before).to(dtype), torch.zeros_like(alpha))
    rgb = torch.zeros(width * height, 3, dtype=dtype, device=device).index_add(
        0, pixel, weight[:, None] * colors[gauss]
    )
    log_t = torch.zeros(width * height, dtype=torch.float64, device=device).index_add(
        0, pixel, torch.where(composited, log_keep, torch.zeros_like(log_keep))
    )
    t_final = torch.exp(log_t).to(dtype)
    out = rgb + t_final[:, None] * background
    return out.reshape(height, width, 3), (1.0 - t_final).reshape(height, width, 1)


def rasterize_torch(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4] wxyz
    scales: Tensor,  # [N, 3] linear
    opacities: Tensor,  # [N] in [0, 1]
    colors: Tensor,  # [N, 3]
    viewmats: Tensor,  # [C, 4, 4] world-to-camera, OpenCV axes
    Ks: Tensor,  # [C, 3, 3]
    width: int,
    height: int,
    backgrounds: Tensor,  # [C, 3]
    batched: bool = True,
    method: str = "tiles",
    tile_size: int = DEFAULT_TILE_SIZE,
    chunk_pairs: int = DEFAULT_CHUNK_PAIRS,
    keep_pairs_limit: int = DEFAULT_KEEP_PAIRS,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Render C cameras; returns rgb [C,H,W,3], alpha [C,H,W,1], means2d [C,N,2] (a graph node whose
    .grad is d loss / d means2d), radii [C,N,2] int32, visible [C,N] bool, depths [C,N].
    batched=False (C == 1): means2d is returned as the [N, 2] node the renderer consumed.

    method "tiles" is the fast renderer; "naive" the simple pair-expansion with plain autograd.
    tile_size, chunk_pairs and keep_pairs_limit tune "tiles" (speed and memory only, never results)."""
    if method not in ("tiles", "naive"):
        raise ValueError(f"rasterize_torch: method must be 'tiles' or 'naive', got {method!r}")
    projections = [
        project_gaussians(means, quats, scales, opacities, viewmats[c], Ks[c], width, height)
        for c in range(viewmats.shape[0])
    ]

    def composite_camera(c: int, means2d: Tensor, proj: Projection) -> tuple[Tensor, Tensor]:
        if method == "naive":
            return composite_naive(means2d, proj.conics, opacities, colors, backgrounds[c], proj.radii, proj.depths,
                                   proj.visible, width, height)
        plan = plan_rows(means2d, proj.radii, proj.depths, proj.visible, width, height, tile_size,
                         chunk_pairs, keep_pairs_limit)
        return composite(means2d, proj.conics, opacities, colors, backgrounds[c], plan, width, height)

    return render_cameras(projections, composite_camera, batched)


def render_cameras(
    projections: list[Projection],  # one per camera
    composite_camera,  # (camera index, means2d [N,2], Projection) -> (rgb [H,W,3], alpha [H,W,1])
    batched: bool,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Composite every camera and stack the outputs; shared by the torch and native cpu backends.

    means2d is one graph node per camera ([C,N,2], or the [N,2] node itself when batched=False) with
    retain_grad, so its .grad holds d loss / d means2d for densification."""
    means2d = torch.stack([p.means2d for p in projections])  # [C, N, 2]
    per_camera = means2d.unbind(0)  # the [N, 2] nodes the compositing consumes
    if not batched:
        means2d = per_camera[0]
    if means2d.requires_grad:
        means2d.retain_grad()
    images = [composite_camera(c, per_camera[c], proj) for c, proj in enumerate(projections)]
    return (
        torch.stack([rgb for rgb, _ in images]),
        torch.stack([alpha for _, alpha in images]),
        means2d,
        torch.stack([p.radii for p in projections]),
        torch.stack([p.visible for p in projections]),
        torch.stack([p.depths for p in projections]),
    )
