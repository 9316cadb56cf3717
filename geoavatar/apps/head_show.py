"""`geoavatar head show`: a contact sheet of a head model that a person can judge at a glance.

Rows: the neutral template (front, three-quarter, side, the parts used by APS); a few expressions;
the open jaw (front, x-ray through the skin, a sagittal cut-away, and the mouth structure alone).
Rendering uses the small mesh rasterizer in geoavatar.render.mesh (CPU is fine: about a second per
tile at the default size).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Optional

import numpy as np
import torch
from torch import Tensor

from geoavatar.head.base import HeadModel
from geoavatar.imaging import to_uint8
from geoavatar.io.atomic import atomic_write_png
from geoavatar.render.camera import intrinsics_from_fov, look_at, world_to_camera
from geoavatar.render.mesh import Lighting, render_mesh

# --- colours -----------------------------------------------------------------------------------

SKIN = (0.86, 0.70, 0.60)
EYE_WHITE = (0.93, 0.93, 0.90)
IRIS = (0.25, 0.33, 0.45)
PUPIL = (0.05, 0.05, 0.06)
TEETH = (0.96, 0.94, 0.84)
GUM_PALATE = (0.80, 0.42, 0.45)  # palate and mouth floor
INTERIOR = (0.45, 0.22, 0.22)  # the skin seen from inside, in cut-away views
BACKGROUND = (1.0, 1.0, 1.0)
LABEL_HEIGHT_FRACTION = 0.09
FOV_DEG = 18.0  # a long lens: little perspective distortion, as a portrait

# Distinct colours for region / part views (Okabe-Ito-like, then extras).
PALETTE = (
    (0.90, 0.62, 0.00), (0.34, 0.71, 0.91), (0.00, 0.62, 0.45), (0.94, 0.89, 0.26), (0.00, 0.45, 0.70),
    (0.84, 0.37, 0.00), (0.80, 0.47, 0.65), (0.55, 0.55, 0.55), (0.60, 0.80, 0.35), (0.55, 0.35, 0.70),
    (0.95, 0.95, 0.95), (0.35, 0.25, 0.20),
)

# Expressions to show, each with the mode names it may go by (metadata["expression_names"]), in order.
WANTED_EXPRESSIONS = (
    ("smile", ("smile",)),
    ("blink", ("blink", "eyes_closed", "eye_close")),
    ("pucker", ("lip_pucker", "pucker", "kiss")),
    ("brow raise", ("brow_raise", "brows_up", "brow_up")),
)


# --- public entry point ------------------------------------------------------------------------


def head_show(
    model: Literal["openhead", "flame"] = "openhead",
    out: Path = Path("head.png"),
    mouth: Literal["geoavatar", "gaussianavatars", "none"] = "geoavatar",
    flame_dir: Optional[Path] = None,
    size: int = 384,
) -> None:
    """Render a contact sheet of a head model: template views, expressions, open jaw and mouth structure.

    Args:
        model: Head model to show: the built-in OpenHead or a user-supplied FLAME.
        out: PNG file to write (its folder is created).
        mouth: Mouth structure appended to the head: GeoAvatar's (teeth with molars, palate, floor),
            GaussianAvatars' teeth rings, or none.
        flame_dir: Folder holding the FLAME files (only for --model flame).
        size: Side of one square tile in pixels.
    """
    from geoavatar.head import load_head_model

    if size < 64:
        raise SystemExit(f"geoavatar head show: --size must be at least 64 pixels, got {size}")
    options = {}
    if model == "flame" and flame_dir is not None:
        options["flame_dir"] = flame_dir
    head = load_head_model(model, mouth=mouth, **options)  # FLAME's file errors are GeoAvatarErrors: one line
    sheet = contact_sheet(head, tile=size)
    atomic_write_png(out, sheet, optimize=True)
    print(f"wrote {out} ({sheet.width}x{sheet.height}): {head.name}, {head.num_vertices} vertices, "
          f"{head.num_faces} faces, {head.num_expr} expression modes, mouth={mouth}")


# --- the sheet ---------------------------------------------------------------------------------


@dataclass
class Tile:
    """One picture of the sheet: which pose, seen from where, coloured how."""

    label: str
    params: dict[str, Tensor] = field(default_factory=dict)  # overrides of the neutral parameters
    yaw_deg: float = 0.0  # camera azimuth about the head's vertical axis; < 0 moves it to the subject's right
    pitch_deg: float = 0.0  # camera elevation; + looks from above
    focus: Literal["head", "mouth"] = "head"
    zoom: float = 1.0  # < 1 shows more around the focus
    shift: float = 0.0  # move the subject right by this fraction of the tile (room for a legend)
    style: Literal["skin", "parts", "xray", "cutaway", "arches"] = "skin"


def contact_sheet(head: HeadModel, tile: int = 384, columns: int = 4):
    """The sheet as a PIL image (columns x rows tiles, each with a label underneath)."""
    from PIL import Image, ImageDraw

    head = head.cpu()
    scene = _HeadScene.build(head)
    tiles = _plan_tiles(head, scene)
    label_h = max(14, int(tile * LABEL_HEIGHT_FRACTION))
    rows = math.ceil(len(tiles) / columns)
    sheet = Image.new("RGB", (columns * tile, rows * (tile + label_h)), tuple(int(255 * c) for c in BACKGROUND))
    draw = ImageDraw.Draw(sheet)
    for i, spec in enumerate(tiles):
        picture = _render_tile(head, scene, spec, tile)
        x, y = (i % columns) * tile, (i // columns) * (tile + label_h)
        sheet.paste(Image.fromarray(picture), (x, y))
        _draw_label(draw, spec.label, x, y + tile, tile, label_h)
        if spec.style == "parts" and scene.part_names:
            _draw_legend(draw, scene.part_names, scene.part_colors, x, y, tile)
        if spec.style == "arches" and scene.mouth_legend:  # in the gap between the two arches
            names, colors = [n for n, _ in scene.mouth_legend], [c for _, c in scene.mouth_legend]
            _draw_legend(draw, names, colors, x, y + tile // 2 - len(names) * _legend_line(tile) // 2, tile)
    return sheet


@dataclass
class _HeadScene:
    """What every tile shares: colours, face sets and framing computed once from the template."""

    vertex_colors: Tensor  # [V, 3]
    mouth_faces: Tensor  # [Fm] face ids of the mouth structure (may be empty)
    head_faces: Tensor  # [Fh] all other faces
    mouth_face_colors: Tensor  # [F, 3] distinct colours for the mouth parts (x-ray / mouth-only views)
    part_face_colors: Tensor | None  # [F, 3] colour of each face's part, None without a partition
    part_names: list[str]
    part_colors: list[tuple[float, float, float]]
    mouth_legend: list[tuple[str, tuple[float, float, float]]]  # mouth part name -> display colour
    centre: Tensor  # [3] framing centre of the head
    radius: float  # framing radius of the head
    mouth_centre: Tensor  # [3]
    mouth_radius: float

    @staticmethod
    def build(head: HeadModel) -> "_HeadScene":
        data = head.data
        template = head.template_output().vertices[0].detach()  # [V, 3]
        num_faces = head.num_faces
        faces = head.faces
        mouth_faces = _mouth_face_ids(head)
        is_mouth = torch.zeros(num_faces, dtype=torch.bool)
        is_mouth[mouth_faces] = True
        head_faces = torch.nonzero(~is_mouth).squeeze(1)

        colors = torch.tensor(SKIN).expand(head.num_vertices, 3).clone()
        _paint_eyes(colors, template, data.regions)
        mouth_vertex_sets = _mouth_vertex_sets(head)
        face_mouth_colors = torch.tensor(SKIN).expand(num_faces, 3).clone()
        for name, (vids, color) in mouth_vertex_sets.items():
            colors[vids] = torch.tensor(_mouth_natural_color(name))
            in_set = torch.zeros(head.num_vertices, dtype=torch.bool)
            in_set[vids] = True
            face_mouth_colors[in_set[faces].all(1)] = torch.tensor(color)

        part_face_colors, part_names, part_colors = _part_colors(head, mouth_faces)

        centre, radius = _head_frame(head, template, head_faces)
        mouth_centre, mouth_radius = _mouth_frame(head, template, centre, radius)
        legend = [(name.replace("_", " "), color) for name, (_, color) in mouth_vertex_sets.items()]
        return _HeadScene(colors, mouth_faces, head_faces, face_mouth_colors, part_face_colors, part_names,
                          part_colors, legend, centre, radius, mouth_centre, mouth_radius)


def _plan_tiles(head: HeadModel, scene: _HeadScene) -> list[Tile]:
    jaw_open = {"jaw_pose": torch.tensor([[0.32, 0.0, 0.0]])}  # radians about the jaw's x axis (FLAME: opens)
    tiles = [
        Tile("template, front"),
        Tile("three-quarter", yaw_deg=-40.0),
        Tile("side", yaw_deg=-90.0),
    ]
    if scene.part_face_colors is not None:
        tiles.append(Tile(f"{len(scene.part_names)} parts (APS)", yaw_deg=-25.0, style="parts", shift=0.14))
    for name, params in _expression_tiles(head):
        tiles.append(Tile(name, params=params, yaw_deg=-12.0))
    tiles.append(Tile("jaw open", params=jaw_open, yaw_deg=-12.0, pitch_deg=5.0))
    if scene.mouth_faces.numel():
        tiles += [
            Tile("jaw open, x-ray: mouth structure", params=jaw_open, pitch_deg=8.0, focus="mouth", style="xray"),
            Tile("cut-away at the mid-plane", params=jaw_open, yaw_deg=-75.0, pitch_deg=-5.0, focus="mouth",
                 style="cutaway", zoom=0.9),
            Tile("upper part from below, lower from above", focus="mouth", style="arches"),
        ]
    return tiles


def _expression_tiles(head: HeadModel, count: int = 4) -> list[tuple[str, dict[str, Tensor]]]:
    """(label, parameters) for a few expressions: named ones from the metadata, else the leading modes.

    A wanted expression uses the mode with exactly that name, else every mode that has it as a
    prefix or suffix ("blink" -> blink_left + blink_right). Named modes are shown at coefficient 1
    (OpenHead's unit is the full expression); unnamed ones (FLAME) at +2, about two standard deviations.
    """
    names = [str(n) for n in (head.data.metadata.get("expression_names") or [])][: head.num_expr]
    chosen: list[tuple[str, list[int], float]] = []
    for label, aliases in WANTED_EXPRESSIONS:
        modes = _modes_named(names, aliases)
        if modes:
            chosen.append((label, modes, 1.0))
    used = {m for _, modes, _ in chosen for m in modes}
    for index in range(head.num_expr):  # top up with the leading modes
        if len(chosen) >= count:
            break
        if index not in used:
            label = names[index].replace("_", " ") if index < len(names) else f"expression mode {index} (+2)"
            chosen.append((label, [index], 1.0 if index < len(names) else 2.0))
    tiles = []
    for label, modes, value in chosen[:count]:
        expr = torch.zeros(1, head.num_expr)
        expr[0, modes] = value
        tiles.append((label, {"expr": expr}))
    return tiles


def _modes_named(names: list[str], aliases: tuple[str, ...]) -> list[int]:
    lowered = [n.lower() for n in names]
    for alias in aliases:
        if alias in lowered:
            return [lowered.index(alias)]
        partial = [i for i, n in enumerate(lowered) if n.startswith(alias + "_") or n.endswith("_" + alias)]
        if partial:
            return partial
    return []


def _render_tile(head: HeadModel, scene: _HeadScene, spec: Tile, size: int) -> np.ndarray:
    params = head.zero_params(1)
    params.update(spec.params)
    with torch.no_grad():
        verts = head.forward_params(params).vertices[0]  # [V, 3]
    centre, radius = (scene.mouth_centre, scene.mouth_radius) if spec.focus == "mouth" else (scene.centre, scene.radius)
    viewmat, K = _orbit_camera(centre, radius / spec.zoom, spec.yaw_deg, spec.pitch_deg, size)
    K[0, 2] += spec.shift * size
    faces = head.faces
    light = Lighting(specular=0.12)

    def draw(face_ids: Tensor, *, face_colors: Tensor | None = None, lighting: Lighting | None = light):
        return render_mesh(verts, faces[face_ids], viewmat, K, size, size,
                           vertex_colors=None if face_colors is not None else scene.vertex_colors,
                           face_colors=None if face_colors is None else face_colors[face_ids],
                           lighting=lighting, background=BACKGROUND, ssaa=2)

    all_faces = torch.arange(head.num_faces)
    if spec.style == "skin":
        image = draw(all_faces).image
    elif spec.style == "parts":
        image = draw(all_faces, face_colors=scene.part_face_colors).image
    elif spec.style == "arches":
        image = _render_arches(head, scene, verts, size, light)
    elif spec.style == "xray":
        skin = draw(scene.head_faces)
        inside = draw(scene.mouth_faces, face_colors=scene.mouth_face_colors)
        # Skin at 35% opacity over the mouth parts where they are visible.
        image = torch.where(inside.mask[..., None] > 0,
                            0.35 * skin.image + 0.65 * (inside.image * inside.mask[..., None]
                                                        + skin.image * (1 - inside.mask[..., None])),
                            skin.image)
    elif spec.style == "cutaway":
        # Remove everything on the camera's side of the mid-sagittal plane x = centre: a section.
        camera_side = 1.0 if spec.yaw_deg > 0 else -1.0
        tri_x = verts[faces][..., 0]  # [F, 3]
        far_half = ((tri_x - float(scene.centre[0])) * camera_side).amax(1) <= 1e-4  # [F]
        is_mouth = torch.zeros(head.num_faces, dtype=torch.bool)
        is_mouth[scene.mouth_faces] = True
        # The inside of the head (skin seen from behind) in a dark flesh tone, so the section reads as one.
        tri = world_to_camera(verts, viewmat)[faces]  # [F, 3, 3]
        normal = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        seen_from_inside = (normal * tri[:, 0]).sum(-1) > 0  # [F]
        skin = torch.where(seen_from_inside[:, None], torch.tensor(INTERIOR), torch.tensor(SKIN))
        face_colors = torch.where(is_mouth[:, None], scene.mouth_face_colors, skin)
        image = draw(torch.nonzero(far_half).squeeze(1), face_colors=face_colors).image
    else:
        raise ValueError(f"unknown tile style '{spec.style}'")
    return to_uint8(image)


def _orbit_camera(centre: Tensor, radius: float, yaw_deg: float, pitch_deg: float, size: int) -> tuple[Tensor, Tensor]:
    """A camera on a sphere around `centre` that frames a ball of `radius` (FLAME axes: +z front, +y up)."""
    yaw, pitch = math.radians(yaw_deg), math.radians(pitch_deg)
    distance = radius * 1.08 / math.sin(math.radians(FOV_DEG) / 2)
    direction = torch.tensor([math.sin(yaw) * math.cos(pitch), math.sin(pitch), math.cos(yaw) * math.cos(pitch)])
    eye = centre + distance * direction
    return look_at(eye, centre, torch.tensor([0.0, 1.0, 0.0])), intrinsics_from_fov(FOV_DEG, size, size)


def _render_arches(head: HeadModel, scene: _HeadScene, verts: Tensor, size: int, light: Lighting) -> Tensor:
    """Two half-height views stacked: the upper mouth part seen from below (teeth arch and palate) and
    the lower part seen from above (teeth arch and floor), front teeth towards the middle."""
    halves = []
    for group, below in (("mouth_upper", True), ("mouth_lower", False)):
        ids = head.data.face_groups.get(group)
        if ids is None or len(ids) == 0:
            halves.append(torch.ones(size // 2, size, 3) * torch.tensor(BACKGROUND))
            continue
        face_ids = torch.as_tensor(np.asarray(ids, dtype=np.int64))
        points = verts[torch.unique(head.faces[face_ids].reshape(-1))]
        lo, hi = points.amin(0), points.amax(0)
        centre = (lo + hi) / 2
        radius = float(torch.maximum(hi[0] - lo[0], (hi[2] - lo[2]) * 2).max()) / 2 * 1.25
        elevation = math.radians(70.0)
        direction = torch.tensor([0.0, (-1.0 if below else 1.0) * math.sin(elevation), math.cos(elevation)])
        distance = radius / math.sin(math.radians(FOV_DEG) / 2)
        # Image "up" is the back of the mouth for the lower arch and the front for the upper one.
        up = torch.tensor([0.0, 0.0, 1.0 if not below else -1.0])
        viewmat = look_at(centre + distance * direction, centre, up)
        K = intrinsics_from_fov(FOV_DEG, size, size // 2)
        halves.append(render_mesh(verts, head.faces[face_ids], viewmat, K, size, size // 2,
                                  face_colors=scene.mouth_face_colors[face_ids], lighting=light,
                                  background=BACKGROUND, ssaa=2).image)
    image = torch.cat(halves, 0)
    if image.shape[0] < size:  # odd sizes
        image = torch.cat([image, torch.ones(size - image.shape[0], size, 3) * torch.tensor(BACKGROUND)], 0)
    return image


# --- which faces are what ----------------------------------------------------------------------


def _mouth_face_ids(head: HeadModel) -> Tensor:
    groups = head.data.face_groups
    if "mouth" in groups:
        return torch.as_tensor(np.asarray(groups["mouth"], dtype=np.int64))
    return torch.zeros(0, dtype=torch.int64)


def _mouth_vertex_sets(head: HeadModel) -> dict[str, tuple[Tensor, tuple[float, float, float]]]:
    """Named vertex sets of the mouth structure -> (vertex ids, display colour).

    Uses the finest groups the model provides: teeth / palate / floor groups when present,
    else the upper and lower parts.
    """
    groups = head.data.vertex_groups
    fine = [n for n in groups if any(k in n for k in ("teeth", "palate", "floor"))]
    names = fine if fine else [n for n in groups if n.startswith("mouth_")]
    display = {
        "upper": (0.20, 0.45, 0.85), "lower": (0.90, 0.55, 0.10),
    }
    out = {}
    for i, name in enumerate(sorted(names)):
        vids = torch.as_tensor(np.asarray(groups[name], dtype=np.int64))
        if vids.numel() == 0:
            continue
        if fine:
            color = _fine_mouth_display_color(name, i)
        else:
            color = display.get(name.removeprefix("mouth_"), PALETTE[i % len(PALETTE)])
        out[name] = (vids, color)
    return out


def _fine_mouth_display_color(name: str, index: int) -> tuple[float, float, float]:
    upper = "upper" in name
    if "teeth" in name:
        return (0.98, 0.96, 0.80) if upper else (0.80, 0.92, 0.98)
    if "palate" in name:
        return (0.85, 0.25, 0.30)
    if "floor" in name:
        return (0.55, 0.30, 0.75)
    return PALETTE[index % len(PALETTE)]


def _mouth_natural_color(name: str) -> tuple[float, float, float]:
    return TEETH if "teeth" in name or not any(k in name for k in ("palate", "floor")) else GUM_PALATE


def _paint_eyes(colors: Tensor, template: Tensor, regions: dict[str, np.ndarray]) -> None:
    """White eyeballs with an iris and pupil around the most forward point (+z) of each eyeball."""
    for side in ("left_eyeball", "right_eyeball"):
        if side not in regions or len(regions[side]) == 0:
            continue
        vids = torch.as_tensor(np.asarray(regions[side], dtype=np.int64))
        points = template[vids]  # [n, 3]
        lo, hi = points.amin(0), points.amax(0)
        centre = (lo + hi) / 2
        direction = torch.nn.functional.normalize(points - centre, dim=-1)
        cos_forward = direction[:, 2]  # +z is the gaze direction at rest
        eye = torch.tensor(EYE_WHITE).expand(len(vids), 3).clone()
        eye[cos_forward > math.cos(math.radians(32))] = torch.tensor(IRIS)
        eye[cos_forward > math.cos(math.radians(13))] = torch.tensor(PUPIL)
        colors[vids] = eye


def _part_colors(head: HeadModel, mouth_faces: Tensor):
    """Per-face colours of the 10 APS parts (geoavatar.head.regions), None when the model has no regions.

    Mouth-structure faces (part -1) keep the mouth colours.
    """
    from geoavatar.head.regions import face_parts

    try:
        parts = face_parts(head.data)
    except ValueError:  # no region masks: no parts tile
        return None, [], []
    names = list(parts.part_names)
    colors = [PALETTE[i % len(PALETTE)] for i in range(len(names))]
    labels = torch.as_tensor(parts.part_of_face, dtype=torch.int64)  # [F], -1 for the mouth
    table = torch.tensor(colors + [GUM_PALATE])  # the last row: mouth structure
    return table[torch.where(labels >= 0, labels, torch.full_like(labels, len(names)))], names, colors


def _head_frame(head: HeadModel, template: Tensor, head_faces: Tensor) -> tuple[Tensor, float]:
    """Framing of whole-head views: the skin without the neck (a portrait crop), as a centre and radius."""
    faces = head.faces[head_faces] if head_faces.numel() else head.faces
    vids = torch.unique(faces.reshape(-1))
    regions = head.data.regions
    neck_ids = [np.asarray(regions[n], dtype=np.int64) for n in ("neck", "boundary") if n in regions]
    if neck_ids:
        is_neck = torch.zeros(head.num_vertices, dtype=torch.bool)
        is_neck[torch.as_tensor(np.concatenate(neck_ids))] = True
        if (~is_neck[vids]).sum() > 3:
            vids = vids[~is_neck[vids]]
    points = template[vids]
    lo, hi = points.amin(0), points.amax(0)
    # The largest side of the box: the head fits in every view of the orbit (front, side, ...).
    return (lo + hi) / 2, float((hi - lo).max() / 2) * 1.12


def _mouth_frame(head: HeadModel, template: Tensor, centre: Tensor, radius: float) -> tuple[Tensor, float]:
    """Framing of close-ups of the mouth: around the lip rings (or the mouth structure)."""
    ids = [r for r in (head.data.lip_ring_upper, head.data.lip_ring_lower) if r is not None]
    groups = head.data.vertex_groups
    mouth_ids = [np.asarray(g) for n, g in groups.items() if n.startswith("mouth")]
    if mouth_ids:
        vids = torch.as_tensor(np.concatenate(mouth_ids + ids).astype(np.int64))
    elif ids:
        vids = torch.as_tensor(np.concatenate(ids).astype(np.int64))
    else:  # no mouth information: the lower front third of the head
        return centre + torch.tensor([0.0, -0.35 * radius, 0.5 * radius]), radius * 0.45
    points = template[vids]
    lo, hi = points.amin(0), points.amax(0)
    return (lo + hi) / 2, max(float((hi - lo).norm() / 2) * 1.25, radius * 0.3)


# --- drawing and writing -----------------------------------------------------------------------


def _draw_label(draw, text: str, x: int, y: int, width: int, height: int) -> None:
    font = _font(max(10, int(height * 0.6)))
    box = draw.textbbox((0, 0), text, font=font)
    tw, th = box[2] - box[0], box[3] - box[1]
    draw.text((x + (width - tw) // 2, y + (height - th) // 2 - box[1]), text, fill=(20, 20, 20), font=font)


def _draw_legend(draw, names: list[str], colors: list, x: int, y: int, tile: int) -> None:
    font = _font(max(9, tile // 34))
    line = _legend_line(tile)
    for i, (name, color) in enumerate(zip(names, colors)):
        top = y + 4 + i * line
        draw.rectangle([x + 4, top + 1, x + 4 + line - 3, top + line - 2], fill=tuple(int(255 * c) for c in color))
        draw.text((x + 6 + line, top), name.replace("_", " "), fill=(30, 30, 30), font=font)


def _legend_line(tile: int) -> int:
    return max(10, tile // 30)


def _font(pixels: int):
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=pixels)  # Pillow >= 10.1 scales its built-in font
    except TypeError:
        return ImageFont.load_default()


__all__ = ["head_show", "contact_sheet", "Tile"]
