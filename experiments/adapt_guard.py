"""What a checkpoint's network is allowed to act on in the Pixel5 RINEX trace (GPS broadcast navigation),
at the point where the ``fused`` mode asks it: slots with a learned sigma, the guard's trust per epoch,
and the slots of signals the network cannot read. No truth is read.

    python experiments/adapt_guard.py shipped W.pt ...
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from fusion.estimate.graph.fuse import learned_guess  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.prepare.raw_load import RawSources  # noqa: E402
from fusion.modes import solve_initial  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402
from learned.infer import Corrector  # noqa: E402

SHARED = Path(os.environ.get("GNSSFUSE_SHARED_DATA", REPO.parent / "shared" / "data"))
TRACE = SHARED / "gsdc2021/train/2021-04-28-US-MTV-1/Pixel5"
NAV = (SHARED / "ephemeris/gps_nav/hour1180.21n",)


def main(weights: list[str]) -> int:
    opts = RunOptions(signals=None, nav=NAV)
    trace = load_trace(TRACE, signals=None, truth="none", min_sats=1, raw_sources=RawSources(NAV))
    at = learned_guess(trace, solve_initial(trace, opts), opts)
    ok = trace.n_sats >= 1
    for w in weights:
        c = Corrector.load(None if w == "shipped" else w)
        p = c.predict(trace, at, ok)
        _, mask, unseen, _ = c._asked(trace, at, ok, c.features.elev_mask_deg)
        q = np.nanquantile(p.trust, [0.1, 0.5, 0.9])
        print(f"{w}: learned sigma on {int(np.isfinite(p.sigma).sum())} of {int(mask.sum())} slots it reads; "
              f"trust p10/p50/p90 {q[0]:.2f}/{q[1]:.2f}/{q[2]:.2f}, max {np.nanmax(p.trust):.2f}, "
              f"{int((p.trust[p.valid] == 0).sum())} of {int(p.valid.sum())} epochs 0; "
              f"{int(unseen.sum())} slots of signals it cannot read")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:] or ["shipped"]))
