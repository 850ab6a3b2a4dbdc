"""The shipped ensemble against each of its members (and any other weights given) on the logs no network here
was trained on: ``fused`` GSDC score [m] on the Pixel5 RINEX with GPS broadcast navigation, smartLoc Berlin, and
the 2021-04-28 MTV-1 and SJC-1 Pixel4 test traces (GPS L1, as ``gnssfuse run`` reads them by default). The test
traces are reported, never used to choose.

    python experiments/shipped_members.py [--extra NAME=WEIGHTS ...]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "experiments"))

from fusion.eval.metrics import mode_metrics  # noqa: E402
from fusion.modes import run_modes, solve_initial  # noqa: E402
from fusion.options import load_options  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402
from learned.ensemble import read_manifest  # noqa: E402
from learned.infer import SHIPPED_WEIGHTS  # noqa: E402
from learned_raw_logs import LOGS as RAW_LOGS, SHARED  # noqa: E402

TRAIN = SHARED / "gsdc2021/train"
#: label -> (folder, RunOptions changes): the raw logs of learned_raw_logs.py, then the GSDC test traces
LOGS = {**RAW_LOGS, "MTV-1 Pixel4 (test)": (TRAIN / "2021-04-28-US-MTV-1/Pixel4", {}),
        "SJC-1 Pixel4 (test)": (TRAIN / "2021-04-28-US-SJC-1/Pixel4", {})}


def weights(extra: list[str]) -> dict[str, Path]:
    """label -> weights: each shipped member, the shipped ensemble, then ``NAME=PATH`` pairs."""
    out = {f"member {p.stem}": p for p in read_manifest(SHIPPED_WEIGHTS)[0]}
    out["shipped ensemble"] = SHIPPED_WEIGHTS
    for item in extra:
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            raise SystemExit(f"--extra: expected NAME=WEIGHTS, got {item!r}")
        out[name] = Path(path)
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--extra", nargs="*", default=[], help="more weights to score, NAME=PATH (.pt or .json)")
    ws = weights(p.parse_args().extra)
    scores = {}
    for log, (path, kw) in LOGS.items():
        opts = RunOptions(**kw)
        trace = load_trace(path, min_sats=1, **load_options(opts))
        wls = solve_initial(trace, opts)
        nodnn = run_modes(trace, ["fused-nodnn"], opts, wls=wls)["fused-nodnn"]
        scores[(log, "fused-nodnn")] = mode_metrics(trace, nodnn)["gsdc_score"]
        for name, w in ws.items():
            res = run_modes(trace, ["fused"], RunOptions(weights=w, **kw), wls=wls)["fused"]
            scores[(log, name)] = mode_metrics(trace, res)["gsdc_score"]
    print("| weights | " + " | ".join(LOGS) + " |")
    print("|---|" + "---|" * len(LOGS))
    for name in ["fused-nodnn", *ws]:
        print(f"| {name} | " + " | ".join(f"{scores[(log, name)]:.2f}" for log in LOGS) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
