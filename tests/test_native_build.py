"""The native extensions' build keys: what makes a cached build reusable."""

import shutil
import types

import pytest
from torch.utils import cpp_extension

from geoavatar import native
from geoavatar.avatar import fused
from geoavatar.render import cpu_backend


def test_building_one_extension_leaves_the_key_of_the_next_unchanged(monkeypatch, tmp_path):
    """torch's loader appends its libraries to the flag lists it is handed: the module's flags must not be those
    lists, or the second extension a process loads gets another key than in a process that loads it first."""
    if shutil.which("c++") is None or not cpp_extension.is_ninja_available():
        pytest.skip("needs a C++ compiler and ninja, as the real build does")
    monkeypatch.setenv("GEOAVATAR_EXT_CACHE", str(tmp_path))

    def load_like_torch(name, sources, extra_cflags, extra_ldflags, build_directory, verbose):
        extra_ldflags += ["-L/torch/lib", "-lc10", "-ltorch_cpu", "-ltorch", "-ltorch_python"]
        return types.ModuleType(name)

    monkeypatch.setattr(cpp_extension, "load", load_like_torch)
    rasterizer_key = native.build_key(cpu_backend._EXTENSION)
    native._build(fused._EXTENSION, verbose=False)
    native._build(fused._EXTENSION, verbose=False)
    assert native.build_key(cpu_backend._EXTENSION) == rasterizer_key
    assert native.LDFLAGS == ("-fopenmp",)


def test_two_environments_with_the_same_versions_build_in_two_folders(monkeypatch):
    """ninja rebuilds when its build command changes, and the command names the environment's torch and Python
    headers: a venv and a fresh clone's venv sharing one folder rebuilt it each time the other had used it."""
    key = native.build_key(cpu_backend._EXTENSION)
    other = {**native.sysconfig.get_paths(), "include": "/elsewhere/include/python3"}
    monkeypatch.setattr(native.sysconfig, "get_paths", lambda: other)
    assert native.build_key(cpu_backend._EXTENSION) != key
