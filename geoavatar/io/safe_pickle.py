"""A restricted unpickler for the user-supplied FLAME pickles (never plain `pickle.load`).

FLAME's `generic_model.pkl` / `flame2023.pkl` / `FLAME_masks.pkl` are Python 2 pickles of dicts
holding numpy arrays, one scipy.sparse matrix (J_regressor) and chumpy `Ch` objects (shapedirs).
A pickle can name any importable callable, so a plain load of a file from the internet can run code.
`RestrictedUnpickler.find_class` resolves only an allow-list, and never imports anything the pickle
names:

- numpy array/scalar/dtype reconstruction (`numpy.core.multiarray._reconstruct`, `.scalar`,
  `numpy.core.numeric._frombuffer`, `numpy.ndarray`, `numpy.dtype`, and their numpy 2 spellings
  `numpy._core.*`), mapped to the objects of the numpy that is installed;
- scipy.sparse csc/csr/coo matrices (any `scipy.sparse*` module spelling, old or new scipy), loaded
  into a stand-in that keeps their raw arrays and is rebuilt with the installed scipy afterwards;
- chumpy classes (`chumpy.ch.Ch`, `chumpy.reordering.*`, `chumpy.ch_ops.*`): a stand-in whose
  `__setstate__` keeps the state dict; a `Ch` stores its value in attribute `x`;
- harmless builtins: `object`, `set`, `frozenset`, `slice`, `complex`, `bytearray`,
  `collections.OrderedDict`, `copyreg._reconstructor` (Python 2 protocol-0/1 object rebuilding; its
  class arguments can only be allow-listed ones) and `_codecs.encode` restricted to latin1 (how
  protocol-2 pickles written by Python 3 store bytes).

Everything else (os.system, builtins.eval/exec, subprocess.Popen, functools.partial, ...) raises
`ForbiddenPickleGlobal`, which names the file and the global, before anything runs.
"""

from __future__ import annotations

import codecs
import collections
import copyreg
import importlib
import io
import pickle
from pathlib import Path

import numpy as np

from geoavatar.errors import GeoAvatarError

SPARSE_CLASSES = ("csc_matrix", "csr_matrix", "coo_matrix", "csc_array", "csr_array", "coo_array")


class ForbiddenPickleGlobal(GeoAvatarError, pickle.UnpicklingError):
    """The pickle names a global outside the allow-list (it could run code when loaded)."""


class UnreadablePickle(GeoAvatarError, pickle.UnpicklingError):
    """The file is not a pickle this loader can read (truncated, foreign objects); the message names it."""


class ChumpyStandIn:
    """Takes the place of a chumpy object; keeps its pickled state (the value is in 'x')."""

    chumpy_path = "chumpy.ch.Ch"

    def __new__(cls, *args, **kwargs):  # NEWOBJ passes the pickled constructor args; ignore them
        return object.__new__(cls)

    def __setstate__(self, state):
        if isinstance(state, tuple) and len(state) == 2:  # (dict state, slot state)
            state = {**(state[0] or {}), **(state[1] or {})}
        self.state = dict(state) if isinstance(state, dict) else {"x": state}

    def to_array(self, source: str) -> np.ndarray:
        value = getattr(self, "state", {}).get("x")
        if value is None:
            raise UnreadablePickle(
                f"{source}: a chumpy object of class {self.chumpy_path} holds no array in attribute 'x'; "
                "only plain chumpy.ch.Ch values are supported (re-save the model with numpy arrays)"
            )
        return np.asarray(to_plain(value, source))


class SparseStandIn:
    """Takes the place of a scipy.sparse matrix; rebuilt with the installed scipy by to_plain()."""

    sparse_format = "csc"

    def __new__(cls, *args, **kwargs):
        return object.__new__(cls)

    def __setstate__(self, state):
        if isinstance(state, tuple) and len(state) == 2:
            state = {**(state[0] or {}), **(state[1] or {})}
        self.state = dict(state)

    def to_scipy(self, source: str):
        import scipy.sparse as sp

        st = {k: to_plain(v, source) for k, v in self.state.items()}
        shape = tuple(int(s) for s in (st.get("_shape") or st.get("shape") or ()))
        try:
            if self.sparse_format in ("csc", "csr"):
                build = sp.csc_matrix if self.sparse_format == "csc" else sp.csr_matrix
                return build((st["data"], st["indices"], st["indptr"]), shape=shape)
            if "coords" in st:  # scipy >= 1.13 coo layout
                row, col = st["coords"]
            else:
                row, col = st["row"], st["col"]
            return sp.coo_matrix((st["data"], (row, col)), shape=shape)
        except (KeyError, ValueError, TypeError) as err:
            raise UnreadablePickle(
                f"{source}: cannot rebuild a scipy.sparse {self.sparse_format} matrix from its pickled state "
                f"(keys {sorted(self.state)}): {err}"
            ) from err


