"""Raw receiver observations (:class:`~fusion.io.raw.RawObs`) + navigation -> :class:`~fusion.trace.Trace`.

Per row (epoch x satellite x signal): the transmit time is the receiver's time tag minus the
pseudorange's flight time (``t_rx - pr / c``, then minus the satellite clock); the satellite state
comes from broadcast navigation or SP3 (+ CLK). The pseudorange is corrected for the satellite
clock (relativity included, group delay removed: ``+ c dt_sv``), the Klobuchar ionosphere
(scaled to the carrier) and the Saastamoinen troposphere; the Doppler for the satellite clock
drift (``+ c d(dt_sv)/dt``) and the carrier phase for the satellite clock (``+ c dt_sv``), as the
:class:`~fusion.trace.Trace` docstring asks. The atmosphere needs the receiver's position and the
satellites' elevations: a batched WLS on the clock-corrected pseudoranges gives them (epochs it
cannot solve take the nearest solved epoch's position).

The receiver's time tag is the phone's estimate of GPS time and may be off by its clock bias,
but the transmit time ``t_tag - pr / c`` is not: the pseudorange carries the same bias, so the
satellite states need no second pass at a clock-corrected time.
Rows of a satellite without ephemeris at that time, without a pseudorange, or of unselected
signals are dropped and counted in ``Trace.skipped``.
"""
from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pandas as pd

from fusion.errors import DataError
from fusion.estimate.wls import solve_wls_arrays
from fusion.geometry import C_LIGHT, ecef2geodetic, elevation_azimuth, line_of_sight
from fusion.gpstime import WEEK_S, format_gps_ms
from fusion.io.discover import SYSTEM_NAMES
from fusion.io.clean import epochs_with_enough_rows
from fusion.io.raw import RawObs
from fusion.nav.atmosphere import iono_scale, klobuchar_l1, tropo_delay
from fusion.nav.precise import MAX_STEP_S, N_LAGRANGE, precise_states
from fusion.nav.sat_states import SIGNAL_CLASS, broadcast_states
from fusion.prepare.multi_clock import multi_clock_positions
from fusion.prepare.rate_check import check_rates
from fusion.trace import (SIGNALS, Trace, cn0_sigma_factor, count_skip, flags_since_previous, pack_rows,
                          resolve_signals)

#: Pseudorange sigma when the file gives none: SIGMA_PR_M at C/N0 >= CN0_REF, growing as
#: 10^((CN0_REF - cn0) / 20) below it (amplitude-noise scaling of code tracking), capped.
SIGMA_PR_M, CN0_REF, SIGMA_PR_MAX_M = 3.0, 35.0, 100.0
#: Doppler and carrier-phase sigmas when the file gives none [m/s], [m].
SIGMA_PRR_MPS, SIGMA_ADR_M = 0.1, 0.01
#: GPS L1 stays the reference signal (:func:`_reference_rows`) while it can solve at least this share of the
#: epochs the best other signal can solve alone: the reference of every log before, where it can serve.
REF_SHARE = 0.5
#: Plausible raw pseudoranges [m] (GNSS orbits: 19,000-26,000 km slant ranges, GEO up to 42,000 km).
_PR_RANGE_M = (1.0e7, 5.0e7)


def pr_sigma_model(cn0: np.ndarray) -> np.ndarray:
    """(...) pseudorange sigma [m] when the file reports none: :data:`SIGMA_PR_M` at C/N0 >= :data:`CN0_REF`,
    growing as 10^((CN0_REF - C/N0) / 20) below it, capped at :data:`SIGMA_PR_MAX_M`. cn0 (...) [dB-Hz]."""
    return np.minimum(SIGMA_PR_M * cn0_sigma_factor(cn0, CN0_REF), SIGMA_PR_MAX_M)


