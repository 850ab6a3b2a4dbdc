"""smartLoc (TU Chemnitz) drives in libRSF text format -> :class:`~fusion.trace.Trace`.

A drive folder holds ``<drive>_Input.txt`` (``pseudorange3`` and ``odom3`` lines) and
``<drive>_GT.txt`` (``point3`` truth); :mod:`fusion.io.librsf` parses them. What the files give and
how it maps onto the Trace:

- Pseudoranges have the satellite clock and the atmosphere removed already, and satellite positions
  are given: no navigation file is needed. The positions are ECEF at transmit time, not rotated for
  the Earth's rotation during flight (checked on Berlin Potsdamer Platz: at the truth, the Sagnac
  rotation halves the spread of the GPS residuals, 7.6 vs 15.3 m median absolute deviation), as the
  Trace wants them.
- ``pseudorange covariance`` is a variance [m^2]: ``pr_sigma`` is its square root. C/N0 -> ``cn0``.
  The given elevation is not kept: it equals the one computed from the geometry at the truth
  (to 1e-12 deg), which every estimator computes itself.
- Systems 1 / 4 / 8 / 16 / 32 -> GPS L1, GLONASS G1, Galileo E1, QZSS J1, BeiDou B1I (GSDC
  constellation codes 1 / 3 / 6 / 4 / 5); SBAS (2) and unknown codes are skipped and counted.
  GLONASS satellites are numbered 301-324 (slot + 300): the slot is kept.
- One number in two systems in one epoch (GPS PRN 2 and GLONASS 302: 1953 such pairs in Berlin
  Potsdamer Platz) are two satellites, told apart by the system. True repeats of one satellite in one
  epoch (none in that drive): identical lines count as ``duplicate_rows`` (one kept); differing ones
  are all dropped (``conflicting_duplicate_rows``): nothing tells which is right.
- Non-reference signals (GLONASS against GPS) have one trace-wide inter-system bias removed, measured
  at a reference-signal WLS, so that WLS can use one clock; the graph still estimates what is left
  with a bias state of their own (:mod:`fusion.estimate.graph.isb`).
- Time stamps are seconds from the start of the drive. GPS time is recovered where the drive's start
  is known (:data:`DRIVE_START_GPS`); otherwise the drive is placed at :data:`UNKNOWN_START_GPS_MS`
  with a warning. Nothing downstream needs absolute time here: elevation and azimuth come from the
  geometry, and no ionosphere, troposphere or satellite clock model is evaluated (already removed).
- ``odom3`` rows (body velocity, turn rate, variances) become ``Trace.odometry``; ``point3`` rows the
  truth, both matched to epochs by their relative time (same stamps as the pseudoranges).
"""
from __future__ import annotations

import logging
import re
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

from fusion.errors import DataError
from fusion.estimate.wls import solve_wls_arrays
from fusion.geometry import line_of_sight
from fusion.io.clean import epochs_with_enough_rows
from fusion.io.librsf import read_librsf
from fusion.io.truth import TRUTH_TOL_MS, check_overlap, interp_gapped, match_nearest
from fusion.trace import SIGNALS, Trace, count_skip, pack_rows, resolve_signals, trace_folder_name

log = logging.getLogger(__name__)

_INPUT = re.compile(r"^(?P<drive>.+)_Input\.txt(\.gz)?$")
#: libRSF system code -> (GSDC constellation type, signal name)
SYSTEMS = {1: (1, "GPS_L1"), 4: (3, "GLO_G1"), 8: (6, "GAL_E1"), 16: (4, "QZS_J1"), 32: (5, "BDS_B1I")}
#: GPS week and second of week of time stamp 0 of known drives. Berlin Potsdamer Platz: the drive's
#: raw u-blox file (smartLoc's ``tu_chemnitz_berlin_1_raw.csv``, rows at 1900/126641.7 s) carries a
#: truth position equal to the libRSF ``point3`` at time 0 (to 1 mm), and its epochs at +0.3, +0.5,
#: +0.7, ... s match the libRSF time stamps.
DRIVE_START_GPS: dict[str, tuple[int, float]] = {"Berlin_Potsdamer_Platz": (1900, 126641.7)}
#: Where a drive of unknown start is placed: the GPS epoch, so that no one mistakes it for a date.
UNKNOWN_START_GPS_MS = 0
# Plausibility bounds (reject garbage, not outliers), as for the other readers.
_SAT_RADIUS_M = (1.0e7, 5.0e7)
_PR_RANGE_M = (1.0e7, 5.0e7)
# pseudorange3 columns after the tag
_T, _PR, _VAR, _X, _SV, _SYS, _EL, _CN0 = 0, 1, 2, 3, 6, 7, 8, 9