def _numpy_global(submodule: str, name: str):
    """numpy.<submodule>.<name> of the installed numpy, whichever of numpy._core / numpy.core has it."""
    for package in ("numpy._core", "numpy.core"):
        try:
            return getattr(importlib.import_module(f"{package}.{submodule}"), name)
        except (ImportError, AttributeError):
            continue
    raise ImportError(f"numpy has no {submodule}.{name}")


def _latin1_encode(text: str, encoding: str = "latin1") -> bytes:
    """The one use of _codecs.encode in protocol-2 pickles: bytes stored as latin1 text."""
    if encoding not in ("latin1", "latin-1") or not isinstance(text, str):
        raise UnreadablePickle(f"_codecs.encode with encoding {encoding!r} is not allowed in a model pickle")
    return codecs.encode(text, "latin1")


_NUMPY_FUNCTIONS = {"multiarray": ("_reconstruct", "scalar"), "numeric": ("_frombuffer",)}
_BUILTINS = {"object": object, "set": set, "frozenset": frozenset, "slice": slice, "complex": complex,
             "bytearray": bytearray}
_stand_in_classes: dict[tuple[str, str], type] = {}


def _stand_in(base: type, module: str, name: str, **attrs) -> type:
    key = (module, name)
    if key not in _stand_in_classes:
        _stand_in_classes[key] = type(f"{base.__name__}[{module}.{name}]", (base,), attrs)
    return _stand_in_classes[key]


class RestrictedUnpickler(pickle.Unpickler):
    """pickle.Unpickler that resolves only allow-listed globals (see the module docstring)."""

    def __init__(self, file, source: str = "<pickle>"):
        super().__init__(file, encoding="latin1")  # FLAME pickles come from Python 2
        self.source = source

    def find_class(self, module: str, name: str):
        for package in ("numpy.core", "numpy._core"):
            for submodule, names in _NUMPY_FUNCTIONS.items():
                if module == f"{package}.{submodule}" and name in names:
                    return _numpy_global(submodule, name)
        if module == "numpy" and name in ("ndarray", "dtype"):
            return getattr(np, name)
        if module in ("__builtin__", "builtins") and name in _BUILTINS:
            return _BUILTINS[name]
        if module in ("copy_reg", "copyreg") and name == "_reconstructor":
            return copyreg._reconstructor
        if module == "_codecs" and name == "encode":
            return _latin1_encode
        if module == "collections" and name == "OrderedDict":
            return collections.OrderedDict
        if (module == "scipy.sparse" or module.startswith("scipy.sparse.")) and name in SPARSE_CLASSES:
            return _stand_in(SparseStandIn, module, name, sparse_format=name[:3])
        if (module == "chumpy" or module.startswith("chumpy.")) and name.isidentifier() and not name.startswith("__"):
            return _stand_in(ChumpyStandIn, module, name, chumpy_path=f"{module}.{name}")
        raise ForbiddenPickleGlobal(
            f"{self.source}: refusing to load: the pickle references '{module}.{name}', which is not an "
            "allowed numpy/scipy.sparse/chumpy array type (a pickle that names other globals can run code)"
        )


def to_plain(obj, source: str = "<pickle>"):
    """Replace stand-ins by numpy arrays / scipy.sparse matrices, recursively through dicts/lists/tuples."""
    if isinstance(obj, ChumpyStandIn):
        return obj.to_array(source)
    if isinstance(obj, SparseStandIn):
        return obj.to_scipy(source)
    if isinstance(obj, dict):
        return {k: to_plain(v, source) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(to_plain(v, source) for v in obj)
    return obj


def load_restricted_pickle(path: str | Path):
    """Load a pickle file with RestrictedUnpickler and return plain numpy/scipy/python objects."""
    path = Path(path)
    data = path.read_bytes()
    return loads_restricted(data, source=str(path))


def loads_restricted(data: bytes, source: str = "<pickle>"):
    try:
        obj = RestrictedUnpickler(io.BytesIO(data), source=source).load()
    except ForbiddenPickleGlobal:
        raise
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError, IndexError) as err:
        raise UnreadablePickle(f"{source}: not a readable pickle ({type(err).__name__}: {err})") from err
    return to_plain(obj, source)
