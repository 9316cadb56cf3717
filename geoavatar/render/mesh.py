"""A small z-buffer triangle rasterizer in PyTorch (CPU or GPU; its scan native on the CPU), for pictures of head
models and for rendering synthetic subjects.

    frags = rasterize_mesh(world_to_camera(vertices, viewmat), faces, K, width, height)
    colour = interpolate(frags, vertex_colors, faces)          # [H, W, 3]
    image, mask = render_mesh(vertices, faces, viewmat, K, width, height, vertex_colors=c, ssaa=2)

How it works (all vectorised, memory bounded):
1. Project the vertices with K; drop triangles with a vertex closer than `near` (no clipping: a head
   model never straddles the camera plane, and clipping would add triangles), degenerate ones, ones
   outside the image and, optionally, back faces.
2. On the CPU, a native loop scans each triangle's pixel bounding box (render/csrc/rasterize_cpu.cpp,
   mesh_zbuffer: steps 3-4 in the same float32 arithmetic). Otherwise (CUDA, or no compiler):
   each triangle's pixel bounding box is split into pieces of at most `piece_pixels` pixels (big
   triangles become row bands) and the pieces are gathered into chunks of about `chunk_candidates`
   (triangle, pixel) candidates, so memory stays bounded whatever the triangle sizes.
3. For every candidate, the screen-space barycentrics are affine functions of the pixel centre
   (evaluated relative to the triangle's first vertex for float32 accuracy); the inside test is
   b >= -1e-5 (a hair of overlap instead of gaps where edges pass exactly through pixel centres).
4. Depth z (1/z is affine in screen space) and face id are packed into one int64 key
   (float32 bits of z << 32 | face id: positive floats order like their bits) and a scatter-min builds
   the z-buffer. Equal depths resolve to the smaller face id: the result is deterministic.
5. For the winning face of each covered pixel the perspective-correct barycentrics are recomputed.

Conventions: OpenCV camera coordinates (+x right, +y down, +z forward), pixel (i, j) has its centre
at (i + 0.5, j + 0.5). Rasterization is not differentiable with respect to vertex positions;
`interpolate` is differentiable with respect to the attributes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from geoavatar.render.camera import scale_intrinsics, world_to_camera

_EMPTY_KEY = torch.iinfo(torch.int64).max
_INSIDE_EPS = 1e-5  # barycentric tolerance of the inside test


class Fragments(NamedTuple):
    """Per-pixel result of rasterize_mesh."""

    face_id: Tensor  # [H, W] int64, -1 where no triangle covers the pixel centre
    bary: Tensor  # [H, W, 3] perspective-correct barycentrics of the visible face (0 where empty)
    depth: Tensor  # [H, W] camera-space z of the visible surface, +inf where empty

    @property
    def mask(self) -> Tensor:
        """[H, W] bool coverage."""
        return self.face_id >= 0


@torch.no_grad()
def rasterize_mesh(
    vertices_cam: Tensor,  # [V, 3] camera coordinates (OpenCV axes)
    faces: Tensor,  # [F, 3] int vertex ids
    K: Tensor,  # [3, 3] intrinsics in pixels
    width: int,
    height: int,
    cull_backfaces: bool = False,
    near: float = 1e-3,
    chunk_candidates: int = 1 << 21,
    piece_pixels: int = 1 << 16,
) -> Fragments:
    """Z-buffer rasterization of a triangle mesh: the nearest face at each pixel centre.

    A face is front-facing when its vertices v0 -> v1 -> v2 turn counter-clockwise seen from the
    camera (its right-hand normal points towards the camera); `cull_backfaces` drops the others.
    Triangles with any vertex at z < near are dropped (not clipped).
    """
    _check_inputs(vertices_cam, faces, K, width, height)
    device = vertices_cam.device
    verts = vertices_cam.detach().to(torch.float64)  # float64 for the per-triangle set-up only
    faces = faces.to(device=device, dtype=torch.int64)
    Kd = K.detach().to(device=device, dtype=torch.float64)
    num_pixels = width * height

    tri = verts[faces]  # [F, 3, 3]
    z = tri[..., 2]  # [F, 3]
    keep = (z >= near).all(dim=1)
    uvw = tri @ Kd.T  # [F, 3, 3]
    xy = uvw[..., :2] / uvw[..., 2:3].clamp_min(near)  # [F, 3, 2] pixel coordinates
    x0, y0 = xy[:, 0, 0], xy[:, 0, 1]
    e1 = xy[:, 1] - xy[:, 0]  # [F, 2]
    e2 = xy[:, 2] - xy[:, 0]  # [F, 2]
    area2 = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]  # [F] twice the signed screen area
    # Degenerate in screen space (height below ~1e-6 of the longest edge, e.g. collinear up to float
    # noise): such slivers would otherwise claim pixel centres that lie exactly on their line.
    longest2 = torch.stack([e1.square().sum(-1), e2.square().sum(-1), (e2 - e1).square().sum(-1)], -1).amax(-1)
    keep &= area2.abs() > 1e-6 * longest2 + 1e-12
    if cull_backfaces:
        normal = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # [F, 3]
        keep &= (normal * tri[:, 0]).sum(-1) < 0  # normal points back at the camera centre

    # Pixel-centre bounding boxes: pixel i is inside when lo <= i + 0.5 <= hi.
    lo = torch.ceil(xy.amin(dim=1) - 0.5)  # [F, 2]
    hi = torch.floor(xy.amax(dim=1) - 0.5)  # [F, 2]
    ix0 = lo[:, 0].clamp_min(0)
    iy0 = lo[:, 1].clamp_min(0)
    ix1 = hi[:, 0].clamp_max(width - 1)
    iy1 = hi[:, 1].clamp_max(height - 1)
    keep &= (ix0 <= ix1) & (iy0 <= iy1)

    face_ids = torch.nonzero(keep).squeeze(1)  # [Fk]
    zbuf = torch.full((num_pixels,), _EMPTY_KEY, dtype=torch.int64, device=device)
    if face_ids.numel() > 0:
        # Screen-space barycentrics b1, b2 = (dx, dy) @ coeff, with (dx, dy) = pixel - v0.
        a = area2[face_ids]
        coeff = torch.stack(
            [torch.stack([e2[face_ids, 1], -e2[face_ids, 0]], -1), torch.stack([-e1[face_ids, 1], e1[face_ids, 0]], -1)],
            dim=-1,
        ) / a[:, None, None]  # [Fk, 2 (dx,dy), 2 (b1,b2)]
        inv_z = 1.0 / z[face_ids]  # [Fk, 3]
        setup = _TriangleSetup(
            face_ids=face_ids,
            table=torch.cat([torch.stack([x0[face_ids], y0[face_ids]], -1), coeff.reshape(-1, 4)], -1).float(),
            inv_z=inv_z.float(),
        )
        box = torch.stack([ix0, iy0, ix1, iy1], -1)[face_ids].long()  # [Fk, 4]
        kernels = _native_kernels() if device.type == "cpu" else None
        if kernels is not None:  # the same keys bit for bit (tests/test_mesh_render.py), the scan ~10x faster
            kernels.mesh_zbuffer(setup.table.contiguous(), setup.inv_z.contiguous(), setup.face_ids.contiguous(),
                                 box.contiguous(), width, zbuf)
        else:
            _rasterize_boxes(setup, box, width, zbuf, chunk_candidates, piece_pixels)

    covered = zbuf != _EMPTY_KEY  # [H*W]
    face_id = torch.full((num_pixels,), -1, dtype=torch.int64, device=device)
    depth = torch.full((num_pixels,), float("inf"), dtype=torch.float32, device=device)
    bary = torch.zeros(num_pixels, 3, dtype=torch.float32, device=device)
    pix = torch.nonzero(covered).squeeze(1)  # [P]
    if pix.numel() > 0:
        keys = zbuf[pix]
        fid = keys & 0xFFFFFFFF  # [P]
        depth[pix] = (keys >> 32).to(torch.int32).view(torch.float32)
        face_id[pix] = fid
        # Perspective-correct barycentrics at the pixel centres, from the screen-space ones.
        tri_px = xy[fid].float()  # [P, 3, 2]
        px = torch.stack([(pix % width).float() + 0.5, (pix // width).float() + 0.5], -1)  # [P, 2]
        screen = _screen_bary(tri_px, px).clamp_min(0.0)  # [P, 3]
        persp = screen / z[fid].float()
        bary[pix] = persp / persp.sum(-1, keepdim=True).clamp_min(1e-20)
    return Fragments(face_id.view(height, width), bary.view(height, width, 3), depth.view(height, width))


def _native_kernels():
    """The render layer's native CPU kernels (render/csrc/rasterize_cpu.cpp), or None where they cannot be built:
    the PyTorch scan below is then the z-buffer."""
    from geoavatar.render import cpu_backend

    return cpu_backend.load_extension()


@dataclass
class _TriangleSetup:
    face_ids: Tensor  # [Fk] ids into the caller's face array
    table: Tensor  # [Fk, 6] float32: vertex-0 pixel x, y; d(b1, b2)/dx; d(b1, b2)/dy
    inv_z: Tensor  # [Fk, 3] 1 / z per vertex


def _rasterize_boxes(
    setup: _TriangleSetup, box: Tensor, width: int, zbuf: Tensor, chunk_candidates: int, piece_pixels: int
) -> None:
    """Enumerate (triangle, pixel) candidates inside the boxes [Fk, 4] and scatter-min into zbuf."""
    device = box.device
    box_w = box[:, 2] - box[:, 0] + 1  # [Fk]
    box_h = box[:, 3] - box[:, 1] + 1
    # Split tall-and-wide boxes into row bands of at most piece_pixels pixels (bounded memory).
    rows_per_piece = (piece_pixels // box_w).clamp_min(1)  # [Fk]
    pieces_per_tri = (box_h + rows_per_piece - 1) // rows_per_piece  # [Fk]
    piece_tri = torch.repeat_interleave(torch.arange(box.shape[0], device=device), pieces_per_tri)  # [Pc]
    first_piece = torch.cumsum(pieces_per_tri, 0) - pieces_per_tri
    piece_rank = torch.arange(piece_tri.shape[0], device=device) - first_piece[piece_tri]
    piece_y0 = box[piece_tri, 1] + piece_rank * rows_per_piece[piece_tri]  # [Pc]
    piece_y1 = torch.minimum(piece_y0 + rows_per_piece[piece_tri] - 1, box[piece_tri, 3])
    piece_w = box_w[piece_tri]
    piece_count = piece_w * (piece_y1 - piece_y0 + 1)  # [Pc] candidates per piece

    # Chunks of consecutive pieces holding about chunk_candidates candidates each.
    ends = torch.cumsum(piece_count, 0)  # [Pc]
    total = int(ends[-1])
    cuts = [0, piece_tri.shape[0]]
    if total > chunk_candidates:
        bounds = torch.arange(chunk_candidates, total, chunk_candidates, device=device, dtype=ends.dtype)
        cuts[1:1] = torch.searchsorted(ends, bounds, right=True).tolist()
    for start, stop in zip(cuts[:-1], cuts[1:]):
        if stop <= start:
            continue
        sl = slice(start, stop)
        _rasterize_pieces(setup, piece_tri[sl], box[piece_tri[sl], 0], piece_y0[sl], piece_w[sl], piece_count[sl],
                          width, zbuf)


def _rasterize_pieces(
    setup: _TriangleSetup,
    tri: Tensor,  # [Pc] triangle index (into setup) per piece
    x0: Tensor,  # [Pc] first column
    y0: Tensor,  # [Pc] first row
    piece_w: Tensor,  # [Pc] columns
    count: Tensor,  # [Pc] candidates
    width: int,
    zbuf: Tensor,  # [H*W] int64 keys, updated in place
) -> None:
    device = tri.device
    total = int(count.sum())
    cand_piece = torch.repeat_interleave(torch.arange(tri.shape[0], device=device), count, output_size=total)  # [N]
    # One row gather of a packed per-piece table is much cheaper than several scattered gathers.
    first = torch.cumsum(count, 0) - count
    piece_table = torch.stack([first, piece_w, x0, y0, tri], -1)  # [Pc, 5]
    per_cand = piece_table.index_select(0, cand_piece)  # [N, 5]
    local = torch.arange(total, device=device) - per_cand[:, 0]  # [N] rank inside the piece
    row = torch.div(local, per_cand[:, 1], rounding_mode="floor")
    px = per_cand[:, 2] + (local - row * per_cand[:, 1])  # [N]
    py = per_cand[:, 3] + row  # [N]
    cand_tri = per_cand[:, 4]  # [N]
    del local, row, per_cand

    tri_table = setup.table.index_select(0, cand_tri)  # [N, 6]: origin x, y, d(b1,b2)/dx, d(b1,b2)/dy
    dx = px.float() + 0.5 - tri_table[:, 0]
    dy = py.float() + 0.5 - tri_table[:, 1]
    b1 = dx * tri_table[:, 2] + dy * tri_table[:, 4]
    b2 = dx * tri_table[:, 3] + dy * tri_table[:, 5]
    del tri_table, dx, dy
    b0 = 1.0 - b1 - b2
    inside = (b0 >= -_INSIDE_EPS) & (b1 >= -_INSIDE_EPS) & (b2 >= -_INSIDE_EPS)
    sel = torch.nonzero(inside).squeeze(1)  # [M]
    if sel.numel() == 0:
        return
    t = cand_tri.index_select(0, sel)
    inv_z = setup.inv_z.index_select(0, t)  # [M, 3]
    bb0 = b0.index_select(0, sel).clamp_min(0)
    bb1 = b1.index_select(0, sel).clamp_min(0)
    bb2 = b2.index_select(0, sel).clamp_min(0)
    # 1/z is affine in screen space; the clamped, renormalised weights keep z inside the triangle.
    depth = (bb0 + bb1 + bb2) / (bb0 * inv_z[:, 0] + bb1 * inv_z[:, 1] + bb2 * inv_z[:, 2])  # [M]
    key = (depth.view(torch.int32).to(torch.int64) << 32) | setup.face_ids.index_select(0, t)
    pixel = py.index_select(0, sel) * width + px.index_select(0, sel)
    zbuf.scatter_reduce_(0, pixel, key, reduce="amin")


def _screen_bary(tri_xy: Tensor, points: Tensor) -> Tensor:
    """Screen-space barycentrics of points [P, 2] in triangles [P, 3, 2] -> [P, 3]."""
    e1 = tri_xy[:, 1] - tri_xy[:, 0]
    e2 = tri_xy[:, 2] - tri_xy[:, 0]
    d = points - tri_xy[:, 0]
    area2 = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    b1 = (d[:, 0] * e2[:, 1] - d[:, 1] * e2[:, 0]) / area2
    b2 = (e1[:, 0] * d[:, 1] - e1[:, 1] * d[:, 0]) / area2
    return torch.stack([1.0 - b1 - b2, b1, b2], -1)


def _check_inputs(vertices_cam: Tensor, faces: Tensor, K: Tensor, width: int, height: int) -> None:
    if vertices_cam.dim() != 2 or vertices_cam.shape[-1] != 3:
        raise ValueError(f"rasterize_mesh: vertices_cam must be [V, 3], got {tuple(vertices_cam.shape)}")
    if faces.dim() != 2 or faces.shape[-1] != 3:
        raise ValueError(f"rasterize_mesh: faces must be [F, 3], got {tuple(faces.shape)}")
    if faces.numel() and (int(faces.min()) < 0 or int(faces.max()) >= vertices_cam.shape[0]):
        raise ValueError(f"rasterize_mesh: faces index outside [0, {vertices_cam.shape[0]})")
    if K.shape != (3, 3):
        raise ValueError(f"rasterize_mesh: K must be [3, 3], got {tuple(K.shape)}")
    if width <= 0 or height <= 0:
        raise ValueError(f"rasterize_mesh: width and height must be positive, got {width}x{height}")
    if faces.shape[0] >= 2**31:
        raise ValueError("rasterize_mesh: more than 2^31 faces")


# --- attributes --------------------------------------------------------------------------------


def interpolate(
    fragments: Fragments,
    vertex_attrs: Tensor,  # [V, C] per-vertex attributes (colours, normals, UVs, positions, ...)
    faces: Tensor,  # [F, 3] the faces given to rasterize_mesh
    background: float | Sequence[float] | Tensor = 0.0,
) -> Tensor:
    """Perspective-correct per-pixel attributes [H, W, C]; `background` where no face is visible.

    Differentiable with respect to vertex_attrs.
    """
    height, width = fragments.face_id.shape
    mask = fragments.mask
    faces = faces.to(device=vertex_attrs.device, dtype=torch.int64)
    fid = fragments.face_id[mask]  # [P]
    corner_attrs = vertex_attrs[faces[fid]]  # [P, 3, C]
    weights = fragments.bary[mask].to(vertex_attrs.dtype)  # [P, 3]
    values = (weights[:, :, None] * corner_attrs).sum(1)  # [P, C]
    return _scatter_to_image(values, mask, background, vertex_attrs.shape[-1])


def behind_surface(
    points_cam: Tensor,  # [N, 3] camera coordinates (OpenCV axes)
    surface_depth: Tensor,  # [H, W] camera z of the visible surface, +inf where none (Fragments.depth)
    K: Tensor,  # [3, 3]
    margin: float,  # same unit as the depths
) -> Tensor:
    """[N] bool: the point lies more than `margin` behind the surface at the pixel it projects to. Points off the
    image, behind the camera or over pixels the surface does not cover are never behind."""
    height, width = surface_depth.shape
    z = points_cam[:, 2]  # [N]
    uv = (points_cam @ K.to(points_cam).T)[:, :2] / z.clamp_min(1e-6)[:, None]  # [N, 2] pixels
    px, py = uv[:, 0].floor().long(), uv[:, 1].floor().long()  # [N]
    inside = (z > 0) & (px >= 0) & (px < width) & (py >= 0) & (py < height)
    surface = surface_depth[py.clamp(0, height - 1), px.clamp(0, width - 1)]  # [N]
    return inside & (z > surface + margin)


def face_attribute(
    fragments: Fragments,
    face_attrs: Tensor,  # [F, C] per-face attributes (flat colours, part labels, ...)
    background: float | Sequence[float] | Tensor = 0.0,
) -> Tensor:
    """The visible face's attribute at every pixel [H, W, C]; `background` where empty."""
    mask = fragments.mask
    values = face_attrs[fragments.face_id[mask]]  # [P, C]
    return _scatter_to_image(values, mask, background, face_attrs.shape[-1])