def smartloc_input(path: Path) -> Path | None:
    """The ``*_Input.txt[.gz]`` file of a smartLoc drive: ``path`` itself or the only one in folder
    ``path``; None when there is none. Several in one folder: :class:`DataError`."""
    if path.is_file():
        return path if _INPUT.match(path.name) else None
    if not path.is_dir():
        return None
    found = sorted(p for p in path.iterdir() if p.is_file() and _INPUT.match(p.name))
    if len(found) > 1:
        raise DataError(f"{path}: several smartLoc input files ({', '.join(p.name for p in found)}); pass one")
    return found[0] if found else None


def drive_start_gps_ms(drive: str, path: Path) -> int:
    """GPS milliseconds of time stamp 0 of ``drive`` (see :data:`DRIVE_START_GPS`)."""
    if drive in DRIVE_START_GPS:
        week, tow = DRIVE_START_GPS[drive]
        return int(week) * 604_800_000 + int(round(tow * 1000))
    warnings.warn(f"{path}: GPS time of smartLoc drive {drive!r} is unknown; its epochs are placed at the "
                  "GPS epoch (1980-01-06) plus their seconds from the drive start", stacklevel=3)
    return UNKNOWN_START_GPS_MS


def load_smartloc(input_path: str | Path, *, signals=None, truth: str = "auto", min_sats: int = 4,
                  truth_tol_ms: float = TRUTH_TOL_MS, name: str | None = None) -> Trace:
    """Load a smartLoc drive: its ``<drive>_Input.txt`` and, unless ``truth="none"``, the
    ``<drive>_GT.txt`` beside it (optional with ``"auto"``).

    signals: names to keep, None for every supported signal in the file. min_sats: epochs with
    fewer pseudoranges are skipped and counted.
    """
    input_path = Path(input_path)
    m = _INPUT.match(input_path.name)
    if m is None:
        raise DataError(f"{input_path}: not a smartLoc input file (<drive>_Input.txt)")
    if truth not in ("auto", "csv", "none"):
        raise DataError(f"{input_path}: truth={truth!r} is not available for smartLoc drives (their truth is "
                        "the <drive>_GT.txt file): use auto or none")
    drive, skipped = m["drive"], {}
    records = read_librsf(input_path, "smartLoc input", skipped)
    if "pseudorange3" not in records:
        raise DataError(f"{input_path}: no usable pseudorange3 line")
    t0 = drive_start_gps_ms(drive, input_path)
    kwargs = _pseudoranges(*records["pseudorange3"], t0, input_path, signals, min_sats, skipped)
    t_ms = kwargs["t_ms"]
    odometry = None
    if "odom3" in records:
        odom_t, odom = _by_time(_plausible_odometry(*records["odom3"], input_path, skipped), t0)
        odometry = match_nearest(t_ms, odom_t, odom, truth_tol_ms)
        gap = ~np.isfinite(odometry).all(axis=1)       # a row skipped or not written: its neighbours' mean
        odometry[gap] = interp_gapped(t_ms[gap], odom_t, odom, ODOMETRY_MAX_GAP_MS)
        count_skip(skipped, "epochs_odometry_interpolated", gap & np.isfinite(odometry).all(axis=1))
        count_skip(skipped, "epochs_without_odometry", ~np.isfinite(odometry).all(axis=1))
    trace = Trace(name=name or trace_folder_name(input_path.parent), skipped=skipped,
                  odometry=odometry, **kwargs)
    gt = input_path.with_name(f"{drive}_GT.txt")
    gt = gt if gt.is_file() else gt.with_name(gt.name + ".gz")
    if truth != "none" and gt.is_file():
        trace.truth = _truth(gt, t_ms, t0, truth_tol_ms, input_path, skipped)
    return trace


