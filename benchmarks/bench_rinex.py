"""Benchmark: our vectorised RINEX 3 observation reader against a plain per-line Python parser
(and, with ``--georinex``, against georinex when it is importable; it is not a dependency).

File: the GSDC 2021 Pixel5 phone log (``2021-04-28-US-MTV-1/Pixel5/supplemental/Pixel5_GnssLog.21o``,
4 MB, 1985 epochs) from ``../shared/data`` (or ``$GNSSFUSE_SHARED_DATA``); without it the 5-epoch
test fixture ``tests/data/pixel5_head.21o`` (figures then say so). Every ratio comes from timings
taken in the same process. The per-line baseline reads every observation with ``float()`` into a
dict per satellite line: the work a straightforward reader does, without building our frame.

    python benchmarks/bench_rinex.py [--repeat N] [--georinex]
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from fusion.io.rinex_obs import read_rinex_obs  # noqa: E402

SHARED = Path(os.environ.get("GNSSFUSE_SHARED_DATA", REPO.parent / "shared" / "data"))
PIXEL5 = SHARED / "gsdc2021/train/2021-04-28-US-MTV-1/Pixel5/supplemental/Pixel5_GnssLog.21o"
FIXTURE = REPO / "tests" / "data" / "pixel5_head.21o"


def per_line_parse(path: Path) -> int:
    """The baseline: one Python pass, ``float()`` per value. Returns the number of values read."""
    lines = path.read_text().splitlines()
    end = next(i for i, line in enumerate(lines) if "END OF HEADER" in line)
    types, sys_letter = {}, ""
    for line in lines[:end]:
        if line[60:].strip() == "SYS / # / OBS TYPES":
            sys_letter = line[0] if line[0] != " " else sys_letter
            types.setdefault(sys_letter, []).extend(line[7:60].split())
    n = 0
    for line in lines[end + 1:]:
        if line.startswith(">"):
            continue
        obs = {}
        for i, t in enumerate(types.get(line[0], ())):
            text = line[3 + 16 * i: 3 + 16 * i + 14].strip()
            if text:
                obs[t] = float(text)
        n += len(obs)
    return n


def _median_time(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def run(quick: bool = False, repeat: int | None = None, georinex: bool = False) -> list[dict]:
    path = PIXEL5 if PIXEL5.is_file() else FIXTURE
    repeat = repeat or (3 if quick else 10)
    raw = read_rinex_obs(path)  # warm-up (imports, page cache)
    ours = _median_time(lambda: read_rinex_obs(path), repeat)
    base = _median_time(lambda: per_line_parse(path), max(1, repeat // 3))
    note = (f"{path.name}: {path.stat().st_size / 1e6:.1f} MB, {raw.n_epochs} epochs, {len(raw.frame)} rows; "
            f"median of {repeat}; cpu")
    records = [
        {"name": "RINEX obs read (ours)", "value": ours, "unit": "s", "note": note},
        {"name": "RINEX obs per-line float() parse (baseline)", "value": base, "unit": "s", "note": note},
        {"name": "RINEX obs speed-up vs per-line parse", "value": base / ours, "unit": "x", "note": note},
    ]
    if georinex:
        records += _georinex(path, ours, note)
    return records


def _georinex(path: Path, ours: float, note: str) -> list[dict]:
    try:
        import georinex  # noqa: F401  (optional, never a dependency)
    except ImportError:
        print("georinex not importable: skipped")
        return []
    t0 = time.perf_counter()
    georinex.load(path)
    gr = time.perf_counter() - t0
    return [{"name": "RINEX obs read (georinex.load, once)", "value": gr, "unit": "s", "note": note},
            {"name": "RINEX obs speed-up vs georinex", "value": gr / ours, "unit": "x", "note": note}]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=10)
    ap.add_argument("--georinex", action="store_true", help="also time georinex.load once (slow)")
    args = ap.parse_args()
    for r in run(repeat=args.repeat, georinex=args.georinex):
        print(f"{r['name']:48s} {r['value']:10.3f} {r['unit']:3s}  {r['note']}")


if __name__ == "__main__":
    main()