def raw_to_trace(raw: RawObs, nav=None, *, signals=None, precise=None, name: str | None = None,
                 min_sats: int = 1, iono_free: bool = False) -> Trace:
    """Build a :class:`Trace` from raw observations.

    nav:     :class:`~fusion.io.rinex_nav.Navigation` (broadcast states, Klobuchar coefficients).
    precise: optional :class:`~fusion.nav.precise.PreciseOrbits` used instead of ``nav`` for
             satellite states (``nav`` then only supplies the ionosphere, and may be None).
    signals: names to keep; None keeps every signal whose constellation has ephemerides.
    min_sats: epochs with fewer rows are dropped and counted.
    iono_free: where a satellite has an L1-class and a second-frequency pseudorange, use their
             ionosphere-free combination (:func:`_iono_free`) instead of both.
    """
    if nav is None and precise is None:
        raise DataError(f"{raw.path}: no navigation data (pass broadcast navigation or SP3 orbits)")
    skipped = dict(raw.skipped)
    rows = _select_rows(raw, nav, precise, signals, skipped)
    st = _states(rows, nav, precise, skipped)
    _check_coverage(raw, rows, st["ok"], nav, precise)
    _check_clock_coverage(rows, precise)
    count_skip(skipped, "rows_no_ephemeris", ~st["ok"])
    rows, st = rows[st["ok"]].reset_index(drop=True), {k: v[st["ok"]] for k, v in st.items()}
    rows["iono_free"], rows["sigma_scale"] = False, 1.0
    if iono_free:
        rows, st = _iono_free(rows, st, skipped)
    rows, st, epoch, t_ns = _epochs(rows, st, min_sats, skipped, raw)
    pr = rows["pr_m"].to_numpy() + C_LIGHT * st["clock_s"]
    rows = check_rates(rows, pr, epoch, raw.path, skipped)
    ref = _reference_rows(rows, epoch)
    rx, clock_m = _receiver_guess(epoch, t_ns.size, st["pos"], pr, ref, raw, rows["signal"].to_numpy(object))
    el, az = _elev_az(st["pos"], rx[epoch])
    if getattr(nav, "klobuchar", None) is None:
        # SP3/CLK carry no ionosphere; uncorrected, L1 ranges are metres long, more at low elevation
        warnings.warn(f"{raw.path}: no ionosphere model (no Klobuchar coefficients: pass a RINEX "
                      "navigation file with --nav); pseudoranges keep their ionospheric delay", stacklevel=2)
    pr = pr - _atmosphere(rows, nav, rx[epoch], el, az)
    pr = pr - _inter_signal_bias(rows, st["pos"], pr, rx[epoch], clock_m[epoch], ref, epoch)
    cols = _columns(rows, st, pr)
    packed = pack_rows(epoch, t_ns.size, cols)
    mask = packed.pop("mask")
    reset, gap = _events_since_previous(raw.frame, t_ns)
    packed["adr_slip"] |= gap[:, None]
    t_ms = np.round(t_ns / 1e6).astype(np.int64)
    return Trace(t_ms=t_ms, mask=mask, clock_reset=reset, name=name or raw.path.stem, skipped=skipped, **packed)


def default_signals(nav, precise) -> tuple[str, ...]:
    """Every signal whose constellation has ephemerides in ``nav`` / ``precise``."""
    letters = precise.systems() if precise is not None else nav.systems()
    prefix = {"G": "GPS", "R": "GLO", "E": "GAL", "C": "BDS", "J": "QZS"}
    return tuple(s for s in SIGNALS if any(s.startswith(prefix[c]) for c in letters))


