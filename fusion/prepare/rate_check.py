"""Doppler and carrier phase held to the pseudoranges' own rate of change, per signal, before they reach
the graph.

Along a satellite's arc a pseudorange, its Doppler (as a range rate) and its carrier phase (as a range)
change at one rate: the satellite's range rate plus the receiver clock's drift. Over a trace, the median
ratio of the pseudoranges' rate between consecutive epochs to the Doppler's (or the carrier's) rate is 1
to a few thousandths: the Pixel5 RINEX test trace gives 1.000 (Doppler) and 0.998 (carrier) on GPS L1 and
1.000 on L5, over thousands of pairs. A writer that stores a signal's Doppler (or carrier phase) with
the opposite sign gives -1: that signal's values are reversed, with a warning and a count. Any other ratio
(a wrong wavelength or unit, values that are not what the header says) leaves that signal's Doppler (or
carrier) out, with a warning and a count, rather than handing the graph a measurement that contradicts
the pseudoranges. A signal with too few pairs to decide is left as it is.

The rates are compared as deviations from their epoch pair's median over the signal's satellites, so that a
clock rate the pseudoranges and the Doppler do not share (pseudoranges built with the clock bias estimated
anew each epoch, a Doppler that keeps the oscillator's drift) cannot pass for a scale error. Only pairs whose
deviation is large (:data:`RATE_MIN_MPS`) vote: a phone's pseudorange rate is noisy by metres per second,
satellites' range rates differ by hundreds.
"""
from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pandas as pd

from fusion.trace import count_skip

#: Consecutive epochs of one satellite and signal at most this far apart form a pair [s].
MAX_PAIR_GAP_S = 1.5
#: Pairs whose Doppler (carrier) rate deviates at least this much from their epoch pair's median vote [m/s].
RATE_MIN_MPS = 50.0
#: Fewest voting pairs that decide a signal.
MIN_PAIRS = 30
#: A median ratio within this of +1 is consistent, within this of -1 reversed.
RATIO_TOL = 0.1


