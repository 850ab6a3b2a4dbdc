"""GTSAM's singular-system exceptions as our one-line errors (fusion.estimate.graph.solve_errors)."""
from __future__ import annotations

import numpy as np

from fusion.errors import GeometryError
from fusion.estimate.graph.solve_errors import geometry_error
from fusion.trace import Trace, empty_trace


def test_the_error_names_the_epoch_its_variable_and_its_measurements():
    kw = empty_trace(3, 6, name="drive/phone")
    kw["mask"][:, :5] = True
    kw["t_ms"] = np.array([0, 1000, 2000])
    err = geometry_error(Trace(**kw), RuntimeError("Indeterminant linear system detected near variable\nSymbol: c1"))
    assert isinstance(err, GeometryError)
    assert str(err).startswith("drive/phone: epoch 1 (t_ms=1000): the graph cannot determine the receiver clock")
    assert "at 5 measured slots" in str(err) and "or an input far off its model" in str(err)
    assert str(geometry_error(Trace(**kw), RuntimeError("boom"))) == "drive/phone: factor graph solve failed: boom"
