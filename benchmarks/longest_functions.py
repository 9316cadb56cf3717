"""The longest functions of a source tree (#29: no god functions), by lines from `def` to the last line of the body.

    python benchmarks/longest_functions.py                 # geoavatar/ of this checkout, the 10 longest
    python benchmarks/longest_functions.py /work/main/geoavatar --top 20

Methods are named Class.method and nested functions outer.inner; a nested function's lines count in its outer
function too (the outer one is as long as it reads). Decorators are not counted, the docstring is.
"""

from __future__ import annotations

import argparse
import ast
from pathlib import Path
from typing import Iterator, NamedTuple

ROOT = Path(__file__).resolve().parents[1]


class Function(NamedTuple):
    lines: int
    path: str  # relative to the tree's parent, e.g. geoavatar/eval/evaluate.py
    line: int
    name: str  # qualified: Class.method, outer.inner


def functions(tree: ast.AST, path: str, prefix: str = "") -> Iterator[Function]:
    """Every function and method below `tree`, with its qualified name and length in lines."""
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            name = prefix + node.name
            yield Function(node.end_lineno - node.lineno + 1, path, node.lineno, name)
            yield from functions(node, path, name + ".")
        elif isinstance(node, ast.ClassDef):
            yield from functions(node, path, prefix + node.name + ".")
        else:
            yield from functions(node, path, prefix)


def longest(source: Path, top: int) -> list[Function]:
    found: list[Function] = []
    for file in sorted(source.rglob("*.py")):
        relative = file.relative_to(source.parent).as_posix()
        found.extend(functions(ast.parse(file.read_text(encoding="utf-8"), filename=str(file)), relative))
    return sorted(found, key=lambda f: (-f.lines, f.path, f.line))[:top]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source", nargs="?", type=Path, default=ROOT / "geoavatar", help="the package folder")
    parser.add_argument("--top", type=int, default=10, help="how many functions to list")
    args = parser.parse_args()
    for function in longest(args.source.resolve(), args.top):
        print(f"{function.lines:5d}  {function.path}:{function.line}  {function.name}")


if __name__ == "__main__":
    main()
