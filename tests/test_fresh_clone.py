"""A user's clone has no ../shared (the real test videos beside our checkout), and every test must pass or skip there.

Running the suite a second time with the folder hidden would take minutes, so instead:
- every test module reaches the shared folder only through conftest's helpers (shared_video, needs_shared_video,
  shared_dir), which skip with the reason when it is absent: no string naming the folder, no path climbing out of the
  checkout and no shared_video call at import anywhere else (read from the modules' syntax trees, so a new test
  cannot bypass them);
- the helpers skip when the folder is absent and follow GEOAVATAR_SHARED;
- the modules that use them collect, in a fresh pytest with GEOAVATAR_SHARED an empty folder, without an error.
"""

from __future__ import annotations

import ast
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

import conftest

TESTS = Path(__file__).resolve().parent
HELPERS = {"shared_video", "needs_shared_video", "shared_dir"}
EXEMPT = {"conftest.py", Path(__file__).name}  # the helpers themselves, and this check


def _levels_up(node: ast.AST) -> int | None:
    """How many folders above `__file__` a `Path(__file__).resolve().parents[k].parent...` expression points
    (0: the file itself); None when it is no such expression."""
    if isinstance(node, ast.Name):
        return 0 if node.id == "__file__" else None
    if isinstance(node, ast.Call):  # Path(__file__), .resolve(), .absolute()
        if isinstance(node.func, ast.Attribute):
            return _levels_up(node.func.value)
        return _levels_up(node.args[0]) if len(node.args) == 1 else None
    if isinstance(node, ast.Attribute) and node.attr == "parent":
        below = _levels_up(node.value)
        return None if below is None else below + 1
    if (isinstance(node, ast.Subscript) and isinstance(node.value, ast.Attribute) and node.value.attr == "parents"
            and isinstance(node.slice, ast.Constant) and isinstance(node.slice.value, int)):
        below = _levels_up(node.value.value)
        return None if below is None else below + node.slice.value + 1
    return None


def shared_data_bypasses(source: str) -> list[str]:
    """Where a test module's source reaches the shared folder other than through conftest's helpers."""
    tree = ast.parse(source)
    docstrings = {id(node.value) for node in ast.walk(tree) if isinstance(node, ast.Expr)}
    inside_functions = {id(inner) for node in ast.walk(tree)
                        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
                        for inner in ast.walk(node)}
    found = []
    for node in ast.walk(tree):
        where = f"line {getattr(node, 'lineno', '?')}"
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docstrings:
            parts = re.split(r"[/\\]", node.value)
            if "shared" in parts or ".." in parts:
                found.append(f"{where}: the path {node.value!r} (use conftest.shared_video)")
            if "GEOAVATAR_SHARED" in node.value:
                found.append(f"{where}: reads GEOAVATAR_SHARED itself (conftest does)")
        levels = _levels_up(node) if isinstance(node, (ast.Attribute, ast.Subscript)) else None
        if levels is not None and levels > 2:  # the file, tests/, the checkout: anything higher is beside it
            found.append(f"{where}: a path {levels} folders above the test file, outside the checkout")
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "shared_video"
                and id(node) not in inside_functions):
            found.append(f"{where}: shared_video at import (it skips: call it in a test or fixture)")
    return found


def test_the_check_finds_each_way_around_the_helpers():
    bypasses = [
        'VIDEO = Path(__file__).resolve().parents[2] / "shared" / "data" / "video" / "wojtek.mp4"',
        'VIDEO = Path(__file__).resolve().parents[1].parent / "data" / "video" / "wojtek.mp4"',
        'VIDEO = Path(__file__).parent.parent.parent / "x.mp4"',
        'VIDEO = Path("../shared/data/video/wojtek.mp4")',
        'ROOT = Path(os.environ.get("GEOAVATAR_SHARED", "/data"))',
        'VIDEO = shared_video("wojtek.mp4")',
    ]
    for source in bypasses:
        assert shared_data_bypasses(source), source
    fine = '''
"""Cut from ../shared's wojtek.mp4 (a docstring may say so)."""
ROOT = Path(__file__).resolve().parents[1] / "README.md"
needs_video = needs_shared_video("wojtek.mp4")
def test_it(tmp_path):
    video = shared_video("wojtek.mp4")
    (tmp_path / "shared.txt").write_text("a shared line")
'''
    assert shared_data_bypasses(fine) == []


def test_every_test_module_reaches_the_shared_folder_through_conftest():
    modules = sorted(path for path in TESTS.rglob("*.py") if path.name not in EXEMPT)
    assert len(modules) > 40
    found = {path.relative_to(TESTS).as_posix(): bypasses for path in modules
             if (bypasses := shared_data_bypasses(path.read_text()))}
    assert not found, f"tests that would fail without ../shared (use conftest's shared_video): {found}"


def test_the_helpers_skip_when_the_folder_is_absent(tmp_path, monkeypatch):
    monkeypatch.setattr(conftest, "SHARED", tmp_path / "nowhere")
    with pytest.raises(pytest.skip.Exception, match=r"nowhere/data/video/wojtek\.mp4 is absent"):
        conftest.shared_video("wojtek.mp4")
    assert conftest.shared_video("wojtek.mp4", required=False) is None
    mark = conftest.needs_shared_video("wojtek.mp4")
    assert mark.args == (True,) and "is absent" in mark.kwargs["reason"]

    present = tmp_path / "here" / "data" / "video" / "wojtek.mp4"
    present.parent.mkdir(parents=True)
    present.write_bytes(b"")
    monkeypatch.setattr(conftest, "SHARED", tmp_path / "here")
    assert conftest.shared_video("wojtek.mp4") == present
    assert conftest.needs_shared_video("wojtek.mp4").args == (False,)


def _modules_using_the_helpers() -> list[str]:
    return sorted(path.name for path in TESTS.glob("test_*.py")
                  if path.name not in EXEMPT and HELPERS & set(re.findall(r"\w+", path.read_text())))


def test_the_shared_data_tests_collect_without_the_folder(tmp_path):
    """GEOAVATAR_SHARED reaches a fresh pytest's conftest, and the modules that use shared data import and collect
    without it (a mark or a path built at import would show here)."""
    modules = _modules_using_the_helpers()
    assert {"test_prepare.py", "test_drive.py"} <= set(modules)
    empty = (tmp_path / "empty").resolve()
    empty.mkdir()
    env = {**os.environ, "GEOAVATAR_SHARED": str(empty), "PYTHONDONTWRITEBYTECODE": "1"}
    collect = subprocess.run([sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "--co", *modules],
                             cwd=TESTS, env=env, capture_output=True, text=True, timeout=300)
    summary = collect.stdout.strip().splitlines()[-1] if collect.stdout.strip() else ""
    # a collection error exits non-zero; a module skipped at import would add "skipped" to the summary
    assert collect.returncode == 0 and re.search(r"\d+ tests collected in", summary) and "skipped" not in summary, (
        collect.stdout[-4000:] + collect.stderr[-2000:])
    assert f"shared test data: {empty} (0 videos); the tests that need them skip" in collect.stdout
