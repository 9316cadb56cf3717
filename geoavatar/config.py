"""Typed configuration of the learned avatar and its training, with the paper's defaults, and the
ablation presets A–I of the paper (Tables 3 and 6).

Everything here is a plain dataclass (tyro turns it into CLI options). Step-based milestones are
written for the paper's 200k-step schedule and `TrainConfig.scaled_to(steps)` rescales all of them
proportionally, so a short CPU run keeps the same shape of schedule (APS at half of the run,
densification window, opacity resets, learning-rate decay); `keep` names milestones to leave as they
are (`geoavatar train` keeps those set on its command line: they are steps of that run).
`TrainConfig.extended(n)` is the same run n steps longer with every milestone where it was
(`geoavatar train --extend`). `config_values` / `with_values` read and set fields by dotted name.

Sources of the defaults:
- GeoAvatar (paper, appendix "Hyperparameters"): SH degree 0, 200k steps, APS at N = 100k,
  tau_rigid 0.1, tau_flexible 2.0, tau_mouth = tau_rigid, tau_angle 0.78 rad, lambda D-SSIM 0.2,
  n = 10 parts. "Except for the hyperparameters mentioned, we follow the settings of GaussianAvatars."
- GaussianAvatars (arguments/__init__.py of its release): learning rates, Adam eps 1e-15,
  densification (every 2000 steps from 10k, gradient threshold 2e-4, percent_dense 0.01, prune
  opacity 0.005, opacity reset every 60k, screen size limit 20 px after the first reset, world size
  limit 0.1 x scene extent), scale loss (lambda 1, threshold 0.6), position loss (lambda 1e-2,
  threshold 1.0, a mean over the visible Gaussians), position lr decay span 600k steps (kept on GeoAvatar's
  200k schedule: 3x the run). Its tracking refinement (expr 1e-3, pose 1e-5, translation 1e-6 under torch's Adam)
  is replaced by ours (issue #27): one Adam step per visit of a frame at the avatar-tracking rates (LearningRates).

How L_reg is weighted (the paper writes L = L_rgb + L_reg with L_reg a *sum* over Gaussians): we use
GaussianAvatars' form, a *mean* over the visible Gaussians with weight 1e-2, and the per-set
thresholds of GeoAvatar. Reason: the paper states that its baseline A (GaussianAvatars' position
loss) and its all-flexible model G "are originally same", which only holds if L_reg keeps
GaussianAvatars' reduction and weight and changes only the threshold. A literal sum with weight 1
would also make the loss depend on the number of Gaussians (10k at the start, 50k later) and act as
a hard wall under Adam. L_angle is part of the same sum in the paper, so it gets the same weight.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, is_dataclass, replace
from typing import Any, Iterable, Literal, get_args

# Which regulariser threshold each face uses (see geoavatar.avatar.aps.face_set_ids):
#   "aps"             rigid until the APS step, then per-part rigid/flexible; mouth faces tau_mouth
#   "rigid"           every Gaussian rigid (paper's F, H)
#   "flexible"        every Gaussian flexible (paper's G, I)
#   "gaussianavatars" one threshold for every face: GaussianAvatars' position loss (paper's A)
FaceSetMode = Literal["aps", "rigid", "flexible", "gaussianavatars"]
# Mouth interior appended to the head model (geoavatar.head.mouth):
#   "none" no interior, "gaussianavatars" frontal teeth only, "geoavatar" teeth+molars+palate+floor
MouthKind = Literal["none", "gaussianavatars", "geoavatar"]
# The 10 APS parts (geoavatar.head.regions.PART_NAMES, the part index there is their priority order; a test keeps
# the two lists equal): named here so that a configuration is checked without loading the head layer.
APSPart = Literal["eyeballs", "lips", "nose", "eye_region", "ears", "forehead", "face", "boundary", "neck", "scalp"]
BackgroundMode = Literal["dataset", "random"]
InitColour = Literal["grey", "images"]

PAPER_STEPS = 200_000
# The budget of a new CPU run given no --steps / --minutes (`train --schedule auto`): the steps and the
# longer image side that gave the best held-out scores measured on both test videos (3000 steps: duda 31.32 dB,
# wojtek 22.19; 1500: 30.38, 21.40), 3 min 39 s for duda on 2 quiet cores (BENCHMARKS.md, training budget).
CPU_STEPS = 3000
CPU_RESOLUTION = 256
# The fields of TrainConfig counted in steps (dotted names): TrainConfig.scaled_to scales them.
STEP_FIELDS = ("aps_step", "densify.start", "densify.stop", "densify.every", "densify.reset_opacity_every",
               "lr.position_decay_steps")


@dataclass
class MouthDeformConfig:
    """Part-wise mouth deformation Phi_upper / Phi_lower (paper Sec. 3.2)."""

    enabled: bool = True  # learn the offsets (presets D, E, H, I, E-no-mouth)
    hidden_width: int = 128  # units per hidden layer
    hidden_layers: int = 2  # hidden layers of each MLP
    frequencies: int = 10  # L of gamma(T): sin/cos(2^l * pi * T / num_frames), l = 0..L-1
    expr_dim: int = 100  # expression coefficients fed to Phi (FLAME npz layout: 100)
    offset_unit: float = 0.01  # metres per unit of MLP output (the MLP predicts centimetres)


@dataclass
class ModelConfig:
    """The learned avatar: Gaussians bound to the head model's faces."""

    sh_degree: int = 0  # GeoAvatar uses SH degree 0 (view-independent colour)
    init_opacity: float = 0.1  # one Gaussian per face at the start, opacity 0.1 (GaussianAvatars)
    # Colour += a linear function (3x3 per Gaussian, zero at the start) of the Gaussian's face normal in world
    # axes: diffuse shading by lights fixed to the world, as when a fixed camera films a turning head. An SH-0
    # colour cannot follow that shading and fakes it with view-dependent layering, which novel views under the
    # same lights expose (BENCHMARKS.md, issue #18). Made for a fixed camera (VHAP / GaussianAvatars layouts,
    # `prepare`); with INSTA's per-frame cameras the world normal hardly changes and the term is an inert second
    # colour. On by default for every preset since #18's third round (front, mouth and novel views better on two
    # generated subjects and both test videos); `--config.model.no-normal-shading` turns it off (GaussianAvatars'
    # and the paper's model; tables measured before that round ran without it).
    normal_shading: bool = True
    # Initial colour of the Gaussians: "images" (default since #18's third round): each face's colour in the
    # training frames, head-on views weighted most, unseen faces from the nearest seen one
    # (avatar/colour_init.py); or "grey" (GaussianAvatars, the paper; `--config.model.init-colour grey`).
    init_colour: InitColour = "images"
    # Hair that follows the head's turn (ours, issue #27; avatar/hair_motion.py): each Gaussian off the face (hair,
    # scalp, ears, neck) moves its local mean and colour linearly with the frame's head rotation and neck pose, so
    # long hair that hangs and swings as the head turns is learned instead of blurred. Held-out PSNR, 256 px
    # (BENCHMARKS.md): d3.mp4 (long hair, 1500 steps) 19.12 -> 20.13 dB, duda 31.32 -> 31.72, wojtek 22.19 -> 24.76
    # (3000 steps). Default since the web player plays it too (web/pack.py); off = GaussianAvatars' rigging.
    hair_follows_head: bool = True
    mouth: MouthKind = "geoavatar"  # mouth interior: none, gaussianavatars (frontal teeth), geoavatar (+molars, palate, floor)
    face_sets: FaceSetMode = "aps"  # regulariser threshold per face: aps, rigid, flexible, gaussianavatars (one threshold)
    mouth_deform: MouthDeformConfig = field(default_factory=MouthDeformConfig)  # part-wise mouth deformation


