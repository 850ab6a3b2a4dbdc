"""How much of each drive's miss of the 1-sigma band is its own offset: the share of |error| within the shipped
calibrated sigma per drive and axis, as it is and with the drive's mean error on that axis removed.

An analysis against the truth after the fact (nothing here feeds a model or a setting). It reads the per-trace
arrays that ``experiments/sigma_calibration.py collect`` writes (the fold networks that never saw each GSDC drive)
and applies the shipped settings (``fusion.estimate.variance_factor.DEFAULTS``, fitted on all thirteen tuning
traces), the tables' *after, final* column.

    python experiments/calibration_offset.py --out /tmp/sigcal11
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from experiments.sigma_calibration import (BAND, MODES, TESTS, base_var, calibrated_var, fmt, load,  # noqa: E402
                                           with_snapshot, within)
from fusion.estimate.variance_factor import DEFAULTS  # noqa: E402


def outside(cov: np.ndarray) -> int:
    """Axes of (3,) coverages outside :data:`BAND`."""
    return int(np.sum((cov < BAND[0]) | (cov > BAND[1])))


def mode_rows(data: dict, mode: str) -> tuple[list[str], int, int, int]:
    """Table rows of one mode over the tuning traces, and how many drive-axes miss the band as they are and
    with each drive's mean removed, of how many."""
    cal = DEFAULTS[mode]
    base = with_snapshot(data, base_var(data, mode), mode, cal.snapshot)
    rows, as_is, demeaned, n = [], 0, 0, 0
    for name, d in data.items():
        if name in TESTS:
            continue
        err = d[f"{mode}/err"]
        var = calibrated_var(d, base[name], mode, cal)
        mean = np.nanmean(err, axis=0)
        a, b = within(err, var), within(err - mean, var)
        as_is, demeaned, n = as_is + outside(a), demeaned + outside(b), n + 3
        rows.append(f"| {name} | {fmt(mean)} | {fmt(a)} | {fmt(b)} |")
    return rows, as_is, demeaned, n


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", type=Path, required=True, help="sigma_calibration.py collect's folder")
    args = p.parse_args()
    data = load(args.out)
    if not data:
        print(f"{args.out}: no collected traces (run experiments/sigma_calibration.py collect first)")
        return 1
    for mode in MODES:
        rows, as_is, demeaned, n = mode_rows(data, mode)
        print(f"## {mode}\n\n{as_is} of {n} drive-axes outside {BAND[0]:.2f}-{BAND[1]:.2f} as they are, "
              f"{demeaned} with each drive's mean error removed\n")
        print("| trace | mean error N / E / D [m] | within 1 sigma | mean removed |\n|---|---|---|---|")
        print("\n".join(rows) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
