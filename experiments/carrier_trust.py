"""Which carrier phase the graph should trust in a street canyon: the simulator's city traces with carrier.

A reflected signal's carrier follows the reflected path. Its length changes as the car turns or the street
changes, and nothing in the carrier itself says so; an unflagged reflection's time-differenced carrier is a few
of its sigmas off, each epoch, where the robust loss does not reach. The variants below weight the carrier by
the satellite's C/N0 (``GraphConfig.tdcp_cn0_ref_dbhz``) and, in ``fused``, by the learned head's distrust of
the same satellite's pseudorange (``GraphConfig.learned_carrier_power``). The last row removes the reflected
and bent signals' carrier by the simulator's own labels: a diagnosis of what is at stake, never an estimator.

Tuning logs only: the held-out simulated traces (no network trained on them) written with carrier phase,

    python experiments/sim_city_traces.py --held-out --scenarios deep urban --first-seed 400 --carrier --out /tmp/simcarho
    python experiments/sim_city_traces.py --held-out --scenarios suburban --first-seed 500 --carrier --out /tmp/simcarsub
    python experiments/sim_city_traces.py --held-out --scenarios suburban urban --first-seed 600 --carrier \
        --constellations GPS --out /tmp/simgps
    python experiments/carrier_trust.py /tmp/simcarho/*/SimPhone /tmp/simcarsub/*/SimPhone /tmp/simgps/*/SimPhone \
        [--jobs 2]

GSDC score [m] of ``fused-nodnn`` and ``fused`` (shipped weights), mean per street kind ("(GPS)": the phone of
GPS L1 + L5 alone).
"""
from __future__ import annotations

import argparse
import sys
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "experiments"))

from fusion.estimate.graph.config import GraphConfig  # noqa: E402
from fusion.eval.metrics import mode_metrics  # noqa: E402
from fusion.gpstime import gps_ms_to_unix_ms  # noqa: E402
from fusion.modes import run_modes, solve_initial  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402
from fusion.trace import SIGNALS  # noqa: E402
from sim_city_traces import street_kind  # noqa: E402

BEFORE = dict(tdcp_cn0_ref_dbhz=0.0, learned_carrier_power=0.0, learned_carrier_knee=1.0)
#: name -> GraphConfig settings (the shipped defaults for the rest)
VARIANTS = {
    "pseudoranges only": dict(use_doppler=False, use_carrier=False),
    "+ Doppler": dict(use_carrier=False),
    "+ Doppler + carrier, before": BEFORE,
    "+ carrier's C/N0 (ref 40 dB-Hz)": dict(BEFORE, tdcp_cn0_ref_dbhz=40.0),
    "+ learned distrust (power 4)": dict(BEFORE, learned_carrier_power=4.0, learned_carrier_min_count=0),
    "+ learned distrust (power 8)": dict(BEFORE, learned_carrier_power=8.0, learned_carrier_min_count=0),
    "+ learned distrust (power 8, knee 2)": dict(BEFORE, learned_carrier_power=8.0, learned_carrier_knee=2.0,
                                                 learned_carrier_min_count=0),
    "+ learned distrust (power 8, from 12 differences)": dict(BEFORE, learned_carrier_power=8.0,
                                                              learned_carrier_min_count=12),
    "shipped defaults": {},
    "shipped, reflected carrier removed (labels: diagnosis)": {},
}
ORACLE = "shipped, reflected carrier removed (labels: diagnosis)"
MODES = ("fused-nodnn", "fused")


def reflected_slots(trace, folder: Path) -> np.ndarray:
    """(E,S) bool: the slots the simulator's labels call reflected or bent (sim_labels.csv)."""
    lab = pd.read_csv(folder / "sim_labels.csv")
    lab = lab[lab.Class != "LOS"]
    bad = pd.DataFrame({"t": lab.utcTimeMillis.astype(np.int64),
                        "sat": lab.ConstellationType.astype(np.int64) * 1000 + lab.Svid.astype(np.int64),
                        "sig": lab.SignalType.map(SIGNALS.index).astype(np.int64), "bad": True})
    e, s = np.nonzero(trace.mask)
    slots = pd.DataFrame({"t": gps_ms_to_unix_ms(trace.t_ms)[e].astype(np.int64),
                          "sat": trace.sat_id[e, s].astype(np.int64), "sig": trace.signal[e, s].astype(np.int64)})
    hit = slots.merge(bad, on=["t", "sat", "sig"], how="left")["bad"].fillna(False).to_numpy(bool)
    out = np.zeros(trace.mask.shape, bool)
    out[e, s] = hit
    return out


def score_trace(folder: str) -> list[dict]:
    """One row per variant and mode: the trace's GSDC score [m]."""
    trace = load_trace(folder, signals="all")
    kind = street_kind(folder)
    gps_only = all(SIGNALS[i].startswith("GPS") for i in np.unique(trace.signal[trace.mask]))
    opts0 = RunOptions(signals=None)
    wls = solve_initial(trace, opts0)
    rows = []
    for name, settings in VARIANTS.items():
        tr = trace
        if name == ORACLE:
            tr = replace(trace, adr_ok=trace.adr_ok & ~reflected_slots(trace, Path(folder)))
        opts = replace(opts0, graph=replace(GraphConfig(), **settings))
        res = run_modes(tr, list(MODES), opts, wls)
        for m in MODES:
            rows.append(dict(trace=Path(folder).parent.name, variant=name,
                             kind=(kind or "-") + (" (GPS)" if gps_only else ""),
                             mode=m, score=mode_metrics(tr, res[m])["gsdc_score"]))
    return rows


def markdown(df: pd.DataFrame) -> str:
    """A frame as a markdown table (its index the first column; column tuples joined by a space)."""
    cols = [" ".join(map(str, c)) if isinstance(c, tuple) else str(c) for c in df.columns]
    lines = ["| " + " | ".join(["", *cols]) + " |", "|" + "---|" * (len(cols) + 1)]
    lines += ["| " + " | ".join([str(i), *(f"{v:.3f}" for v in row)]) + " |" for i, row in zip(df.index, df.values)]
    return "\n".join(lines)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("traces", nargs="+", help="simulated trace folders written with --carrier")
    p.add_argument("--jobs", type=int, default=1)
    p.add_argument("--csv", type=Path, default=None, help="also write every trace's scores here")
    args = p.parse_args()
    with ProcessPoolExecutor(args.jobs) as pool:
        rows = [r for part in pool.map(score_trace, args.traces) for r in part]
    df = pd.DataFrame(rows)
    if args.csv:
        df.to_csv(args.csv, index=False)
    print(markdown(df.pivot_table(index="variant", columns=["kind", "mode"], values="score", sort=False)))
    per = df[df.variant.isin(["+ Doppler", "+ Doppler + carrier, before", "shipped defaults"])]
    print()
    print(markdown(per.pivot_table(index="trace", columns=["variant", "mode"], values="score", sort=False)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