@dataclass
class LossConfig:
    """L = L_rgb + L_reg (+ GaussianAvatars' scale loss). Units of tau: face-scale local units."""

    lambda_dssim: float = 0.2  # L_rgb = (1 - lambda) L1 + lambda (1 - SSIM)
    lambda_reg: float = 1e-2  # weight of the mean of ReLU(r - tau_set) (see module docstring)
    tau_rigid: float = 0.1  # distance threshold of the rigid set
    tau_flexible: float = 2.0  # distance threshold of the flexible set
    tau_mouth: float | None = None  # None: tau_rigid, as the paper sets
    tau_gaussianavatars: float = 1.0  # GaussianAvatars' threshold_xyz, used by face_sets="gaussianavatars"
    use_angle: bool = True  # L_angle on/off (preset E on; A-D, F, G off)
    lambda_angle: float = 1e-2  # same weight as L_reg: the paper sums both terms
    tau_angle: float = 0.78  # 45 degrees
    angle_two_sided: bool = False  # False: angle to the +normal (keeps Gaussians above their face)
    lambda_scale: float = 1.0  # GaussianAvatars: mean |ReLU(exp(s_local) - 0.6)|
    threshold_scale: float = 0.6
    visible_only: bool = True  # GaussianAvatars averages the regularisers over visible Gaussians

    @property
    def tau_mouth_value(self) -> float:
        return self.tau_rigid if self.tau_mouth is None else self.tau_mouth


