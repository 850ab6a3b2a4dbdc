"""Adaptation without ground truth on a phone in a street canyon: the Pixel5 RINEX test trace (or smartLoc, a
tuning log) seen from the simulator's streets (``canyon_on_phone.py``), adapted on its own canyon log, then scored.

No log here is a phone in a dense city with truth, and the hidden phones of issue 20 are exactly that: this is
the nearest stand-in for "adapted on each phone's own log". For each street layout the canyon trace is handed
to ``gnssfuse adapt``'s code without its truth (the truth only placed the streets, as in
``canyon_on_phone.py``), then ``fused`` with the shipped and the adapted weights and ``fused-nodnn`` are scored
against the truth. Prints a Markdown table like ``adapt_eval.py``'s.

    python experiments/adapt_canyon.py [--seeds 0 1 2] [--height 30 100 --width 12 25] [--sp3]
    python experiments/adapt_canyon.py --log smartloc [--seeds 0 1 2] [--height 30 100 --width 12 25]

The Pixel5 is a test trace: its rows are reported, never chosen on. smartLoc (a u-blox in Berlin's Potsdamer
Platz, GPS + GLONASS, no network trained on it) is a tuning log: streets laid over a real canyon, without Doppler
or carrier.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "experiments"))

import learned.adapt as adapt_module  # noqa: E402
from adapt_eval import SMARTLOC, decision_words, graph_words  # noqa: E402
from canyon_on_phone import in_canyon  # noqa: E402
from few_satellites import NAV, PIXEL5  # noqa: E402
from pixel5_table import ORBITS  # noqa: E402
from fusion.eval.metrics import mode_metrics  # noqa: E402
from fusion.modes import run_modes  # noqa: E402
from fusion.options import load_options  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402
from fusion.sim.canyon import CanyonModel  # noqa: E402
from learned.adapt import AdaptConfig  # noqa: E402
from learned.infer import SHIPPED_WEIGHTS  # noqa: E402


def adapted_on(trace, opts: RunOptions, folder: Path) -> tuple[Path, dict]:
    """Adapt the shipped weights on ``trace`` with its truth removed; (the adapted weights, the record).
    ``learned.adapt.load_log`` is swapped for the in-memory log while it runs (the teacher loads by path)."""
    blind = replace(trace, truth=None)
    real = adapt_module.load_log
    adapt_module.load_log = lambda path, o, max_epochs=None: blind
    try:
        out = folder / "w.json"
        return out, adapt_module.adapt([trace.name], out, weights=SHIPPED_WEIGHTS, cfg=AdaptConfig(), opts=opts)
    finally:
        adapt_module.load_log = real


def row(trace, opts: RunOptions) -> dict:
    """Scores of ``fused-nodnn``, ``fused`` shipped and adapted on ``trace`` [m], the decision and the times."""
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        w, rec = adapted_on(trace, opts, Path(tmp))
        t_adapt = time.perf_counter() - t0
        shipped = run_modes(trace, ["fused-nodnn", "fused"], opts)
        adapted = run_modes(trace, ["fused"], replace(opts, weights=w))["fused"]
    s = {k: mode_metrics(trace, r)["gsdc_score"] for k, r in shipped.items()}
    s["adapted"] = mode_metrics(trace, adapted)["gsdc_score"]
    return dict(s, decision=decision_words(rec), graph=graph_words(rec),
                heldout=" -> ".join("-" if v is None else f"{v:.3f}" for v in rec["heldout"]), t=t_adapt)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--height", type=float, nargs=2, default=(15.0, 60.0), help="building heights [m], lo hi")
    p.add_argument("--width", type=float, nargs=2, default=(15.0, 35.0), help="street widths [m], lo hi")
    p.add_argument("--sp3", action="store_true", help="multi-GNSS SP3/CLK instead of broadcast GPS (the Pixel5)")
    p.add_argument("--log", choices=("pixel5", "smartloc"), default="pixel5", help="the log laid in the streets")
    a = p.parse_args()
    if a.sp3 and a.log == "smartloc":
        p.error("--sp3 is for the Pixel5: smartLoc's pseudoranges come with satellite positions")
    if a.log == "smartloc":
        orbits = {}                               # its pseudoranges come with satellite positions
    else:
        orbits = ORBITS["CODE SP3/CLK, multi-GNSS (+ hour1180.21n ionosphere)"] if a.sp3 else {"nav": (NAV,)}
    opts = RunOptions(signals=None, **orbits)     # None: every signal the orbits cover, as canyon_on_phone.py
    trace = load_trace(PIXEL5 if a.log == "pixel5" else SMARTLOC, min_sats=1, **load_options(opts))
    model = CanyonModel(height_m=tuple(a.height), width_m=tuple(a.width))
    print(f"| {'Pixel5 RINEX' if a.log == 'pixel5' else 'smartLoc'} | fused-nodnn | fused, shipped "
          "| fused, adapted | adapted / shipped | decision | held-out criterion [m] by epoch | graph check [m] "
          "| adapt [s] |")
    print("|---|---|---|---|---|---|---|---|---|")
    ratios = []
    for seed in a.seeds:
        canyon, _ = in_canyon(trace, model, seed)
        r = row(canyon, opts)
        ratios.append(r["adapted"] / r["fused"])
        print(f"| canyon, streets seed {seed} | {r['fused-nodnn']:.2f} | {r['fused']:.2f} | {r['adapted']:.2f} | "
              f"{ratios[-1]:.3f} | {r['decision']} | {r['heldout']} | {r['graph']} | {r['t']:.0f} |", flush=True)
    print(f"\nmean adapted / shipped: {sum(ratios) / len(ratios):.3f}; worst {max(ratios):.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