def consecutive_pairs(key: np.ndarray, epoch: np.ndarray, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Row indices (i, j) (P,) of the same ``key`` (N,) at consecutive epochs ``epoch`` (N,) int at most
    :data:`MAX_PAIR_GAP_S` apart (``t_ns`` (N,) int each row's time), i before j."""
    order = np.lexsort((epoch, key))
    i, j = order[:-1], order[1:]
    gap_s = (t_ns[j] - t_ns[i]) / 1e9
    same = (key[i] == key[j]) & (epoch[j] == epoch[i] + 1) & (gap_s > 0) & (gap_s <= MAX_PAIR_GAP_S)
    return i[same], j[same]


def rate_ratio(pr_rate: np.ndarray, rate: np.ndarray) -> tuple[float, int]:
    """The median of pr_rate / rate (P,) (the rates' deviations, :func:`deviations`) over the pairs whose
    |rate| >= :data:`RATE_MIN_MPS` (finite both), and how many voted (NaN ratio where none did)."""
    vote = np.isfinite(pr_rate) & np.isfinite(rate) & (np.abs(rate) >= RATE_MIN_MPS)
    n = int(vote.sum())
    return (float(np.median(pr_rate[vote] / rate[vote])) if n else float("nan")), n


def verdict(ratio: float, n: int) -> str:
    """"ok", "reversed", "inconsistent" or "undecided" (fewer than :data:`MIN_PAIRS` voting pairs)."""
    if n < MIN_PAIRS:
        return "undecided"
    if abs(ratio - 1.0) <= RATIO_TOL:
        return "ok"
    return "reversed" if abs(ratio + 1.0) <= RATIO_TOL else "inconsistent"


def deviations(rate: np.ndarray, group: np.ndarray) -> np.ndarray:
    """(P,) each pair's rate minus the median of its group's (P,) int finite rates (NaN stays NaN)."""
    return rate - pd.Series(rate).groupby(group).transform("median").to_numpy()


def _kind_rates(rows: pd.DataFrame, i: np.ndarray, j: np.ndarray, dt: np.ndarray) -> dict[str, np.ndarray]:
    """Each kind's rate over the pairs (i, j) (P,) [m/s], NaN where a pair cannot give one: the Doppler's
    mean over the pair, the carrier's difference (both valid, no slip at j)."""
    prr = rows["prr_mps"].to_numpy(float)
    adr = rows["adr_m"].to_numpy(float)
    adr_ok = rows["adr_ok"].to_numpy(bool) & np.isfinite(adr)
    carrier_pair = adr_ok[i] & adr_ok[j] & ~rows["adr_slip"].to_numpy(bool)[j]
    return {"doppler": 0.5 * (prr[i] + prr[j]),
            "carrier": np.where(carrier_pair, (adr[j] - adr[i]) / dt, np.nan)}


def check_rates(rows: pd.DataFrame, pr: np.ndarray, epoch: np.ndarray, path: str | Path,
                skipped: dict[str, int]) -> pd.DataFrame:
    """``rows`` (a raw frame's rows, one per measurement) with each signal's Doppler (``prr_mps``) and carrier
    phase (``adr_m``) reversed where they run against the pseudoranges ``pr`` (N,) [m], or left out
    (``prr_mps`` NaN, ``adr_ok`` False) where they disagree otherwise (module docstring); ``epoch`` (N,) int
    each row's epoch. Counts ``doppler_sign_reversed:<signal>`` (and ``carrier_...``, ``..._rate_inconsistent``)
    in ``skipped`` with the number of measurements concerned, and warns naming ``path``."""
    code, names = pd.factorize(rows["signal"])                # integer codes: object compares are slow
    key = rows["sat_id"].to_numpy(np.int64) * 64 + code
    t_ns = rows["t_ns"].to_numpy(np.int64)
    i, j = consecutive_pairs(key, epoch, t_ns)
    dt = (t_ns[j] - t_ns[i]) / 1e9
    group = code[i].astype(np.int64) * (int(epoch.max(initial=0)) + 1) + epoch[i]
    pr_rate = deviations((pr[j] - pr[i]) / dt, group)
    rates = {k: deviations(v, group) for k, v in _kind_rates(rows, i, j, dt).items()}
    out = rows
    for kind, column in (("doppler", "prr_mps"), ("carrier", "adr_m")):
        for c, name in enumerate(names):
            pairs = code[i] == c
            ratio, n = rate_ratio(pr_rate[pairs], rates[kind][pairs])
            action = verdict(ratio, n)
            if action in ("ok", "undecided"):
                continue
            out = out.copy() if out is rows else out
            these = (code == c) & np.isfinite(out[column].to_numpy(float))
            if kind == "carrier":
                these &= out["adr_ok"].to_numpy(bool)
            _apply(out, kind, column, these, action)
            label = "sign_reversed" if action == "reversed" else "rate_inconsistent"
            count_skip(skipped, f"{kind}_{label}:{name}", these)
            what = ("has the opposite sign to the pseudoranges' rate: reversed" if action == "reversed"
                    else "disagrees with the pseudoranges' rate: left out")
            warnings.warn(f"{path}: the {kind} of {name} {what} (median ratio of the pseudorange rate to it "
                          f"{ratio:+.3f} over {n} epoch pairs, expected +1)", stacklevel=3)
    return out


def _apply(rows: pd.DataFrame, kind: str, column: str, these: np.ndarray, action: str) -> None:
    """Reverse, or leave out, ``kind``'s values in ``column`` at rows ``these`` (N,) bool, in place."""
    if action == "reversed":
        rows.loc[these, column] = -rows.loc[these, column]
    elif kind == "doppler":
        rows.loc[these, column] = np.nan
    else:
        rows.loc[these, "adr_ok"] = False
