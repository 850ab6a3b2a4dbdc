"""Benchmark: the GnssLogger reader on a long log, against a bare ``pandas.read_csv`` of the same
``Raw`` records (the floor: CSV parsing with no GNSS processing), in the same run.

The log is synthetic in length only: the 2-epoch GSDC 2023 pixel7pro fixture
(``tests/data/pixel7pro_gnss_log_2ep.txt``) repeated with advancing ``TimeNanos`` to ``--epochs``
epochs (36 records each) and written to a temporary file, so the script runs anywhere.

    python benchmarks/bench_gnss_log.py [--epochs 5000] [--repeat 3]
"""
from __future__ import annotations

import argparse
import io
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from fusion.io.gnss_log import read_gnss_log  # noqa: E402

FIXTURE = REPO / "tests" / "data" / "pixel7pro_gnss_log_2ep.txt"


def long_log(n_epochs: int) -> str:
    """The fixture's header and first epoch, repeated ``n_epochs`` times one second apart."""
    lines = FIXTURE.read_text().splitlines(keepends=True)
    head = [line for line in lines if line.startswith("#")]
    raw = [line.split(",") for line in lines if line.startswith("Raw,")]
    first = [v for v in raw if v[2] == raw[0][2]]
    out = head[:]
    for e in range(n_epochs):
        for v in first:
            out.append(",".join(v[:2] + [str(int(v[2]) + e * 10**9)] + v[3:]))
    return "".join(out)


def _median_time(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def run(quick: bool = False, epochs: int | None = None, repeat: int | None = None) -> list[dict]:
    epochs = epochs or (500 if quick else 5000)
    repeat = repeat or (1 if quick else 3)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "gnss_log.txt"
        path.write_text(long_log(epochs))
        n = len(read_gnss_log(path).frame)
        ours = _median_time(lambda: read_gnss_log(path), repeat)
        plain = _median_time(lambda: pd.read_csv(io.StringIO("\n".join(
            line[4:] for line in path.read_text().splitlines() if line.startswith("Raw,"))), header=None,
            low_memory=False), repeat)
        note = f"{epochs} epochs, {n} records, {path.stat().st_size / 1e6:.0f} MB; median of {repeat}; cpu"
    return [
        {"name": "GnssLogger read (ours)", "value": ours, "unit": "s", "note": note},
        {"name": "GnssLogger Raw lines, bare pandas.read_csv", "value": plain, "unit": "s", "note": note},
        {"name": "GnssLogger ours / bare read_csv", "value": ours / plain, "unit": "x", "note": note},
    ]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--epochs", type=int, default=5000)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    for r in run(epochs=args.epochs, repeat=args.repeat):
        print(f"{r['name']:44s} {r['value']:8.3f} {r['unit']:2s}  {r['note']}")


if __name__ == "__main__":
    main()