def _scatter_to_image(values: Tensor, mask: Tensor, background, channels: int) -> Tensor:
    height, width = mask.shape
    bg = torch.as_tensor(background, dtype=values.dtype, device=values.device).expand(channels)
    out = bg.expand(height, width, channels)
    return out.masked_scatter(mask[..., None], values) if values.numel() else out.clone()


def vertex_normals(
    vertices: Tensor,  # [V, 3]
    faces: Tensor,  # [F, 3]
) -> Tensor:
    """Area-weighted unit vertex normals [V, 3] (right-hand rule v0 -> v1 -> v2)."""
    faces = faces.to(device=vertices.device, dtype=torch.int64)
    tri = vertices[faces]  # [F, 3, 3]
    face_normal = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # [F, 3], |n| = 2 area
    normals = torch.zeros_like(vertices)
    for corner in range(3):
        normals = normals.index_add(0, faces[:, corner], face_normal)
    return F.normalize(normals, dim=-1, eps=1e-20)


def face_normals(vertices: Tensor, faces: Tensor) -> Tensor:
    """Unit face normals [F, 3]."""
    faces = faces.to(device=vertices.device, dtype=torch.int64)
    tri = vertices[faces]
    return F.normalize(torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), dim=-1, eps=1e-20)


def dilation_pixels(fraction: float, width: int, height: int) -> int:
    """A dilation given as a fraction of the longer image side, in whole pixels (at least 1 when > 0; 0 for 0)."""
    return max(1, int(round(fraction * max(width, height)))) if fraction > 0 else 0


