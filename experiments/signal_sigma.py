"""Should a RINEX log's pseudorange sigma depend on the signal? (Not adopted; `experiments/results/signal_sigma.md`.)

A RINEX log reports no pseudorange uncertainty, so every signal gets the same C/N0 model
(:func:`fusion.prepare.raw_trace.pr_sigma_model`: 3 m at 35 dB-Hz and above). Code-tracking noise scales with
the chip length, so a GNSS engineer would weight L5 / E5a (10.23 Mchip/s) above L1 C/A and GLONASS G1
(0.511 Mchip/s) below it. Two parts:

- ``ratios``: what the phones' own tracking loops say, truth-free: in GnssLogger logs (which report
  ``ReceivedSvTimeUncertaintyNanos``), each signal's median reported sigma over GPS L1's at the same C/N0 (5 dB-Hz
  bins, bins with at least ``--min-count`` measurements of both, weighted by the smaller count).
- ``sims``: the held-out simulated traces (``sim_city_traces.py --held-out``, and its deep ones; nothing is
  trained on them), read as a RINEX log would be (the C/N0 model instead of the reported sigma), scored by
  ``wls``, ``fused-nodnn`` and ``fused`` with every signal's model x 1 and with a factor table (``--factors``),
  mean GSDC score [m] per street kind. With ``--nav``, a RINEX log the same way (reported only, for a test trace).

    python experiments/signal_sigma.py ratios ../shared/data/android_samples/pixel6.txt \\
        ../shared/data/gsdc2023/samples/2023-09-07-18-59-us-ca/pixel7pro/gnss_log.txt
    python experiments/sim_city_traces.py --out /tmp/simho --held-out
    python experiments/sim_city_traces.py --out /tmp/simdeepho --held-out --scenarios deep --first-seed 300
    python experiments/signal_sigma.py sims /tmp/simho/*/SimPhone /tmp/simdeepho/*/SimPhone \\
        --factors GPS_L5=0.5,GAL_E5A=0.5,QZS_J5=0.5,BDS_B2A=0.5,GAL_E5B=0.5,GLO_G1=2
    python experiments/signal_sigma.py sims ../shared/data/gsdc2021/train/2021-04-28-US-MTV-1/Pixel5 \
        --nav ../shared/data/ephemeris/gps_nav/hour1180.21n
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "experiments"))

from fusion.eval.metrics import mode_metrics  # noqa: E402
from fusion.io.gnss_log import read_gnss_log  # noqa: E402
from fusion.modes import run_modes  # noqa: E402
from fusion.options import load_options, parse_signals  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.prepare.raw_trace import CN0_REF, pr_sigma_model  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402
from fusion.trace import SIGNALS, Trace  # noqa: E402
from sim_city_traces import street_kind  # noqa: E402

MODES = ("wls", "fused-nodnn", "fused")


def md(df: pd.DataFrame) -> str:
    """``df`` (index and columns) as a GitHub markdown table, 2 decimals, "-" for NaN."""
    names = [", ".join(map(str, i)) if isinstance(i, tuple) else str(i) for i in df.index]
    lines = ["| | " + " | ".join(map(str, df.columns)) + " |", "|---|" + "---|" * df.shape[1]]
    lines += [f"| {n} | " + " | ".join("-" if pd.isna(v) else f"{v:.2f}" for v in row) + " |"
              for n, row in zip(names, df.to_numpy())]
    return "\n".join(lines)


def reported_ratios(path: Path, min_count: int) -> dict[str, float]:
    """Signal -> its reported pseudorange sigma over GPS L1's at the same C/N0 (weighted over 5 dB-Hz bins)."""
    f = read_gnss_log(path).frame
    f = f[np.isfinite(f["pr_sigma_m"]) & (f["pr_sigma_m"] > 0) & (f["pr_sigma_m"] < 300) & np.isfinite(f["cn0"])]
    f = f.assign(bin=(f["cn0"] // 5) * 5)
    med = f.groupby(["signal", "bin"])["pr_sigma_m"].agg(["median", "size"])
    if "GPS_L1" not in med.index.get_level_values(0):
        return {}
    ref = med.xs("GPS_L1", level="signal")
    out = {}
    for sig in med.index.get_level_values(0).unique():
        both = med.xs(sig, level="signal").merge(ref, left_index=True, right_index=True, suffixes=("", "_ref"))
        w = np.minimum(both["size"], both["size_ref"]).where(lambda n: n >= min_count, 0)
        if w.sum() > 0:
            out[sig] = float(np.exp(np.average(np.log(both["median"] / both["median_ref"]), weights=w)))
    return out


def as_rinex(trace: Trace, factor: np.ndarray) -> Trace:
    """The trace with the C/N0 model (times ``factor`` (len(SIGNALS),) per signal) in place of the reported sigma."""
    cn0 = np.where(trace.cn0 > 0, trace.cn0, CN0_REF - 10)
    model = pr_sigma_model(cn0) * factor[trace.signal]
    return replace(trace, pr_sigma=np.where(trace.mask, model, 1.0), pr_sigma_ok=np.zeros_like(trace.mask))


def parse_factors(text: str) -> np.ndarray:
    """'GPS_L5=0.5,GLO_G1=2' -> (len(SIGNALS),) factors, 1 where not named."""
    f = np.ones(len(SIGNALS))
    for item in filter(None, (s.strip() for s in text.split(","))):
        name, value = item.split("=")
        f[SIGNALS.index(name)] = float(value)
    return f


def sims(paths: list[Path], factors: np.ndarray, nav: tuple[Path, ...] = ()) -> pd.DataFrame:
    """GSDC score per trace, mode and table (x 1 / the factors). ``nav``: a RINEX log's navigation (its
    signals then the format's default)."""
    opts = RunOptions(signals=None if nav else parse_signals("all"), nav=nav, sigma_calibration=False)
    rows = []
    for p in paths:
        trace = load_trace(p, min_sats=1, **load_options(opts))
        kind = street_kind(p.parent.name) or "log"
        for table, f in (("x 1", np.ones(len(SIGNALS))), ("factors", factors)):
            t = as_rinex(trace, f)
            res = run_modes(t, list(MODES), opts)
            rows += [{"trace": p.parent.name, "kind": kind, "table": table, "mode": m,
                      "score": mode_metrics(t, res[m])["gsdc_score"]} for m in MODES]
    return pd.DataFrame(rows)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("ratios")
    r.add_argument("logs", type=Path, nargs="+")
    r.add_argument("--min-count", type=int, default=10)
    s = sub.add_parser("sims")
    s.add_argument("traces", type=Path, nargs="+")
    s.add_argument("--nav", type=Path, nargs="+", default=(), help="navigation of RINEX logs among the traces")
    s.add_argument("--factors", default="GPS_L5=0.5,GAL_E5A=0.5,QZS_J5=0.5,BDS_B2A=0.5,GAL_E5B=0.5,GLO_G1=2")
    args = p.parse_args()
    if args.cmd == "ratios":
        table = pd.DataFrame({str(q): reported_ratios(q, args.min_count) for q in args.logs}).T
        print(md(table))
        return 0
    df = sims(args.traces, parse_factors(args.factors), tuple(args.nav))
    mean = df.pivot_table(index=["kind", "table"], columns="mode", values="score", aggfunc="mean")
    print(f"factors: {args.factors}\n")
    print(md(mean.reindex(columns=list(MODES))))
    per = df.pivot_table(index=["trace", "mode"], columns="table", values="score")
    print("\n" + md(per))
    return 0


if __name__ == "__main__":
    sys.exit(main())
