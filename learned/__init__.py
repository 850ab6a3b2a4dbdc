"""gnssfuse's learned side: the set-transformer correction (features, model, training, inference),
its GTSAM factors, and the ``dnn`` / ``fused`` modes. Imports ``fusion``; ``fusion`` never imports it.

Public API (imported lazily)::

    from learned import Corrector, learned_prior_factor, learned_pseudorange_factors
"""
from __future__ import annotations

import importlib

_PUBLIC = {
    "Corrector": "learned.infer", "learned_prior_factor": "learned.factor",
    "learned_prior_factors": "learned.factor", "learned_pose_translation_factor": "learned.factor",
    "learned_pseudorange_factors": "learned.factor",
}
__all__ = sorted(_PUBLIC)


def __getattr__(name: str):
    if name in _PUBLIC:
        return getattr(importlib.import_module(_PUBLIC[name]), name)
    raise AttributeError(f"module 'learned' has no attribute {name!r}")
