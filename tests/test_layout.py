"""The library stays readable: no module of sagonline/ over 400 lines, no function over 80 lines
without a reason ("Why one function:") in its docstring, and no import running back up from the
fitting package into the datasets."""

from __future__ import annotations

import ast
import subprocess
import sys

from tests.fixtures import ROOT

PACKAGE = ROOT / "sagonline"


def test_no_module_over_400_lines():
    long = {
        str(p.relative_to(ROOT)): n
        for p in PACKAGE.rglob("*.py")
        if (n := p.read_text().count("\n")) > 400
    }
    assert not long, long


def test_long_functions_say_why():
    silent = []
    for p in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = node.end_lineno - node.lineno + 1
                doc = ast.get_docstring(node) or ""
                if length > 80 and "Why one function:" not in doc:
                    silent.append(f"{p.relative_to(ROOT)}:{node.lineno} {node.name} ({length})")
    assert not silent, silent


def test_fitting_does_not_depend_on_the_datasets():
    code = "import sys, sagonline.fitting; print([m for m in sys.modules if 'datasets' in m])"
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr
