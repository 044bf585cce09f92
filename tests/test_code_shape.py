"""The shape the code keeps: no function outside the numba kernels longer than 80 lines, no training
module longer than 500."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MAX_LINES = 80  # from the def (or its first decorator) to its last line, docstring included


def _long_functions() -> list[str]:
    found = []
    for package in ("langfield", "querying", "encoders"):
        for path in sorted((ROOT / package).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    continue
                decorators = [ast.unparse(d) for d in node.decorator_list]
                if any("njit" in d for d in decorators):  # kernels stay whole for speed
                    continue
                start = min([node.lineno] + [d.lineno for d in node.decorator_list])
                if node.end_lineno - start + 1 > MAX_LINES:
                    found.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name}")
    return found


def test_no_function_outside_the_kernels_is_longer_than_80_lines() -> None:
    assert _long_functions() == []


MAX_TRAINING_MODULE_LINES = 500  # a module of langfield/training does one job (docs/layout.md)


def test_no_training_module_is_longer_than_500_lines() -> None:
    long = [
        f"{path.relative_to(ROOT)}: {n} lines"
        for path in sorted((ROOT / "langfield" / "training").rglob("*.py"))
        if (n := len(path.read_text().splitlines())) > MAX_TRAINING_MODULE_LINES
    ]
    assert long == []