@dataclass
class WarpedViewConfig:
    """A loss at a camera turned about the head whose target is the training frame warped through the posed head mesh
    (train/warped_view.py, issue #18): a Lambertian skin point the training camera sees has the same colour from
    the side, so the avatar is asked to show it there too. No ground truth beyond the frame itself; on real videos the
    mesh is the tracker's, so its error moves the warped colours.

    Off by default (weight 0): it is for side views, and the front (self re-enactment) never gains from it; larger
    weights than 0.05 cost the front 1-2 dB (BENCHMARKS.md, "Novel views (issue #18, sixth round)")."""

    # Weight of the mean L1 over the valid pixels of the turned render (0: off). Gain at 0.05 on the generated
    # subjects: held-out yaw +-30 views +0.3 dB on average (up to +0.5), LPIPS 1-8 % lower. Cost: 1.4x the training
    # time, the front -0.17..+0.08 dB at 1500 steps and -0.32 at 6000; on the real videos no visible change.
    weight: float = 0.0
    turned_yaw: float = 30.0  # largest |yaw| of the turned camera, degrees (uniform, seeded per step)
    turned_pitch: float = 15.0  # largest |pitch|, degrees
    # Take the turned camera every this many steps (each costs two mesh z-buffers and a render). Weight 0.2 every 4th
    # step gave 0.05-every-step's side-view gain for 1.09x the training time, but cost the front 0.2-0.3 dB on two
    # generated subjects of three.
    every: int = 1
    # APS parts whose faces lie on skin the head model fits: not the scalp (hair lies centimetres above it), forehead
    # (fringes), ears and neck (hair, collars) or the mouth interior (hidden by the lips)
    parts: tuple[APSPart, ...] = ("face", "nose", "eye_region", "lips")
    depth_tolerance: float = 0.005  # metres behind the training camera's z-buffer that still counts as seen there
    max_angle: float = 70.0  # degrees between a face's normal and the training camera's line of sight, at most

    def active(self, step: int) -> bool:
        return self.weight > 0 and step % self.every == 0


