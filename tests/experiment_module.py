"""Import a script of ``experiments/`` (not a package) as a module, for the tests of its helpers."""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

REPO = Path(__file__).resolve().parents[1]


def experiment_module(name: str) -> ModuleType:
    """``experiments/<name>.py`` loaded as the module ``name`` (registered in ``sys.modules`` first: a dataclass
    there resolves its annotations through it)."""
    spec = importlib.util.spec_from_file_location(name, REPO / "experiments" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod
