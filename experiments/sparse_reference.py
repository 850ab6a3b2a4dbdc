"""A log whose GPS L1 is sparse, as in a street canyon with a phone that tracks every constellation: the
reference signal of the inter-signal biases (``fusion.prepare.raw_trace._reference_rows``).

A raw log's pseudoranges of every signal are put on one receiver clock by removing each signal's bias against
a reference signal, measured on the epochs the reference solves alone. The reference used to be GPS L1
whenever the log had any; now it is the signal that solves the most epochs alone (GPS L1 while it solves at
least half as many, GLONASS last). Here the Pixel5 RINEX test trace has its GPS L1 thinned at load to K
satellites per epoch (the first K rows of each epoch; every other signal untouched), in every epoch or in all
but the first N. Each row is loaded and solved with the reference of before (GPS L1 always) and of now; "fails"
gives the loader's refusal. Nothing is tuned here. GSDC score [m]; shipped weights and graph defaults.

``--header-position``: the log's header gives an approximate position (the Pixel5's gives none), as many
RINEX files do. Where no signal solves an epoch alone, the loader of before then took it for the atmosphere and
left every other signal's bias in its pseudoranges; now it refuses such a log (``before`` rows: that path).

    python experiments/sparse_reference.py [--header-position]
"""
from __future__ import annotations

import sys
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "experiments"))

import fusion.prepare.raw_trace as raw_trace  # noqa: E402
from few_satellites import PIXEL5  # noqa: E402
from pixel5_table import ORBITS  # noqa: E402
from fusion.errors import GnssfuseError  # noqa: E402
from fusion.eval.metrics import mode_metrics  # noqa: E402
from fusion.modes import run_modes, solve_initial  # noqa: E402
from fusion.options import load_options  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402

MODES = ("wls", "fused-nodnn", "fused")
#: a point in Mountain View, near the Pixel5's drive (ECEF [m]): the approximate position of --header-position
MTV = np.array([-2694685.5, -4293642.4, 3857878.9])
#: (GPS L1 satellites kept per epoch or None for all, epochs at the start left whole)
THINNING = ((None, 0), (3, 0), (2, 0), (3, 100))


def gps_l1_reference(rows: pd.DataFrame, epoch: np.ndarray) -> np.ndarray:
    """The rule of before: GPS L1 whenever the log has it, else the most common signal."""
    sig = rows["signal"].to_numpy(object)
    return sig == ("GPS_L1" if (sig == "GPS_L1").any() else pd.Series(sig).mode().iloc[0])


def no_multi_clock(sat_pos, pr, mask, group):
    """Before there was no guess with a clock per signal."""
    E, G = mask.shape[0], int(group.max()) + 1
    return np.full((E, 3), np.nan), np.full((E, G), np.nan)


def header_position_guess(guess):
    """The receiver guess of before where the reference solved no epoch alone: the header's position, and no
    clock to measure the signals' biases against (so none is removed)."""
    def receiver_guess(epoch, n_epochs, sat_pos, pr, ref, raw, sig):
        try:
            return guess(epoch, n_epochs, sat_pos, pr, ref, raw, sig)
        except GnssfuseError:
            if raw.approx_pos is None:
                raise
            return np.broadcast_to(raw.approx_pos, (n_epochs, 3)).copy(), np.full(n_epochs, np.nan)
    return receiver_guess


def thinned(select, keep: int | None, whole_first: int, header: bool = False):
    """``raw_trace._select_rows`` with GPS L1 cut to ``keep`` rows per epoch after the first ``whole_first``
    (and the header's position set to :data:`MTV` with ``header``)."""
    def select_rows(raw, nav, precise, signals, skipped):
        if header:
            raw.approx_pos = MTV
        rows = select(raw, nav, precise, signals, skipped)
        if keep is None:
            return rows
        l1 = np.flatnonzero(rows["signal"].to_numpy(object) == "GPS_L1")
        rank = rows.iloc[l1].groupby("t_ns").cumcount().to_numpy()
        t = rows["t_ns"].to_numpy()
        epochs = np.unique(t)
        late = t >= epochs[min(whole_first, epochs.size - 1)]       # whole_first 0: every epoch
        drop = np.zeros(len(rows), bool)
        drop[l1[rank >= keep]] = True
        return rows[~(drop & late)].reset_index(drop=True)
    return select_rows


def scores(opts: RunOptions) -> str:
    """The modes' GSDC scores on the Pixel5 as loaded now, or the loader's refusal."""
    try:
        trace = load_trace(PIXEL5, min_sats=1, **load_options(opts))
    except GnssfuseError as e:
        return " | ".join(["fails"] * len(MODES)) + f" | {str(e).split(': ', 1)[-1]}"
    wls = solve_initial(trace, opts)
    res = run_modes(trace, list(MODES), opts, wls=wls)
    return " | ".join(f"{mode_metrics(trace, res[m])['gsdc_score']:.2f}" for m in MODES) + " | "


def main() -> int:
    header = "--header-position" in sys.argv[1:]
    warnings.simplefilter("ignore")
    select, now, guess = raw_trace._select_rows, raw_trace._reference_rows, raw_trace._receiver_guess
    multi = raw_trace.multi_clock_positions
    print("| orbits | GPS L1 per epoch | reference | " + " | ".join(MODES) + " | refusal |")
    print("|---|---|---|" + "---|" * (len(MODES) + 1))
    try:
        for orbit, src in ORBITS.items():
            opts = RunOptions(signals=None, **src)
            for keep, first in THINNING:
                raw_trace._select_rows = thinned(select, keep, first, header)
                what = "all" if keep is None else f"{keep}" + (f" after the first {first} epochs" if first else "")
                for name, rule, then, fallback in (
                        ("GPS L1 (before)", gps_l1_reference, header_position_guess(guess), no_multi_clock),
                        ("most epochs alone, else a clock per signal (now)", now, guess, multi)):
                    raw_trace._reference_rows, raw_trace._receiver_guess = rule, then
                    raw_trace.multi_clock_positions = fallback
                    print(f"| {orbit} | {what} | {name} | {scores(opts)} |", flush=True)
    finally:
        raw_trace._select_rows, raw_trace._reference_rows, raw_trace._receiver_guess = select, now, guess
        raw_trace.multi_clock_positions = multi
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
