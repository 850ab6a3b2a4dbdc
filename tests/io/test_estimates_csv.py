"""estimates.csv is written by :func:`fusion.io.estimates.write_csv`: the bytes pandas' ``to_csv`` writes."""
from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from fusion.io.estimates import FLOAT_FORMAT, write_csv


def _pandas(frame: pd.DataFrame, path) -> bytes:
    frame.to_csv(path, index=False, float_format=FLOAT_FORMAT)
    return path.read_bytes()


FLOATS = np.array([0.0, -0.0, 1.5, -2696239.0162519, 37.395847712345678, 1e-300, 5e-324, 1.7e308, -1e22, 123456789012.5,
                   np.nan, np.inf, -np.inf, 0.1 + 0.2, 2.0 ** 53, 1e16, 9.9999999995, 99999.999995])


@pytest.mark.parametrize("frame", [
    pd.DataFrame({"gps_millis": np.arange(len(FLOATS), dtype=np.int64) * 10**12 - 5, "x_m": FLOATS,
                  "sigma_n_m": np.roll(FLOATS, 3), "bridged": np.arange(len(FLOATS)) % 2}),
    pd.DataFrame({"a": np.random.default_rng(1).normal(0, 1e6, 500), "b": np.arange(500, dtype=np.uint32),
                  "c": np.random.default_rng(2).normal(0, 1, 500).astype(np.float32)}),
    pd.DataFrame({"gps_millis": np.zeros(0, np.int64), "lat_deg": np.zeros(0)}),
    pd.DataFrame({"flag": [True, False], "name": ["a,b", 'q"'], "x": [1.0, np.nan]}),     # left to pandas
    pd.DataFrame({"x,y": [1.0, 2.0]}),
])
def test_write_csv_writes_what_pandas_writes(frame, tmp_path):
    write_csv(frame, tmp_path / "ours.csv")
    assert (tmp_path / "ours.csv").read_bytes() == _pandas(frame, tmp_path / "pandas.csv")
