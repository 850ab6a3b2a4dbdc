"""Per-epoch series helpers (fusion.estimate.graph.series)."""
from __future__ import annotations

import numpy as np

from fusion.estimate.graph.series import where_solved


def test_an_unsolved_epoch_takes_the_fallback_and_a_solved_one_keeps_its_position():
    pos = np.array([[1.0, 2.0, 3.0], [np.nan, 0.0, 0.0], [4.0, 5.0, 6.0]])
    other = np.full((3, 3), -1.0)
    np.testing.assert_array_equal(where_solved(pos, other), [[1, 2, 3], [-1, -1, -1], [4, 5, 6]])
    np.testing.assert_array_equal(where_solved(pos, 0.0)[1], [0, 0, 0])
