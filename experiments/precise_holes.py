"""How far a precise orbit interpolated across a hole in its SP3 file is off: epochs cut out of the middle of the
CODE 5-min file (`../shared/data/ephemeris/precise/`) and interpolated back by the run's own Lagrange
interpolation (:func:`fusion.nav.precise._lagrange`, its hole limit lifted), against the positions cut out; the
worst and the median satellite. The figures behind :data:`fusion.nav.precise.MAX_STEP_S`.

    python experiments/precise_holes.py
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "experiments"))

import fusion.nav.precise as precise  # noqa: E402
from few_satellites import SHARED  # noqa: E402
from fusion.io.sp3 import read_sp3  # noqa: E402

SP3 = SHARED / "ephemeris/precise/COD0MGXFIN_20211180000_01D_05M_ORB.SP3"


def hole_errors(orb, k: int) -> np.ndarray:
    """(N,) each whole-day satellite's largest 3-D error [m] over the k - 1 epochs cut at the file's middle (a step
    of k spacings)."""
    mid = orb.t_ms.size // 2
    keep = np.r_[0:mid, mid + k - 1:orb.t_ms.size]
    t, pos = orb.t_ms[keep], orb.pos[keep]
    t_ref, t_q = (t - t[0]) * 1e-3, (orb.t_ms[mid:mid + k - 1] - t[0]) * 1e-3
    whole = np.flatnonzero(np.isfinite(orb.pos).all(axis=(0, 2)))
    return np.array([np.linalg.norm(precise._lagrange(t, t_ref, pos, np.full(t_q.size, c), t_q)
                                    - orb.pos[mid:mid + k - 1, c], axis=1).max() for c in whole])


def main() -> int:
    orb = read_sp3(SP3)
    spacing_min = int(np.median(np.diff(orb.t_ms)) // 60_000)
    precise.MAX_STEP_S = np.inf                     # the limit under test, lifted
    print(f"{SP3.name}: {orb.sats.size} satellites, {spacing_min}-min spacing\n")
    print("| hole (step) [min] | worst satellite [m] | median satellite [m] |\n|---|---|---|")
    for k in (2, 3, 4, 6, 8, 12, 18, 30):
        e = hole_errors(orb, k)
        print(f"| {k * spacing_min} | {e.max():.3f} | {np.median(e):.3f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
