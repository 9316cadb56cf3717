"""The layers of docs/ARCHITECTURE.md hold: `lint-imports` checks the layers contract of pyproject.toml
([tool.importlinter]) on every import of the package, those inside functions included."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LAYERS = "cli > apps > eval > train | prep | web > data > avatar > render > head > base > errors"


def _lint_imports() -> str:
    """The lint-imports of this interpreter's environment (a venv used without activation is not on PATH)."""
    beside = Path(sys.executable).with_name("lint-imports")
    found = str(beside) if beside.is_file() else shutil.which("lint-imports")
    if found is None:
        pytest.fail("lint-imports is not installed: `make install` installs requirements/dev.txt (import-linter)")
    return found


def test_no_module_imports_from_a_layer_above_its_own():
    result = subprocess.run([_lint_imports(), "--no-cache", "--no-logo"], cwd=ROOT, capture_output=True, text=True,
                            timeout=300)
    report = result.stdout + result.stderr
    assert result.returncode == 0, f"an import breaks the layers (docs/ARCHITECTURE.md):\n{report}"
    assert f"Layers: {LAYERS}" in " ".join(report.split()), report  # the contract checked is the one documented
    assert "1 kept, 0 broken" in report, report


def test_every_package_of_geoavatar_has_a_layer():
    """A module in no layer would be checked by nothing: each top-level module is named in the contract."""
    import pkgutil

    tomllib = pytest.importorskip("tomllib")  # Python 3.11+
    import geoavatar

    contract = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"][0]
    named = {name.strip() for layer in contract["layers"] for name in layer.replace("|", ":").split(":")}
    modules = {info.name for info in pkgutil.iter_modules(geoavatar.__path__)}
    assert modules - named == set(), f"add these to a layer of pyproject.toml's contract: {sorted(modules - named)}"
