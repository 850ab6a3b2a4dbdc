"""The package layout's rules: fusion never imports learned, functions stay short, the public API holds."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: The issue's ceiling for a function's length; the code stays well under it.
MAX_FUNCTION_LINES = 80


def _modules(package: str) -> list[Path]:
    return sorted((ROOT / package).rglob("*.py"))


def _imported(tree: ast.AST) -> set[str]:
    """Every module name an import statement anywhere in ``tree`` names (inside functions too)."""
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
    return names


def test_fusion_never_imports_learned():
    offenders = [f"{p.relative_to(ROOT)}: {m}" for p in _modules("fusion")
                 for m in _imported(ast.parse(p.read_text()))
                 if m == "learned" or m.startswith("learned.")]
    assert not offenders, offenders


def test_fusion_names_learned_modes_by_string_only():
    from fusion.modes import MODES
    learned = {name: target for name, target in MODES.items() if str(target).startswith("learned.")}
    assert {"dnn", "fused"} <= set(learned) and all(isinstance(t, str) and ":" in t for t in learned.values())


@pytest.mark.parametrize("package", ["fusion", "learned"])
def test_no_long_functions(package):
    long = []
    for p in _modules(package):
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_FUNCTION_LINES:
                    long.append(f"{p.relative_to(ROOT)}:{node.lineno} {node.name} ({n} lines)")
    assert not long, long


def test_public_api():
    from fusion import RunOptions, load_trace, run_modes
    from learned import Corrector, learned_prior_factor, learned_pseudorange_factors
    assert all(callable(f) for f in (RunOptions, load_trace, run_modes, Corrector, learned_prior_factor,
                                     learned_pseudorange_factors))


def test_io_only_parses():
    """fusion/io reads and writes files: it imports nothing that computes (estimators, the layer that
    turns records into a Trace, the simulator, evaluation, the application layer). Besides the shared
    vocabulary (trace, run types, geometry, time), the navigation record types it fills
    (fusion.nav.orbits.GpsNav, fusion.nav.glonass) are the one other thing it takes."""
    above = ("fusion.prepare", "fusion.estimate", "fusion.sim", "fusion.eval", "fusion.modes", "fusion.cli",
             "fusion.evaluate", "fusion.parallel")
    allowed_nav = {"fusion.nav.orbits", "fusion.nav.glonass"}
    offenders = [f"{p.relative_to(ROOT)}: {m}" for p in _modules("fusion/io")
                 for m in _imported(ast.parse(p.read_text()))
                 if m.startswith(above) or (m.startswith("fusion.nav") and m not in allowed_nav)]
    assert not offenders, offenders