def dilate_mask(mask: Tensor, pixels: int) -> Tensor:
    """[H, W] bool grown by `pixels` in every direction (a square structuring element)."""
    if pixels <= 0 or not bool(mask.any()):
        return mask
    size = 2 * pixels + 1
    return F.max_pool2d(mask[None, None].float(), size, stride=1, padding=pixels)[0, 0] > 0


# --- shading -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Lighting:
    """Directional lights fixed to the camera (studio lighting that follows the view).

    Directions point from the surface towards the light, in camera axes (+x right, +y down, +z forward):
    the default key light comes from the upper left of the viewer, the fill from the right.
    """

    directions: tuple[tuple[float, float, float], ...] = ((-0.45, -0.55, -1.0), (0.7, -0.1, -0.7))
    intensities: tuple[float, ...] = (0.75, 0.3)
    ambient: float = 0.25
    specular: float = 0.0  # Blinn-Phong strength of a soft white highlight from the key light
    shininess: float = 24.0
    two_sided: bool = True  # light back faces as if their normal were flipped (open surfaces, mouth interior)


def shade(
    albedo: Tensor,  # [..., 3] surface colour in [0, 1]
    normals: Tensor,  # [..., 3] camera-space normals (need not be unit)
    view_dirs: Tensor | None = None,  # [..., 3] surface -> camera unit vectors; None: (0, 0, -1)
    lighting: Lighting = Lighting(),
) -> Tensor:
    """Lambertian + ambient (+ optional Blinn-Phong specular) shading, [..., 3] in [0, 1]."""
    n = F.normalize(normals, dim=-1, eps=1e-20)
    if view_dirs is None:
        view_dirs = torch.tensor([0.0, 0.0, -1.0], dtype=n.dtype, device=n.device).expand_as(n)
    if lighting.two_sided:
        facing = (n * view_dirs).sum(-1, keepdim=True)
        n = torch.where(facing < 0, -n, n)
    light = torch.full_like(n[..., :1], lighting.ambient)
    highlight = torch.zeros_like(light)
    for i, (direction, intensity) in enumerate(zip(lighting.directions, lighting.intensities)):
        d = F.normalize(torch.tensor(direction, dtype=n.dtype, device=n.device), dim=0)
        light = light + intensity * (n @ d).clamp_min(0.0)[..., None]
        if i == 0 and lighting.specular > 0:
            half = F.normalize(d + view_dirs, dim=-1)
            highlight = lighting.specular * (n * half).sum(-1, keepdim=True).clamp_min(0.0) ** lighting.shininess
    return (albedo * light + highlight).clamp(0.0, 1.0)