#: An epoch without an odometry row of its own takes the rows around it across a gap of up to this [ms] (a row or
#: two of the 5 Hz log): a missing step breaks the odometry chain of the graph.
ODOMETRY_MAX_GAP_MS = 1000.0
#: Beyond these a car's odometry row is corrupt, not driven [m/s, rad/s]: one such row bent the whole graph's track.
MAX_ODOMETRY_SPEED_MPS = 70.0
MAX_ODOMETRY_TURN_RADPS = 3.0


def _plausible_odometry(values: np.ndarray, line: np.ndarray, path: Path, skipped: dict) -> np.ndarray:
    """The ``odom3`` rows (N, 13: time, ODOMETRY_COLUMNS) a car can have driven: speeds within
    :data:`MAX_ODOMETRY_SPEED_MPS`, turn rates within :data:`MAX_ODOMETRY_TURN_RADPS`, no negative variance; the
    others skipped, counted and warned of by their first line (``line`` (N,))."""
    v, w, var = values[:, 1:4], values[:, 4:7], values[:, 7:]
    ok = (np.abs(v) <= MAX_ODOMETRY_SPEED_MPS).all(1) & (np.abs(w) <= MAX_ODOMETRY_TURN_RADPS).all(1) \
        & (var >= 0).all(1)
    if not ok.all():
        warnings.warn(f"{path}:{line[~ok][0]}: odometry no car drives (speed above {MAX_ODOMETRY_SPEED_MPS:g} m/s, "
                      f"turn rate above {MAX_ODOMETRY_TURN_RADPS:g} rad/s or a negative variance); "
                      f"{int((~ok).sum())} such line(s) skipped", stacklevel=3)
    count_skip(skipped, "odometry_rows_implausible", ~ok)
    return values[ok]


def _by_time(values: np.ndarray, t0: int) -> tuple[np.ndarray, np.ndarray]:
    """(N,) GPS ms of libRSF rows (time in column 0) sorted, one row per time (the first), and their
    other columns (N, k)."""
    t = t0 + np.round(values[:, 0] * 1000).astype(np.int64)
    order = np.argsort(t, kind="stable")
    t, values = t[order], values[order]
    first = np.r_[True, np.diff(t) > 0]
    return t[first], values[first, 1:]


def _truth(gt: Path, t_ms: np.ndarray, t0: int, tol_ms: float, input_path: Path, skipped: dict) -> np.ndarray:
    """(E, 3) ECEF truth at the epochs from the ``point3`` lines of ``gt``."""
    local: dict[str, int] = {}
    records = read_librsf(gt, "smartLoc ground truth", local)
    for k, v in local.items():
        count_skip(skipped, f"truth_{k}", v)
    if "point3" not in records:
        raise DataError(f"{gt}: no usable point3 line")
    ref_t, ref = _by_time(records["point3"][0], t0)
    out = match_nearest(t_ms, ref_t, ref[:, :3], tol_ms)
    check_overlap(t_ms, ref_t, out, input_path, gt)
    return out


def _pseudoranges(v: np.ndarray, line: np.ndarray, t0: int, path: Path, signals, min_sats: int,
                  skipped: dict[str, int]) -> dict:
    """Trace keyword arguments (no truth, no odometry) from pseudorange3 values (N, 10) and their
    line numbers (N,)."""
    const, sig = _systems(v[:, _SYS].astype(np.int64), path, line, skipped)
    keep = sig >= 0
    sel = np.arange(len(SIGNALS)) if signals is None else resolve_signals(signals)
    chosen = np.isin(sig, sel)
    count_skip(skipped, "rows_signal_not_selected", keep & ~chosen)
    r = np.linalg.norm(v[:, _X:_X + 3], axis=1)
    good = ((r > _SAT_RADIUS_M[0]) & (r < _SAT_RADIUS_M[1]) & (v[:, _PR] > _PR_RANGE_M[0])
            & (v[:, _PR] < _PR_RANGE_M[1]) & (v[:, _VAR] > 0))
    count_skip(skipped, "rows_bad_values", keep & chosen & ~good)
    keep &= chosen & good
    if not keep.any():
        raise DataError(f"{path}: no usable pseudorange of signal(s) {', '.join(SIGNALS[i] for i in sel)}")
    sv = v[:, _SV].astype(np.int64)
    sat_id = 1000 * const + np.where(sv >= 100, sv % 100, sv)
    t = t0 + np.round(v[:, _T] * 1000).astype(np.int64)
    keep &= _unique_rows(t, sat_id, v, keep, skipped)
    order = np.flatnonzero(keep)[np.lexsort((sat_id[keep], t[keep]))]
    ok, epoch, t_ms = epochs_with_enough_rows(t[order], min_sats, skipped, path, "pseudoranges")
    order = order[ok]
    packed = pack_rows(epoch, t_ms.size, {
        "sat_pos": v[order, _X:_X + 3], "pr": v[order, _PR], "pr_sigma": np.sqrt(v[order, _VAR]),
        "sat_id": sat_id[order].astype(np.int32), "signal": sig[order].astype(np.int8), "cn0": v[order, _CN0],
    })
    packed["pr"] = packed["pr"] - _inter_system_bias(packed, path)
    E, S = packed["pr"].shape
    return dict(t_ms=t_ms, sat_vel=np.zeros((E, S, 3)), clock_reset=np.zeros(E, bool), **packed)


