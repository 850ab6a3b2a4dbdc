"""Cut the smartLoc Berlin drive in time into two drives of the same format: the first part (time stamps
before ``--cut-a`` s) to train on, the rest (from ``--cut-b`` s) to evaluate on, with a gap between so that
no epoch of one lies next to an epoch of the other.

Used by ``experiments/results/smartloc_training.md``: what a network learns from a real street canyon, measured
on streets of the same drive it did not see. Both parts keep the drive's name, so the reader finds its start
time (:data:`fusion.prepare.smartloc.DRIVE_START_GPS`).

    python experiments/smartloc_split.py --out /tmp/slsplit      # -> /tmp/slsplit/{A,B}/Berlin_Potsdamer_Platz
"""
from __future__ import annotations

import argparse
import os
import shutil
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("GNSSFUSE_SHARED_DATA", REPO.parent / "shared" / "data"))
DRIVE = "Berlin_Potsdamer_Platz"


def split_file(src: Path, a: Path, b: Path, cut_a: float, cut_b: float) -> tuple[int, int]:
    """Copy each line of a libRSF text file (time stamp in its second field) to ``a`` (before ``cut_a``) or
    ``b`` (from ``cut_b``); lines between are dropped. Returns the lines written to each."""
    n_a = n_b = 0
    with src.open() as f, a.open("w") as fa, b.open("w") as fb:
        for line in f:
            fields = line.split()
            t = float(fields[1]) if len(fields) > 1 else float("nan")
            if t < cut_a:
                fa.write(line)
                n_a += 1
            elif t >= cut_b:
                fb.write(line)
                n_b += 1
    return n_a, n_b


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--cut-a", type=float, default=165.0, help="part A: time stamps before this [s]")
    p.add_argument("--cut-b", type=float, default=175.0, help="part B: time stamps from this [s]")
    args = p.parse_args()
    src = SHARED / "smartloc" / DRIVE
    if not src.is_dir():
        print(f"{src}: not found (set GNSSFUSE_SHARED_DATA)")
        return 1
    for part in ("A", "B"):
        (args.out / part / DRIVE).mkdir(parents=True, exist_ok=True)
        shutil.copy(src / "readme.txt", args.out / part / DRIVE / "readme.txt")
    for kind in ("Input", "GT"):
        name = f"{DRIVE}_{kind}.txt"
        n_a, n_b = split_file(src / name, args.out / "A" / DRIVE / name, args.out / "B" / DRIVE / name,
                              args.cut_a, args.cut_b)
        print(f"{name}: {n_a} lines to A, {n_b} to B")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