@dataclass
class DensifyConfig:
    """Adaptive density control (GaussianAvatars' values, written for a 200k-step run)."""

    start: int = 10_000  # densify when step > start ...
    # ... and step < stop: a third of the run (ours, #40); GaussianAvatars densifies for the whole run, 3DGS for half
    # of it. The rest then refines a fixed set. 3000 steps at 256 px, held-out frames of d3 / duda / wojtek: to the end
    # -> half -> a third, Gaussians 145k -> 100k -> 70k on d3 (duda 55k -> 40k, wojtek 60k -> 43k), d3's train
    # 15.6 -> 11.5 -> 10.1 min, PSNR from half to a third +0.00 / +0.11 / -0.05 dB, LPIPS +3 % / -1 % / +4 %; the
    # avatar renders 1.3x faster (BENCHMARKS.md "Time to a good avatar"). 67k, not 66,666: scales to whole steps.
    stop: int = 67_000
    every: int = 2_000  # densify and prune every this many steps
    reset_opacity_every: int = 60_000  # reset the opacities every this many steps (while densifying)
    reset_opacity_value: float = 0.01  # opacities are clamped to at most this value at a reset
    grad_threshold: float = 2e-4  # mean screen-space gradient norm in NDC units (3DGS convention)
    percent_dense: float = 0.01  # clone if max world scale <= percent_dense * extent, else split
    split_children: int = 2  # Gaussians a split makes of one
    split_shrink: float = 0.8  # children scale = parent scale / (split_shrink * split_children)
    prune_opacity: float = 0.005  # prune Gaussians less opaque than this
    max_screen_size: float = 20.0  # px; applied once step > reset_opacity_every
    max_world_size: float = 0.1  # x extent; applied once step > reset_opacity_every
    min_scene_extent: float = 1.0  # metres; floor for a monocular (single camera) scene extent


@dataclass
class LearningRates:
    """Adam learning rates (GaussianAvatars) and those of the parts GeoAvatar adds."""

    position: float = 5e-3  # x scene extent, decays exponentially to position_final
    position_final: float = 5e-5
    # Steps of the exponential decay to position_final. GaussianAvatars decays over its 600k steps; GeoAvatar
    # trains 200k and otherwise keeps GaussianAvatars' settings, so the span stays 600k (3x the run, on the
    # paper's schedule): a run ends at ~1e-3 x extent, not at position_final. Measured +1.2 dB test PSNR for
    # every preset A-F against a span of one run (BENCHMARKS.md, issue #13, third round).
    position_decay_steps: int = 3 * PAPER_STEPS
    features: float = 2.5e-3  # colour (SH 0)
    opacity: float = 0.05
    scaling: float = 0.017
    rotation: float = 1e-3
    adam_eps: float = 1e-15  # Adam's eps for the Gaussians
    # Phi's rate is not given by the paper. Phi corrects *subtle* per-frame mouth misalignment (mm); with
    # Adam every weight of its last layer moves ~lr per step whatever the gradient's size, and the
    # output is in centimetres, so 1e-4 let the part offsets drift ~5 mm within 1500 steps even with
    # exact parameters (nothing to correct), costing 2 dB of mouth PSNR; 1e-5 keeps them ~0.3 mm
    # there and D = C (BENCHMARKS.md, issue #13).
    mouth_deform: float = 1e-5
    # Training's refinement of the per-frame parameters, per visit of a frame (train/frame_params.RowAdam): the rates
    # of the per-frame fit against the avatar (train/avatar_tracking.py). GaussianAvatars' 1e-3 / 1e-5 / 1e-6 under
    # torch's Adam left it inert; on d3.mp4 (E, 3000 steps at 256 px) these lift the training frames 26.6 -> 29.6 dB
    # with held-out unchanged (docs/expressive_video.md).
    tracking_expr: float = 1e-2
    tracking_pose: float = 1e-3  # rotation, neck, jaw, eyes (rad)
    tracking_translation: float = 2e-4  # m


