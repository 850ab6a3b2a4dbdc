"""Pseudorange sigmas held to what the pseudoranges themselves show (``GraphConfig.pseudorange_check_window_s``),
measured: per trace, the GSDC score (mean of horizontal p50 and p95) [m] of ``fused-nodnn`` (and of ``fused``
where the shipped network never saw the trace) with the check off and at each window, and the share of
pseudoranges whose sigma it raised.

    GNSSFUSE_SHARED_DATA=../shared/data python experiments/pseudorange_check.py [--sim DIR] [--windows 0,60,300]

Decide on the twelve GSDC training drives (pseudoranges only), smartLoc (a u-blox in a Berlin canyon) and
the simulated city traces (``--sim``: folders written by ``experiments/sim_city_traces.py``, Doppler and
carrier included); the test traces (Pixel5 RINEX with GPS broadcast navigation, MTV-1 and SJC-1 Pixel4) are
reported (``--test``), never chosen on.
"""
from __future__ import annotations

import argparse
import os
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from fusion.eval.metrics import mode_metrics  # noqa: E402
from fusion.modes import run_modes  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.prepare.raw_load import RawSources  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402

SHARED = Path(os.environ.get("GNSSFUSE_SHARED_DATA", REPO.parent / "shared" / "data"))
TRAIN = SHARED / "gsdc2021/train"
NAV = (SHARED / "ephemeris/gps_nav/hour1180.21n",)
TEST = {"2021-04-28-US-MTV-1/Pixel5": NAV, "2021-04-28-US-MTV-1/Pixel4": (), "2021-04-28-US-SJC-1/Pixel4": ()}


def logs(sim: Path | None, test: bool) -> list[tuple[str, Path, tuple, bool]]:
    """(name, folder, navigation files, whether to run ``fused`` too: the shipped network never saw it)."""
    out = [(d.parent.name, d, (), False) for d in sorted(TRAIN.glob("2020-*/Pixel4"))]
    out.append(("smartLoc Berlin", SHARED / "smartloc/Berlin_Potsdamer_Platz", (), True))
    if sim is not None:
        out += [(d.parent.name, d, (), False) for d in sorted(sim.glob("*/SimPhone"))]
    if test:
        out += [(name, TRAIN / name, nav, True) for name, nav in TEST.items()]
    return out


def scores(path: Path, nav: tuple, windows: list[float], fused: bool) -> list[tuple[float, float | None, float]]:
    """Per window: (fused-nodnn score, fused score or None, share of pseudoranges raised)."""
    gsdc = path.is_relative_to(TRAIN) and not nav
    trace = load_trace(path, signals=None if not gsdc else ("GPS_L1",), min_sats=1, raw_sources=RawSources(nav))
    out = []
    for w in windows:
        opts = RunOptions(signals=None, nav=nav)
        opts = replace(opts, graph=replace(opts.graph, pseudorange_check_window_s=w))
        res = run_modes(trace, ["fused-nodnn", "fused"] if fused else ["fused-nodnn"], opts)
        nod = res["fused-nodnn"]
        raised = nod.info.get("pseudorange_sigmas_raised", 0) / max(int(trace.mask.sum()), 1)
        out.append((mode_metrics(trace, nod)["gsdc_score"],
                    mode_metrics(trace, res["fused"])["gsdc_score"] if fused else None, raised))
    return out


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--sim", type=Path, default=None)
    p.add_argument("--test", action="store_true")
    p.add_argument("--windows", default="0,60,300")
    a = p.parse_args()
    windows = [float(w) for w in a.windows.split(",")]
    head = " | ".join(f"window {w:g} s" for w in windows)
    print(f"| trace | fused-nodnn: {head} | fused: {head} | raised |")
    print("|---|" + "---|" * (2 * len(windows) + 1))
    ratios = {w: [] for w in windows[1:]}
    for name, path, nav, fused in logs(a.sim, a.test):
        r = scores(path, nav, windows, fused)
        nod = " | ".join(f"{x[0]:.2f}" for x in r)
        fu = " | ".join("-" if x[1] is None else f"{x[1]:.2f}" for x in r)
        print(f"| {name} | {nod} | {fu} | " + " / ".join(f"{x[2]:.0%}" for x in r[1:]) + " |", flush=True)
        if name not in TEST:
            for w, x in zip(windows[1:], r[1:]):
                ratios[w].append(x[0] / r[0][0])
    for w, v in ratios.items():
        print(f"\nfused-nodnn, window {w:g} s / off over the tuning traces: mean {np.mean(v):.3f}, "
              f"best {min(v):.3f}, worst {max(v):.3f}, better on {sum(x < 1 for x in v)} of {len(v)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