def _select_rows(raw: RawObs, nav, precise, signals, skipped: dict[str, int]) -> pd.DataFrame:
    """Rows of selected signals with a plausible pseudorange."""
    f = raw.frame
    covered = default_signals(nav, precise)
    names = covered if signals is None else tuple(SIGNALS[i] for i in resolve_signals(signals))
    keep = np.ones(len(f), bool) if signals is None else f["signal"].isin(names).to_numpy()
    count_skip(skipped, "rows_signal_not_selected", ~keep)
    # a constellation the navigation lacks, chosen or not: said as such, not as a file of the wrong day
    bare = keep & ~f["signal"].isin(covered).to_numpy()
    count_skip(skipped, "rows_constellation_without_navigation", bare)
    _warn_without_navigation(raw, f["const"].to_numpy(object)[bare], nav, precise)
    keep = keep & ~bare
    pr = f["pr_m"].to_numpy()
    good = np.isfinite(pr) & (pr > _PR_RANGE_M[0]) & (pr < _PR_RANGE_M[1])
    count_skip(skipped, "rows_no_pseudorange", keep & ~good)
    # the ionosphere scales with the carrier: GLONASS rows of an unknown channel have none
    known = np.isfinite(f["carrier_hz"].to_numpy())
    count_skip(skipped, "rows_unknown_carrier_frequency", keep & good & ~known)
    rows = f[keep & good & known].reset_index(drop=True)
    if rows.empty:
        have = ", ".join(SYSTEM_NAMES.get(x, x) for x in sorted(_systems(nav, precise)))
        raise DataError(f"{raw.path}: no pseudorange of signal(s) {', '.join(names)} (navigation covers {have})")
    return rows


def _warn_without_navigation(raw: RawObs, letters: np.ndarray, nav, precise) -> None:
    """Say which constellations the log measured but no navigation covers. letters: (M,) of those rows."""
    if letters.size == 0:
        return
    names, counts = np.unique(letters.astype(str), return_counts=True)   # as str: sorts 3x faster than objects
    what = ", ".join(f"{SYSTEM_NAMES.get(n, n)} ({c} measurements)" for n, c in zip(names, counts))
    have = ", ".join(SYSTEM_NAMES[s] for s in sorted(_systems(nav, precise)))
    warnings.warn(f"{raw.path}: no navigation for {what}; the navigation covers {have}: pass a "
                  "navigation file of those constellations (--nav FILE, any RINEX name) to use them", stacklevel=3)


def _systems(nav, precise) -> set[str]:
    return precise.systems() if precise is not None else nav.systems()


def _check_clock_coverage(rows: pd.DataFrame, precise) -> None:
    """Warn where a clock file given beside the SP3 misses some of the log: the SP3's own clock column (its
    coarser samples) serves those measurements, as it does without a clock file."""
    clk = None if precise is None else precise.clk
    if clk is None or not len(rows):
        return
    t = rows["t_ns"].to_numpy(np.int64) // 1_000_000
    outside = (t < clk.t_ms[0]) | (t > clk.t_ms[-1])
    if outside.any():
        warnings.warn(f"{clk.source}: the clock file covers {format_gps_ms(int(clk.t_ms[0]))[:19]} to "
                      f"{format_gps_ms(int(clk.t_ms[-1]))[:19]} GPS time; {int(outside.sum())} of {outside.size} "
                      "measurements outside it take the SP3 file's own clocks", stacklevel=3)


def _check_coverage(raw: RawObs, rows: pd.DataFrame, ok: np.ndarray, nav, precise) -> None:
    """Refuse a log no navigation record covers, naming the log's and the navigation's dates
    (a file of the wrong day is the usual cause); warn when most rows lack ephemerides."""
    if ok.mean() >= 0.5:
        return
    t = rows["t_ns"].to_numpy(np.int64) // 1_000_000
    log_span = f"{format_gps_ms(int(t.min()))[:19]} to {format_gps_ms(int(t.max()))[:19]} GPS time"
    span = _navigation_span(nav, precise)
    cover = "no usable records" if span is None else \
        f"{format_gps_ms(span[0])[:19]} to {format_gps_ms(span[1])[:19]}"
    files = ", ".join(Path(f).name for f in (nav.sources if nav is not None and precise is None else
                                             [precise.sp3.source]))
    msg = f"{raw.path}: the log runs {log_span} but the navigation ({files}) covers {cover}"
    if precise is None and nav is not None and len(nav.file_spans) > 1:     # which file is of which day
        msg += " (" + "; ".join(f"{Path(f).name}: {nav.records_text(f)}" for f in nav.file_spans) + ")"
    inside = span is not None and span[0] <= t.min() and t.max() <= span[1]
    if not ok.any() and precise is not None and inside:
        clocks = precise.clk is not None or (precise.sp3.clock is not None and np.isfinite(precise.sp3.clock).any())
        raise DataError(msg + (f": too few epochs ({N_LAGRANGE} around each time), or a hole of over "
                               f"{MAX_STEP_S / 60:g} minutes, to interpolate its orbits at the log's times" if clocks
                               else ": it holds no satellite clock (pass a clock file, --clk)"))
    if not ok.any():
        raise DataError(msg + ": pass a navigation file of the log's day (--nav FILE)")
    warnings.warn(f"{msg}: {int((~ok).sum())} of {ok.size} measurements have no ephemeris", stacklevel=3)


