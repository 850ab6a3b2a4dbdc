"""Does the Doppler / carrier sigma check (``GraphConfig.doppler_check_window_s`` / ``carrier_check_window_s``,
``fusion/estimate/graph/consistency.py``) keep more measurements from making the graph worse?

``fused-nodnn`` on each trace with pseudoranges only, and with Doppler and carrier unchecked, with the Doppler
checked (the default) and with both checked, first as logged and then with the Doppler, the carrier or both
made worse than their stated sigmas (seeded): each
satellite's pseudorange rate gets a bias constant over 20-s blocks, N(0, ``--prr-bias`` m/s), plus white
N(0, ``--prr-white`` m/s) noise (reflected-path Doppler in a street canyon); each carrier phase a random walk
of N(0, ``--adr-step`` m) steps (multipath change every epoch). The stated sigmas are left as logged, as a
phone leaves them. The traces: the Pixel5 RINEX test trace with GPS broadcast navigation (reported, not
tuned on) and the simulated city traces of ``experiments/sim_city_traces.py`` (``--sim DIR``).

    GNSSFUSE_SHARED_DATA=../shared/data python experiments/raw_sigma_check.py --sim /tmp/sim
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
from fusion.options import load_options  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402
from fusion.trace import Trace  # noqa: E402

SHARED = Path(os.environ.get("GNSSFUSE_SHARED_DATA", REPO.parent / "shared" / "data"))
PIXEL5 = SHARED / "gsdc2021/train/2021-04-28-US-MTV-1/Pixel5"
BLOCK_S = 20.0


def degraded(trace: Trace, prr_bias: float, prr_white: float, adr_step: float, seed: int) -> Trace:
    """``trace`` with Doppler and carrier phase worse than their stated sigmas (module docstring)."""
    rng = np.random.default_rng(seed)
    E, S = trace.mask.shape
    t = (trace.t_ms - trace.t_ms[0]) / 1000.0
    block = (t // BLOCK_S).astype(int)
    sats = np.unique(trace.sat_id[trace.mask])
    bias = {int(s): rng.normal(0.0, prr_bias, block.max() + 1) for s in sats}
    per_slot = np.zeros((E, S))
    for s, b in bias.items():
        hit = trace.sat_id == s
        per_slot[hit] = b[np.broadcast_to(block[:, None], (E, S))[hit]]
    out = trace
    if trace.prr is not None:
        prr = trace.prr + np.where(trace.prr_ok, per_slot + rng.normal(0.0, prr_white, (E, S)), 0.0)
        out = replace(out, prr=prr)
    if trace.adr is not None:
        walk = {int(s): np.cumsum(rng.normal(0.0, adr_step, E)) for s in sats}
        adr = trace.adr.copy()
        for s, w in walk.items():
            hit = (trace.sat_id == s) & trace.adr_ok
            adr[hit] += np.broadcast_to(w[:, None], (E, S))[hit]
        out = replace(out, adr=adr)
    return out


def score(trace: Trace, opts: RunOptions, **graph) -> float:
    res = run_modes(trace, ["fused-nodnn"], replace(opts, graph=replace(opts.graph, **graph)))["fused-nodnn"]
    return mode_metrics(trace, res)["gsdc_score"]


def row(name: str, trace: Trace, opts: RunOptions, pr: float) -> str:
    """One table row; pr the score with pseudoranges only (which the degradations leave alone)."""
    off = score(trace, opts, doppler_check_window_s=0.0, carrier_check_window_s=0.0)
    dop = score(trace, opts, doppler_check_window_s=60.0, carrier_check_window_s=0.0)
    both = score(trace, opts, doppler_check_window_s=60.0, carrier_check_window_s=60.0)
    return (f"| {name} | {pr:.2f} | {off:.2f} | {dop:.2f} | {both:.2f} | {off / pr:.3f} | {dop / pr:.3f} | "
            f"{both / pr:.3f} |")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--sim", type=Path, help="folder of experiments/sim_city_traces.py's traces")
    p.add_argument("--prr-bias", type=float, default=1.0)
    p.add_argument("--prr-white", type=float, default=0.3)
    p.add_argument("--adr-step", type=float, default=0.1)
    args = p.parse_args(argv)
    traces = []
    if PIXEL5.is_dir():
        opts = RunOptions(signals=None, nav=(SHARED / "ephemeris/gps_nav/hour1180.21n",))
        traces.append(("Pixel5 RINEX (test trace)", load_trace(PIXEL5, min_sats=1, **load_options(opts)), opts))
    for d in sorted(args.sim.glob("sim-*")) if args.sim else []:
        opts = RunOptions(signals="all")
        traces.append((d.name, load_trace(d / "SimPhone", **load_options(opts)), opts))
    print("GSDC score [m] of fused-nodnn; ratios to pseudoranges only\n")
    print("| trace | pseudoranges only | + Doppler, carrier: unchecked | Doppler checked | both checked | "
          "unchecked / pr | Doppler checked / pr | both checked / pr |")
    print("|---|---|---|---|---|---|---|---|")
    for seed, (name, trace, opts) in enumerate(traces):
        kinds = {"as logged": None, "Doppler degraded": (args.prr_bias, args.prr_white, 0.0)}
        if trace.has_carrier:
            kinds.update({"carrier degraded": (0.0, 0.0, args.adr_step),
                          "both degraded": (args.prr_bias, args.prr_white, args.adr_step)})
        pr = score(trace, opts, use_doppler=False, use_carrier=False)
        for label, how in kinds.items():
            t = trace if how is None else degraded(trace, *how, seed)
            print(row(f"{name}, {label}", t, opts, pr), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
