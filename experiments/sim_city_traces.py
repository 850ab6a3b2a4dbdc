"""The simulated traces the shipped network is co-trained on: four GSDC 2021 training drives' ground-truth
tracks replayed through the simulator's ``urban`` and ``suburban`` scenarios (GPS, GLONASS, Galileo, BeiDou;
C/N0 from a DLL model; street-side building masks with NLOS delays, C/N0 drops and Doppler errors), one
seed per trace, 1,200 epochs each. They teach the network what the 2021 files never carry (C/N0, other
constellations and signals); ``learned/weights/TRAINING.md`` and ``experiments/results/crossval_v3.md``
measure what they buy on real logs.

    python experiments/sim_city_traces.py --out /tmp/sim      # writes /tmp/sim/sim-<scenario>-<seed>/SimPhone/

``--held-out`` writes eight traces no network is trained on, for tuning graph settings where the learned part
acts inside the trace: four other drives' tracks (never replayed in training), seeds 101-108,
``/tmp/simho/ho-<scenario>-<seed>/SimPhone/``.

``--scenarios deep --first-seed 200`` writes the same tracks through the ``deep`` high-rise scenario (seeds
201-204; with ``--held-out``, ``--first-seed 300``: 301-304), traces that are not part of the shipped recipe.

``--carrier`` adds carrier phase (the simulator's reflected paths lengthen it as they do the code; a signal that
turns reflected or back slips, flagged), e.g.
``--held-out --scenarios deep urban --first-seed 400 --carrier --out /tmp/simcarho``: a phone's carrier in a
canyon, where the learned part met the graph's carrier-tightened track on no other tuning log; with
``--constellations GPS`` a GPS L1 + L5 phone's (the Pixel5's measurement set with broadcast orbits).
"""
from __future__ import annotations

import argparse
import os
import re
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from fusion.cli import main as cli  # noqa: E402

SHARED = Path(os.environ.get("GNSSFUSE_SHARED_DATA", REPO.parent / "shared" / "data"))
#: replayed tracks (training drives only: never a test trace's road)
TRACKS = ("2020-05-14-US-MTV-2", "2020-05-29-US-MTV-1", "2020-06-04-US-MTV-1", "2020-07-08-US-MTV-1")
SCENARIOS = ("urban", "suburban")
#: the street kinds (simulator scenarios) a written trace's collection name can carry
STREET_KINDS = ("suburban", "urban", "deep")
#: the held-out set's tracks (``--held-out``) and its first seed
HELD_OUT_TRACKS = ("2020-05-21-US-MTV-1", "2020-06-11-US-MTV-1", "2020-05-21-US-MTV-2", "2020-05-29-US-MTV-2")
HELD_OUT_SEED = 100


def street_kind(name: str | Path) -> str | None:
    """The street kind a trace written here carries in its name (``<prefix>-<scenario>-<seed>``, or a path through
    that folder), or None."""
    found = re.search(r"-(" + "|".join(STREET_KINDS) + r")-", str(name))
    return found.group(1) if found else None


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--epochs", type=int, default=1200)
    p.add_argument("--held-out", action="store_true", help="the eight held-out traces instead of the training ones")
    p.add_argument("--scenarios", nargs="+", default=list(SCENARIOS), help="simulator scenarios, each track through each")
    p.add_argument("--first-seed", type=int, default=None, help="seeds count up from the one after this "
                   f"(default 0 for training, {HELD_OUT_SEED} held out)")
    p.add_argument("--carrier", action="store_true", help="carrier phase too (not in the shipped recipe's traces)")
    p.add_argument("--broadcast-errors", action="store_true",
                   help="the range errors broadcast corrections leave, too (not in the shipped recipe's traces)")
    p.add_argument("--constellations", default=None, help="e.g. GPS: a phone of one constellation (default: all four)")
    args = p.parse_args(argv)
    tracks, seed, prefix = (HELD_OUT_TRACKS, HELD_OUT_SEED, "ho") if args.held_out else (TRACKS, 0, "sim")
    seed = seed if args.first_seed is None else args.first_seed
    for track in tracks:
        for scenario in args.scenarios:
            seed += 1
            gt = SHARED / "gsdc2021" / "trajectories" / track / "Pixel4" / "ground_truth.csv"
            rc = cli(["simulate", "--out", str(args.out), "--scenario", scenario, "--trajectory", str(gt),
                      "--seed", str(seed), "--collection", f"{prefix}-{scenario}-{seed}", "--epochs", str(args.epochs)]
                     + (["--carrier"] if args.carrier else [])
                     + (["--broadcast-errors"] if args.broadcast_errors else [])
                     + (["--constellations", args.constellations] if args.constellations else []))
            if rc:
                return rc
    return 0


if __name__ == "__main__":
    sys.exit(main())