@dataclass
class TrainConfig:
    """Everything that defines a training run of the avatar."""

    steps: int = PAPER_STEPS  # total training steps (the CLI sets it with --steps or --minutes)
    aps_step: int = 100_000  # N: APS happens after this many steps (face_sets="aps")
    # GaussianAvatars refines the tracked per-frame expression, pose and translation during
    # training with tiny learning rates (its default, not_finetune_flame_params=False); GeoAvatar
    # follows GaussianAvatars' settings, so it is on in every preset. Test frames are never refined.
    refine_tracking: bool = True
    # The colour behind the avatar in training, the target composited on the same colour (randomness.step_background):
    # "dataset" = the dataset's one background, as GaussianAvatars; "random" = a uniform random colour per
    # step, so that no Gaussian can lower the loss by showing the background colour (e.g. to carve the
    # silhouette) and off-mask pixels ask for transparency, not for that colour.
    background: BackgroundMode = "dataset"
    model: ModelConfig = field(default_factory=ModelConfig)  # the learned avatar
    loss: LossConfig = field(default_factory=LossConfig)  # L = L_rgb + L_reg (+ L_angle, scale loss)
    warped_view: WarpedViewConfig = field(default_factory=WarpedViewConfig)  # the frame warped to a turned camera
    densify: DensifyConfig = field(default_factory=DensifyConfig)  # adaptive density control
    lr: LearningRates = field(default_factory=LearningRates)  # Adam learning rates

    def scaled_to(self, steps: int, keep: Iterable[str] = ()) -> "TrainConfig":
        """The same schedule for `steps` total steps: every step-based milestone (STEP_FIELDS) scaled in
        proportion, except those named in `keep` (dotted names, e.g. "aps_step"), which stay as they are:
        `geoavatar train` keeps the milestones a user set on the command line, read as steps of this run."""
        if int(steps) <= 0:
            raise ValueError(f"TrainConfig.scaled_to: steps must be positive, got {steps}")
        keep = set(keep)
        unknown = sorted(keep - set(STEP_FIELDS))
        if unknown:
            raise ValueError(f"TrainConfig.scaled_to: keep names no step-based field: {', '.join(unknown)}")
        steps = int(steps)
        ratio = steps / self.steps
        minimum = {"densify.start": 0, "densify.stop": 0, "aps_step": 0}
        values = config_values(self)
        scaled = {name: values[name] if name in keep else max(minimum.get(name, 1), int(round(values[name] * ratio)))
                  for name in STEP_FIELDS}
        return with_values(replace(self, steps=steps), scaled)

    def extended(self, extra_steps: int) -> "TrainConfig":
        """This run's configuration trained `extra_steps` longer (`geoavatar train --extend`): `steps` grows,
        every milestone stays at its step. So the added steps run after the schedule's end: no densification
        or opacity reset (densify.stop <= the old end), APS already done, the position learning rate going on
        along its decay (to lr.position_final at lr.position_decay_steps, then held), the other rates constant."""
        if int(extra_steps) <= 0:
            raise ValueError(f"TrainConfig.extended: extra_steps must be positive, got {extra_steps}")
        return replace(self, steps=self.steps + int(extra_steps))

    def validate(self) -> "TrainConfig":
        """Raise ValueError naming the option when a value is out of range."""
        problems = []
        if self.steps <= 0:
            problems.append(f"steps must be positive (got {self.steps})")
        if not 0 <= self.aps_step <= self.steps:
            problems.append(f"aps_step must lie in [0, steps={self.steps}] (got {self.aps_step})")
        if self.background not in ("dataset", "random"):
            problems.append(f"background must be 'dataset' or 'random' (got {self.background!r})")
        if self.model.sh_degree != 0:
            problems.append(f"model.sh_degree: only 0 is supported (GeoAvatar uses 0), got {self.model.sh_degree}")
        if self.model.init_colour not in ("grey", "images"):
            problems.append(f"model.init_colour must be 'grey' or 'images' (got {self.model.init_colour!r})")
        if not 0.0 < self.model.init_opacity < 1.0:
            problems.append(f"model.init_opacity must lie in (0, 1) (got {self.model.init_opacity})")
        if self.model.mouth_deform.enabled and self.model.mouth == "none":
            problems.append("model.mouth_deform.enabled needs a mouth structure (model.mouth is 'none')")
        md = self.model.mouth_deform
        for name in ("hidden_width", "hidden_layers", "expr_dim"):
            if getattr(md, name) < 1:
                problems.append(f"model.mouth_deform.{name} must be >= 1 (got {getattr(md, name)})")
        if md.frequencies < 0:
            problems.append(f"model.mouth_deform.frequencies must be >= 0 (got {md.frequencies})")
        for name in ("tau_rigid", "tau_flexible", "tau_gaussianavatars", "tau_angle", "lambda_reg",
                     "lambda_angle", "lambda_scale", "threshold_scale"):
            if getattr(self.loss, name) < 0:
                problems.append(f"loss.{name} must be >= 0 (got {getattr(self.loss, name)})")
        if not 0.0 <= self.loss.lambda_dssim <= 1.0:
            problems.append(f"loss.lambda_dssim must lie in [0, 1] (got {self.loss.lambda_dssim})")
        wv = self.warped_view
        for name in ("weight", "turned_yaw", "turned_pitch", "depth_tolerance"):
            if getattr(wv, name) < 0:
                problems.append(f"warped_view.{name} must be >= 0 (got {getattr(wv, name)})")
        if wv.every < 1:
            problems.append(f"warped_view.every must be >= 1 (got {wv.every})")
        if not 0 < wv.max_angle <= 90:
            problems.append(f"warped_view.max_angle must lie in (0, 90] degrees (got {wv.max_angle})")
        part_names = get_args(APSPart)
        unknown = [name for name in wv.parts if name not in part_names]
        if unknown or not wv.parts:
            given = ", ".join(wv.parts) or "none"
            problems.append(f"warped_view.parts must be some of {', '.join(part_names)} (got {given})")
        d = self.densify
        if d.every < 1 or d.reset_opacity_every < 1:
            problems.append("densify.every and densify.reset_opacity_every must be >= 1")
        if d.split_children < 2:
            problems.append(f"densify.split_children must be >= 2 (got {d.split_children})")
        for f in fields(LearningRates):
            if getattr(self.lr, f.name) < 0:
                problems.append(f"lr.{f.name} must be >= 0 (got {getattr(self.lr, f.name)})")
        if problems:
            raise ValueError("invalid training configuration: " + "; ".join(problems))
        return self


