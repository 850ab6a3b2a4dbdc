"""The shipped ensemble's pass over a trace (``Corrector.predict``): epochs in chunks of like satellite counts,
each padded to its own largest set (``learned.infer.INFER_CHUNK`` = 512, as shipped), against every epoch in
one chunk padded to the trace's largest (the code before, 4096), in the same process, best of ``repeats``.

Traces: the Pixel5 RINEX trace with SP3/CLK (GPS, GLONASS, Galileo: 17-30 signals an epoch) where
``../shared/data`` (or ``$GNSSFUSE_SHARED_DATA``) exists, and the shipped GSDC Pixel4 trace (GPS L1).

    PYTHONPATH=. python benchmarks/bench_infer.py [--quick]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import learned.infer as infer  # noqa: E402
from benchmarks.bench_pixel5 import PRECISE, TRACE as PIXEL5  # noqa: E402
from fusion.modes import solve_initial  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.prepare.raw_load import RawSources  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402

SHIPPED = REPO / "data/gsdc2021/train/2021-04-28-US-MTV-1/Pixel4"


def traces() -> list[tuple[str, object]]:
    """(name, Trace) pairs: the shipped trace, and the Pixel5 with SP3/CLK where the shared data is."""
    out = [("shipped GSDC Pixel4, GPS L1", load_trace(SHIPPED))]
    if PIXEL5.exists():
        sources = RawSources(sp3=PRECISE / "COD0MGXFIN_20211180000_01D_05M_ORB.SP3",
                             clk=PRECISE / "COD0MGXFIN_20211180000_01D_30S_CLK.CLK")
        out.append(("Pixel5 RINEX, SP3/CLK, all signals", load_trace(PIXEL5, signals=None, raw_sources=sources)))
    return out


def best_time(corrector, trace, wls, chunk: int, repeats: int) -> float:
    """Best of ``repeats`` wall times [s] of one ensemble pass with ``INFER_CHUNK`` = ``chunk``."""
    shipped, infer.INFER_CHUNK = infer.INFER_CHUNK, chunk
    try:
        times = []
        for _ in range(repeats):
            t = time.perf_counter()
            corrector.predict(trace, wls.pos, wls.valid)
            times.append(time.perf_counter() - t)
        return min(times)
    finally:
        infer.INFER_CHUNK = shipped


def run(quick: bool = False) -> list[dict]:
    """benchmarks/README.md entry point; ``quick``: 2 repeats instead of 5."""
    repeats = 2 if quick else 5
    corrector = infer.Corrector.load(None)
    n_nets = len(getattr(corrector, "members", [corrector]))      # a single network has no members
    recs = []
    for name, trace in traces():
        wls = solve_initial(trace, RunOptions())
        old = best_time(corrector, trace, wls, 4096, repeats)
        new = best_time(corrector, trace, wls, infer.INFER_CHUNK, repeats)
        note = (f"{name}, {trace.n_epochs} epochs, shipped ensemble ({n_nets} networks), CPU, best of {repeats}, "
                "same process")
        recs += [{"name": "ensemble pass, chunks by satellite count", "value": round(new, 4), "unit": "s",
                  "note": note},
                 {"name": "ensemble pass, one chunk (before)", "value": round(old, 4), "unit": "s", "note": note},
                 {"name": "ensemble pass, chunks by count / one chunk", "value": round(new / old, 3), "unit": "x",
                  "note": note}]
    return recs


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true")
    for r in run(p.parse_args().quick):
        print(f"{r['name']:45s} {r['value']:>8} {r['unit']:2s}  {r['note']}")


if __name__ == "__main__":
    main()