def _systems(code: np.ndarray, path: Path, line: np.ndarray, skipped: dict) -> tuple[np.ndarray, np.ndarray]:
    """(N,) GSDC constellation type and SIGNALS index per row (-1 for systems not supported, which are
    counted as ``rows_unsupported_system:<code>``)."""
    const, sig = np.full(code.shape, -1), np.full(code.shape, -1)
    for c, (k, name) in SYSTEMS.items():
        const[code == c], sig[code == c] = k, SIGNALS.index(name)
    bad = sig < 0
    for c in np.unique(code[bad]):
        count_skip(skipped, f"rows_unsupported_system:{c}", code == c)
    if bad.any():
        log.info("%s:%d: satellite system %d is not supported (SBAS or unknown); such rows skipped",
                 path, line[bad][0], code[bad][0])
    return const, sig


def _unique_rows(t: np.ndarray, sat_id: np.ndarray, v: np.ndarray, keep: np.ndarray, skipped: dict) -> np.ndarray:
    """(N,) bool: False for repeats of a row already seen with the same time, satellite and values
    (``duplicate_rows``), and for every row of a (time, satellite) whose rows disagree
    (``conflicting_duplicate_rows``). Only rows in ``keep`` take part."""
    idx = np.flatnonzero(keep)
    df = pd.DataFrame(v[idx][:, [_PR, _VAR, _X, _X + 1, _X + 2, _CN0]]).assign(t=t[idx], sat=sat_id[idx])
    exact = df.duplicated().to_numpy()
    # a (time, satellite) conflicts when its rows hold more than one distinct set of values
    distinct = df.assign(d=~exact).groupby(["t", "sat"])["d"].transform("sum").to_numpy()
    conflict = distinct > 1
    count_skip(skipped, "duplicate_rows", exact & ~conflict)
    count_skip(skipped, "conflicting_duplicate_rows", conflict)
    out = np.ones(t.shape, bool)
    out[idx] = ~(exact | conflict)
    return out


def _inter_system_bias(packed: dict, path: Path) -> np.ndarray:
    """(E, S) trace-wide inter-system bias [m] of each slot against the reference signal (GPS L1 when
    present, else the commonest): the median over the trace of ``pr - range - clock`` at a robust
    reference-signal WLS; 0 on reference slots, and where no epoch could be solved."""
    mask, sig = packed["mask"], packed["signal"].astype(np.int64)
    present, counts = np.unique(sig[mask], return_counts=True)
    ref = 0 if 0 in present else int(present[np.argmax(counts)])
    bias = np.zeros(mask.shape)
    if present.size <= 1:
        return bias
    w = solve_wls_arrays(packed["sat_pos"], packed["pr"], mask & (sig == ref), elev_mask_deg=10.0, robust=True)
    rng, _ = line_of_sight(packed["sat_pos"], np.where(w.valid[:, None], w.pos, 0.0))
    resid = packed["pr"] - rng - w.clock_m[:, None]
    for s in present[present != ref]:              # a handful of signals
        on = mask & (sig == s)
        use = on & w.valid[:, None]
        if use.any():
            b = float(np.median(resid[use]))
            bias[on] = b
            log.info("%s: %s bias against %s: %.2f m (removed; the graph estimates what is left)",
                     path, SIGNALS[s], SIGNALS[ref], b)
    return bias