# --- ablation presets -------------------------------------------------------------------------


@dataclass(frozen=True)
class AblationComponents:
    """What one preset switches (the columns of the paper's ablation tables)."""

    face_sets: FaceSetMode
    mouth: MouthKind
    mouth_deform: bool
    angle_loss: bool
    description: str


# Paper Table 3 (A-E, cumulative) and Table 6 (F-I). Reading of the paper:
# - A is GaussianAvatars with SH degree 0: its own position loss (one threshold for every face,
#   teeth included), its frontal teeth, no deformation, no L_angle. The paper says A and G "are
#   originally same" (it believes GaussianAvatars' threshold equals tau_flexible); GaussianAvatars'
#   released threshold is 1.0, which A uses, so here G differs from A only by that number (2.0).
# - F/G train "the baseline model assuming every Gaussian as the rigid / flexible set": A's
#   components with a single GeoAvatar threshold for every Gaussian, no L_angle.
# - H/I add "FLAME mouth modification, i.e. mesh modification and part-wise deformation" to F/G.
#   Table 6's I equals Table 7's "Ours w/o APS" to the last digit (0.853 / 31.318 / 0.930 / 0.629), so
#   H and I keep the rest of GeoAvatar, L_angle included, and GeoAvatar's mouth set F_m with
#   tau_m = tau_r (it belongs to the mouth structure, not to APS); F and G, with GaussianAvatars'
#   teeth, give every face, teeth included, their one threshold.
# - Table 7's isolating ablations: "w/o APS" = I, "w/o L_angle" = D, and the two others are
#   "E-no-mouth" and "E-no-deform" below.
ABLATIONS: dict[str, AblationComponents] = {
    "A": AblationComponents("gaussianavatars", "gaussianavatars", False, False, "GaussianAvatars, SH degree 0 (baseline)"),
    "B": AblationComponents("aps", "gaussianavatars", False, False, "A + APS"),
    "C": AblationComponents("aps", "geoavatar", False, False, "B + mouth structure"),
    "D": AblationComponents("aps", "geoavatar", True, False, "C + part-wise mouth deformation"),
    "E": AblationComponents("aps", "geoavatar", True, True, "D + L_angle = GeoAvatar"),
    "F": AblationComponents("rigid", "gaussianavatars", False, False, "baseline, every Gaussian rigid"),
    "G": AblationComponents("flexible", "gaussianavatars", False, False, "baseline, every Gaussian flexible"),
    "H": AblationComponents("rigid", "geoavatar", True, True, "F + mouth structure and deformation"),
    "I": AblationComponents("flexible", "geoavatar", True, True, "G + mouth structure and deformation (= GeoAvatar w/o APS)"),
    "E-no-mouth": AblationComponents("aps", "gaussianavatars", True, True, "GeoAvatar w/o mouth structure (Table 7)"),
    "E-no-deform": AblationComponents("aps", "geoavatar", False, True, "GeoAvatar w/o part-wise deformation (Table 7)"),
}
DEFAULT_PRESET = "E"
PresetName = Literal["A", "B", "C", "D", "E", "F", "G", "H", "I", "E-no-mouth", "E-no-deform"]
assert set(PresetName.__args__) == set(ABLATIONS), "PresetName must list every preset of ABLATIONS"