def _navigation_span(nav, precise) -> tuple[int, int] | None:
    if precise is not None:
        t = precise.sp3.t_ms
        return (int(t.min()), int(t.max())) if t.size else None
    return nav.span_ms()


def _states(rows: pd.DataFrame, nav, precise, skipped: dict[str, int] | None = None) -> dict[str, np.ndarray]:
    """(N,) satellite states at each row's transmit time (two passes: the second at the transmit
    time corrected by the first pass's satellite clock, which moves the satellite ~4 m per ms)."""
    t_ns = rows["t_ns"].to_numpy(np.int64)
    t_ms = t_ns // 1_000_000
    base = (t_ns - t_ms * 1_000_000) * 1e-9 - rows["pr_m"].to_numpy() / C_LIGHT
    sat_id, sig = rows["sat_id"].to_numpy(), pd.Index(SIGNALS).get_indexer(rows["signal"]).astype(np.int8)
    fn = (lambda dt, sk=None: precise_states(precise, sat_id, sig, t_ms, dt, nav)) if precise is not None else \
         (lambda dt, sk=None: broadcast_states(nav, sat_id, sig, t_ms, dt, sk))
    st = fn(base)
    st = fn(base - st["clock_s"], skipped)
    st["signal"] = sig
    return st


def _iono_free(rows: pd.DataFrame, st: dict[str, np.ndarray], skipped: dict[str, int]):
    """Rows with L1-class + second-frequency pairs replaced by their ionosphere-free combination.

    Per (epoch, satellite) with an L1-class row (L1 / E1 / B1I / J1) and a second-frequency row
    (L2 / E5b / B2I first, else L5 / E5a), the second row's pseudorange becomes
    ``(f1^2 P1 - f2^2 P2) / (f1^2 - f2^2)`` of the clock-corrected pair (each with its own group
    delay removed, so the combination carries the broadcast clock's own reference), flagged
    ``iono_free`` (no Klobuchar), its sigma propagated; it keeps its signal index, Doppler and
    carrier, so the combined rows form their own bias group. The L1 row of each pair is dropped
    (counted ``rows_combined_iono_free``); second-frequency rows without a partner are dropped too
    (``rows_iono_free_unpaired``) so that group holds combinations only. GLONASS (one frequency
    here) and unpaired L1 rows stay as they are. rows: (N,) frame; st: (N,) satellite states.
    """
    cls = SIGNAL_CLASS[st["signal"]]
    glo = rows["const"].to_numpy(object) == "R"
    df = pd.DataFrame({"t": rows["t_ns"].to_numpy(np.int64), "sat": rows["sat_id"].to_numpy(np.int64),
                       "cls": cls, "i": np.arange(len(rows))})
    first = df[(cls == 0) & ~glo].drop_duplicates(["t", "sat"]).set_index(["t", "sat"])["i"].rename("i1")
    second = df[cls > 0].sort_values("cls", ascending=False, kind="stable").drop_duplicates(["t", "sat"])
    pair = first.to_frame().join(second.set_index(["t", "sat"])["i"].rename("i2"), how="inner")
    i1, i2 = pair["i1"].to_numpy(), pair["i2"].to_numpy()
    f = rows["carrier_hz"].to_numpy()
    p = rows["pr_m"].to_numpy() + C_LIGHT * st["clock_s"]
    a = f[i1] ** 2 / (f[i1] ** 2 - f[i2] ** 2)
    b = a - 1.0                                      # f2^2 / (f1^2 - f2^2)
    rows = rows.copy()
    rows.loc[i2, "pr_m"] = a * p[i1] - b * p[i2] - C_LIGHT * st["clock_s"][i2]
    sig = rows["pr_sigma_m"].to_numpy()
    rows.loc[i2, "pr_sigma_m"] = np.hypot(a * sig[i1], b * sig[i2])
    rows.loc[i2, "iono_free"] = True
    rows["sigma_scale"] = 1.0
    rows.loc[i2, "sigma_scale"] = np.hypot(a, b)    # for the C/N0 model sigma where the file has none
    keep = np.ones(len(rows), bool)
    keep[i1] = False
    count_skip(skipped, "rows_combined_iono_free", i1.size)
    unpaired = (cls > 0) & ~rows["iono_free"].to_numpy(bool)
    count_skip(skipped, "rows_iono_free_unpaired", unpaired)
    keep &= ~unpaired
    return rows[keep].reset_index(drop=True), {k: v[keep] for k, v in st.items()}