# --- convenience -------------------------------------------------------------------------------


class MeshImage(NamedTuple):
    image: Tensor  # [H, W, 3] RGB in [0, 1], composited over the background
    mask: Tensor  # [H, W] coverage in [0, 1] (fractional on anti-aliased edges)


def box_downsample(image: Tensor, factor: int) -> Tensor:
    """Average factor x factor blocks: [H*f, W*f, C] -> [H, W, C] (or [H*f, W*f] -> [H, W])."""
    if factor == 1:
        return image
    squeeze = image.dim() == 2
    x = image[..., None] if squeeze else image
    hf, wf, c = x.shape
    if hf % factor or wf % factor:
        raise ValueError(f"box_downsample: size {hf}x{wf} is not a multiple of {factor}")
    x = x.reshape(hf // factor, factor, wf // factor, factor, c).mean(dim=(1, 3))
    return x[..., 0] if squeeze else x


def render_mesh(
    vertices: Tensor,  # [V, 3] world coordinates
    faces: Tensor,  # [F, 3]
    viewmat: Tensor,  # [4, 4] world-to-camera, OpenCV axes
    K: Tensor,  # [3, 3]
    width: int,
    height: int,
    vertex_colors: Tensor | None = None,  # [V, 3] in [0, 1]
    face_colors: Tensor | None = None,  # [F, 3] in [0, 1] (wins over vertex_colors)
    lighting: Lighting | None = Lighting(),  # None: unlit colours
    background: Sequence[float] = (1.0, 1.0, 1.0),
    ssaa: int = 2,
    cull_backfaces: bool = False,
    flat_shading: bool = False,
) -> MeshImage:
    """Shaded RGB picture of a mesh and its coverage mask, supersampled ssaa x ssaa and box-filtered.

    Without colours the mesh is a light grey. Smooth shading interpolates area-weighted vertex normals;
    flat_shading uses face normals (faceted look, shows the tessellation).
    """
    if ssaa < 1:
        raise ValueError(f"render_mesh: ssaa must be >= 1, got {ssaa}")
    faces = faces.to(device=vertices.device, dtype=torch.int64)
    verts_cam = world_to_camera(vertices, viewmat.to(vertices))  # [V, 3]
    hi_w, hi_h = width * ssaa, height * ssaa
    frags = rasterize_mesh(verts_cam, faces, scale_intrinsics(K.to(vertices), ssaa), hi_w, hi_h, cull_backfaces)

    mask = frags.mask  # [h, w]
    if face_colors is not None:
        albedo = face_attribute(frags, face_colors.to(vertices))
    elif vertex_colors is not None:
        albedo = interpolate(frags, vertex_colors.to(vertices), faces)
    else:
        albedo = torch.full((hi_h, hi_w, 3), 0.8, dtype=vertices.dtype, device=vertices.device)
    if lighting is not None:
        if flat_shading:
            normals = face_attribute(frags, face_normals(verts_cam, faces))
        else:
            normals = interpolate(frags, vertex_normals(verts_cam, faces), faces)
        positions = interpolate(frags, verts_cam, faces)  # [h, w, 3]
        view_dirs = F.normalize(-positions, dim=-1, eps=1e-20)
        color = shade(albedo, normals, view_dirs, lighting)
    else:
        color = albedo
    bg = torch.as_tensor(background, dtype=color.dtype, device=color.device)
    color = torch.where(mask[..., None], color, bg)
    return MeshImage(box_downsample(color, ssaa), box_downsample(mask.to(color.dtype), ssaa))


__all__ = [
    "Fragments", "rasterize_mesh", "interpolate", "face_attribute", "behind_surface", "dilate_mask", "dilation_pixels",
    "vertex_normals", "face_normals",
    "Lighting", "shade", "MeshImage", "render_mesh", "box_downsample",
]