def preset(name: str = DEFAULT_PRESET, steps: int | None = None) -> TrainConfig:
    """The training configuration of an ablation preset (paper defaults), optionally scaled to `steps`."""
    if name not in ABLATIONS:
        raise ValueError(f"unknown preset '{name}'; choose one of {', '.join(ABLATIONS)}")
    parts = ABLATIONS[name]
    base = TrainConfig()
    model = replace(
        base.model,
        face_sets=parts.face_sets,
        mouth=parts.mouth,
        mouth_deform=replace(base.model.mouth_deform, enabled=parts.mouth_deform),
    )
    config = replace(base, model=model, loss=replace(base.loss, use_angle=parts.angle_loss)).validate()
    return config if steps is None else config.scaled_to(steps)


def config_values(config: Any, prefix: str = "") -> dict[str, Any]:
    """Every leaf field of a (nested) config dataclass, or of its asdict() / JSON form, by dotted name:
    {"aps_step": 100000, "loss.tau_rigid": 0.1, ...}."""
    items = config.items() if isinstance(config, dict) else ((f.name, getattr(config, f.name)) for f in fields(config))
    out = {}
    for name, value in items:
        if is_dataclass(value) or isinstance(value, dict):
            out.update(config_values(value, f"{prefix}{name}."))
        else:
            out[f"{prefix}{name}"] = value
    return out


def with_values(config: Any, values: dict[str, Any]) -> Any:
    """A copy of a (nested) config dataclass with the leaf fields named by dotted names set; ValueError
    naming an unknown field."""
    nested: dict[str, dict[str, Any]] = {}
    direct = {}
    names = {f.name for f in fields(config)}
    for name, value in values.items():
        head, _, rest = name.partition(".")
        if head not in names or bool(rest) != is_dataclass(getattr(config, head)):
            raise ValueError(f"{type(config).__name__} has no field '{name}'")
        if rest:
            nested.setdefault(head, {})[rest] = value
        else:
            direct[head] = value
    for head, inner in nested.items():
        direct[head] = with_values(getattr(config, head), inner)
    return replace(config, **direct)


def preset_components(config: TrainConfig) -> AblationComponents:
    """The component switches a configuration sets (for reports and tests)."""
    return AblationComponents(
        config.model.face_sets, config.model.mouth, config.model.mouth_deform.enabled, config.loss.use_angle, ""
    )


def presets_table() -> str:
    """A short text table of the presets."""
    rows = [f"{'preset':<12} {'face sets':<16} {'mouth':<16} {'deform':<7} {'L_angle':<8} description"]
    for name, p in ABLATIONS.items():
        rows.append(
            f"{name:<12} {p.face_sets:<16} {p.mouth:<16} {'yes' if p.mouth_deform else 'no':<7} "
            f"{'yes' if p.angle_loss else 'no':<8} {p.description}"
        )
    return "\n".join(rows)