def _epochs(rows: pd.DataFrame, st: dict, min_sats: int, skipped: dict[str, int], raw: RawObs):
    """Epoch index per row, dropping (and counting) epochs with fewer than ``min_sats`` rows."""
    keep, epoch, t_ns = epochs_with_enough_rows(rows["t_ns"].to_numpy(np.int64), min_sats, skipped, raw.path,
                                                "measurements with ephemerides")
    return rows[keep].reset_index(drop=True), {k: v[keep] for k, v in st.items()}, epoch, t_ns


def _events_since_previous(frame: pd.DataFrame, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(E,) clock resets and (E,) gaps of the kept epochs ``t_ns`` (E,) measured against every epoch
    of the file: a reset on an epoch dropped later (too few satellites, no ephemeris) still
    happened before the next kept one, and a dropped epoch may hide a cycle slip."""
    t_all, inv = np.unique(frame["t_ns"].to_numpy(np.int64), return_inverse=True)
    reset = np.zeros(t_all.size, bool)
    np.logical_or.at(reset, inv, frame["clock_reset"].to_numpy(bool))
    return flags_since_previous(reset, np.searchsorted(t_all, t_ns))


def _reference_rows(rows: pd.DataFrame, epoch: np.ndarray) -> np.ndarray:
    """(N,) bool: rows of the reference signal, whose receiver clock the other signals' inter-signal biases
    are measured against: the one that can solve the most epochs alone (four or more of its satellites in an
    epoch), GPS L1 while it can solve at least :data:`REF_SHARE` of that many, GLONASS only when no other
    signal can (each of its FDMA channels has a bias of its own). With GPS L1 as the only reference, a canyon
    log whose GPS L1 rarely shows four satellites got no inter-signal biases, or no receiver guess, however
    many satellites the other constellations showed (``experiments/sparse_reference.py``). epoch (N,): each
    row's epoch index."""
    sig = rows["signal"].to_numpy(object)
    per_epoch = pd.Series(1, index=pd.MultiIndex.from_arrays([sig, epoch])).groupby(level=[0, 1]).size()
    solvable = (per_epoch >= 4).groupby(level=0).sum()
    if solvable.max() == 0:
        # no signal solves an epoch alone: the receiver guess takes a clock per signal (_receiver_guess)
        ref = "GPS_L1" if (sig == "GPS_L1").any() else pd.Series(sig).mode().iloc[0]
        return sig == ref
    best = solvable.drop([s for s in solvable.index if str(s).startswith("GLO")], errors="ignore")
    best = best if best.max() > 0 else solvable
    ref = best.idxmax()
    if solvable.get("GPS_L1", 0) >= REF_SHARE * best.max():
        ref = "GPS_L1"
    return sig == ref


def _receiver_guess(epoch: np.ndarray, n_epochs: int, sat_pos: np.ndarray, pr: np.ndarray,
                    ref: np.ndarray, raw: RawObs, sig: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(E, 3) receiver position and (E,) reference clock [m] (NaN where unsolved) from a robust WLS on the
    reference signal's clock-corrected pseudoranges (one clock: the other signals carry unknown
    inter-signal biases); where the reference solves no epoch alone, from a clock per signal
    (:mod:`fusion.prepare.multi_clock`); unsolved epochs take the nearest solved one's position.

    epoch: (N,) epoch per row; sat_pos: (N, 3); pr: (N,); ref: (N,) bool reference-signal rows; sig (N,) each
    row's signal.
    """
    packed = pack_rows(epoch[ref], n_epochs, {"sat_pos": sat_pos[ref], "pr": pr[ref]})
    w = solve_wls_arrays(packed["sat_pos"], packed["pr"], packed["mask"], elev_mask_deg=10.0, robust=True)
    pos, clock = w.pos, w.clock_m                    # NaN where not solved
    if not w.valid.any() and not ref.all():
        codes = pd.factorize(sig)[0]
        packed = pack_rows(epoch, n_epochs, {"sat_pos": sat_pos, "pr": pr, "group": codes})
        pos, clocks = multi_clock_positions(packed["sat_pos"], packed["pr"], packed["mask"], packed["group"])
        clock = clocks[:, codes[np.flatnonzero(ref)[0]]]
    good = np.flatnonzero(np.isfinite(pos).all(axis=1))
    if good.size == 0:
        if raw.approx_pos is None:
            raise DataError(f"{raw.path}: no epoch could be solved for the approximate receiver position "
                            f"the atmosphere models need{_why_unsolved(epoch[ref], n_epochs)}")
        if not ref.all():
            # the header's position serves the atmosphere, but the other signals' biases (metres to hundreds
            # on phones) would stay in their pseudoranges: kilometres of error, not a solution
            raise DataError(f"{raw.path}: no epoch could be solved, by one signal alone or with a clock per "
                            "signal, so the biases between its signals cannot be measured")
        return np.broadcast_to(raw.approx_pos, (n_epochs, 3)).copy(), np.full(n_epochs, np.nan)
    near = good[np.clip(np.searchsorted(good, np.arange(n_epochs)), 0, good.size - 1)]
    prev = good[np.clip(np.searchsorted(good, np.arange(n_epochs)) - 1, 0, good.size - 1)]
    near = np.where(np.abs(prev - np.arange(n_epochs)) < np.abs(near - np.arange(n_epochs)), prev, near)
    return pos[near], clock


def _why_unsolved(epoch: np.ndarray, n_epochs: int) -> str:
    """What the reference signal's rows, their epochs (N,), say of why no epoch solved."""
    most = int(np.bincount(epoch, minlength=n_epochs).max()) if epoch.size else 0
    if most < 4:
        return f": no epoch has 4 satellites on one signal (at most {most})"
    return ": the pseudoranges agree on no position (a wrong observation type in the header, or corrupt values?)"


def _inter_signal_bias(rows: pd.DataFrame, sat_pos: np.ndarray, pr: np.ndarray, rx: np.ndarray,
                       clock_m: np.ndarray, ref: np.ndarray, epoch: np.ndarray) -> np.ndarray:
    """(N,) inter-signal range bias [m] of each row: per signal (and GLONASS channel), the median
    over the trace of ``pr - range - reference clock``; 0 on reference rows. Like GSDC's
    ``isrbM``, it lets one receiver clock serve every signal in WLS (phones show L5 / E5a and
    GLONASS biases of metres to hundreds of metres); the graph still estimates what is left.

    The reference clock is the median of the reference rows' ``pr - range`` in each epoch, on
    the atmosphere-corrected ranges: the WLS clock (``clock_m``, solved before the troposphere
    was removed) carries the troposphere's common part, metres that would otherwise land in
    every other signal's bias.

    sat_pos, rx: (N, 3); pr, clock_m: (N,) (NaN clock where the epoch was not solved); ref: (N,);
    epoch: (N,) epoch index of each row.
    """
    rng, _ = line_of_sight(sat_pos[:, None, :], rx)
    d = pr - rng[:, 0]
    clock = pd.Series(np.where(ref & np.isfinite(clock_m), d, np.nan)).groupby(epoch).transform("median").to_numpy()
    resid = d - clock
    groups = [rows["signal"].to_numpy(object), rows["glo_k"].to_numpy()]       # per signal and GLONASS channel
    bias = pd.Series(np.where(ref, np.nan, resid)).groupby(groups).transform("median").to_numpy()
    return np.where(ref | ~np.isfinite(bias), 0.0, bias)


def _elev_az(sat_pos: np.ndarray, rx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N,) elevation and azimuth [deg] of satellites (N, 3) seen from receivers (N, 3)."""
    _, los = line_of_sight(sat_pos[:, None, :], rx)
    el, az = elevation_azimuth(los, rx)
    return el[:, 0], az[:, 0]


def _atmosphere(rows: pd.DataFrame, nav, rx: np.ndarray, el: np.ndarray, az: np.ndarray) -> np.ndarray:
    """(N,) ionospheric (when the navigation header has Klobuchar coefficients) + tropospheric
    delay [m] per row; rx: (N, 3) receiver ECEF, el/az: (N,) [deg]."""
    llh = ecef2geodetic(rx)
    delay = tropo_delay(llh[:, 0], llh[:, 2], el)
    klob = getattr(nav, "klobuchar", None)
    if klob is not None:
        tow = (rows["t_ns"].to_numpy(np.int64) // 1_000_000 % (WEEK_S * 1000)) / 1000.0
        l1 = klobuchar_l1(klob, llh[:, 0], llh[:, 1], az, el, tow)
        delay = delay + np.where(rows["iono_free"].to_numpy(bool), 0.0, l1 * iono_scale(rows["carrier_hz"].to_numpy()))
    return delay


def _columns(rows: pd.DataFrame, st: dict[str, np.ndarray], pr: np.ndarray) -> dict[str, np.ndarray]:
    """Trace per-row columns (N,) / (N, 3) for :func:`fusion.trace.pack_rows`."""
    cn0 = rows["cn0"].to_numpy()
    sigma = rows["pr_sigma_m"].to_numpy()
    model = pr_sigma_model(np.nan_to_num(cn0, nan=CN0_REF - 10))
    reported = np.isfinite(sigma) & (sigma > 0)
    sigma = np.where(reported, sigma, model * rows["sigma_scale"].to_numpy())
    prr = rows["prr_mps"].to_numpy() + C_LIGHT * st["clock_drift"]
    prr_ok = np.isfinite(prr)
    adr = rows["adr_m"].to_numpy() + C_LIGHT * st["clock_s"]
    adr_ok = rows["adr_ok"].to_numpy(bool) & np.isfinite(adr)
    prr_sig, adr_sig = rows["prr_sigma_mps"].to_numpy(), rows["adr_sigma_m"].to_numpy()
    return {
        "sat_pos": st["pos"], "sat_vel": st["vel"], "pr": pr, "pr_sigma": sigma, "pr_sigma_ok": reported,
        "sat_id": rows["sat_id"].to_numpy(np.int32), "signal": st["signal"],
        "cn0": np.nan_to_num(cn0, nan=0.0),
        "prr": np.where(prr_ok, prr, 0.0), "prr_ok": prr_ok,
        "prr_sigma": np.where(prr_ok & np.isfinite(prr_sig) & (prr_sig > 0), prr_sig, np.where(prr_ok, SIGMA_PRR_MPS, 1.0)),
        "adr": np.where(adr_ok, adr, 0.0), "adr_ok": adr_ok,
        "adr_sigma": np.where(adr_ok & np.isfinite(adr_sig) & (adr_sig > 0), adr_sig, np.where(adr_ok, SIGMA_ADR_M, 1.0)),
        "adr_slip": rows["adr_slip"].to_numpy(bool),
    }
