"""Load a trace folder holding raw receiver logs: a RINEX observation file or a GnssLogger log
(directly or in ``supplemental/``), navigation from the folder or given, truth from
``ground_truth.csv`` (GSDC 2021 or 2022/23 columns) or a SPAN NMEA log, interpolated to the
receiver's epochs (a phone's epochs are not on the truth's whole seconds).

RINEX observation and navigation files are found by their header, not their name
(:mod:`fusion.io.discover`): ``hksc137c.21f`` (BeiDou), ``*_EN.rnx`` (Galileo), ``.crx.gz``
(Hatanaka) are all read. The navigation files used, and the constellations each covers, are
printed on stderr; a GLONASS channel the observation header lacks comes from the navigation
records, else from the slot table (:data:`fusion.io.nav_records.SLOT_CHANNEL`).
"""
from __future__ import annotations

import re
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fusion.errors import DataError
from fusion.io.discover import SYSTEM_NAMES, files_of_kind, is_gnss_logger, rinex_kind
from fusion.io.truth import (GSDC2021_TRUTH_HEIGHT_ERROR_M, check_overlap, interp_gapped, llh_ecef,
                             read_truth_csv, warn_outside_bay_area)
from fusion.trace import Trace, count_skip, trace_folder_name

#: GnssLogger logs.
_LOG = re.compile(r"(gnss_?log.*\.txt)(\.gz)?$", re.IGNORECASE)
#: Navigation systems :func:`fusion.io.rinex_nav.read_nav` models (M: mixed).
_NAV_SYSTEMS = set("GRECJM")
_SP3 = re.compile(r"\.sp3(\.gz)?$", re.IGNORECASE)
_CLK = re.compile(r"\.clk(\.gz)?$", re.IGNORECASE)
#: Truth CSV rows are 1 Hz: interpolate across gaps up to this long [ms].
CSV_MAX_GAP_MS = 1500


@dataclass
class RawSources:
    """Navigation given by the user (``--nav``, ``--sp3``, ``--clk``); empty: search the folder."""

    nav: tuple[Path, ...] = ()
    sp3: Path | None = None
    clk: Path | None = None
    #: ionosphere-free combination where a satellite has two frequencies (``--iono-free``)
    iono_free: bool = False


def _files(folder: Path, pattern: re.Pattern) -> list[Path]:
    """Files in ``folder`` and ``folder/supplemental`` whose names match ``pattern``."""
    out = []
    for d in (folder, folder / "supplemental"):
        if d.is_dir():
            out += sorted(p for p in d.iterdir() if p.is_file() and pattern.search(p.name))
    return out


def raw_log_files(folder: Path) -> list[Path]:
    """RINEX observation files (by header, Hatanaka too) and GnssLogger logs (by name, or by content
    for ``.txt`` files named otherwise) in ``folder`` or its ``supplemental/``."""
    txt = re.compile(r"\.txt(\.gz)?$", re.IGNORECASE)
    logs = _files(folder, _LOG)
    logs += [p for p in _files(folder, txt) if p not in logs and is_gnss_logger(p)]
    return [p for p in files_of_kind(folder, "obs") if p not in logs] + sorted(logs)


def read_raw(path: Path, glonass_channels: dict[int, int] | None = None):
    """A RINEX observation file or a GnssLogger log -> :class:`~fusion.io.raw.RawObs`.
    glonass_channels: slot -> channel for RINEX headers that lack some (e.g. from navigation)."""
    if _LOG.search(path.name) or is_gnss_logger(path):
        from fusion.io.gnss_log import read_gnss_log
        return read_gnss_log(path)
    from fusion.io.rinex_obs import read_rinex_obs
    return read_rinex_obs(path, glonass_channels)


def navigation_files(folder: Path) -> list[Path]:
    """RINEX navigation files of the systems we model in ``folder`` or ``supplemental/``, found by
    header whatever their names; others (SBAS, NavIC) are named on stderr and left out."""
    out = []
    for p in files_of_kind(folder, "nav"):
        kind = rinex_kind(p)
        system = kind.system
        # RINEX 2 navigation: we read GPS (type N) and GLONASS (type G) files
        if system in _NAV_SYSTEMS and (kind.version >= 3 or system in "GR"):
            out.append(p)
        else:
            _say(f"navigation: {p.name} holds {SYSTEM_NAMES.get(system, system)} records only: not used")
    return out


def _say(line: str) -> None:
    print(line, file=sys.stderr)


def describe_navigation(nav) -> list[str]:
    """One line per navigation file: its name, the constellations it covers and its records' time span."""
    out = []
    for f, systems in nav.file_systems.items():
        what = ", ".join(SYSTEM_NAMES[s] for s in "GRECJ" if s in systems) or "no usable records"
        when = nav.records_text(f)
        out.append(f"navigation: {Path(f).name} ({what}{'' if when is None else ', ' + when + ' GPST'})")
    return out


def _navigation(folder: Path, src: RawSources):
    """(broadcast Navigation or None, PreciseOrbits or None) from the options or the folder."""
    from fusion.io.rinex_nav import read_nav

    nav_files = list(src.nav) or navigation_files(folder)
    sp3 = src.sp3 or next(iter(_files(folder, _SP3)), None)
    clk = src.clk or (next(iter(_files(folder, _CLK)), None) if sp3 is not None else None)
    if src.clk is not None and sp3 is None:
        raise DataError(f"{src.clk}: a clock file needs SP3 orbits too (--sp3)")
    nav = read_nav(nav_files) if nav_files else None
    for line in describe_navigation(nav) if nav is not None else []:
        _say(line)
    precise = None
    if sp3 is not None:
        from fusion.io.clk import read_clk
        from fusion.io.sp3 import read_sp3
        from fusion.nav.precise import PreciseOrbits
        precise = PreciseOrbits(read_sp3(sp3), read_clk(clk) if clk is not None else None)
        _say(f"precise orbits: {Path(sp3).name}" + (f", clocks: {Path(clk).name}" if clk is not None else ""))
    if nav is None and precise is None:
        raise DataError(f"{folder}: no navigation data: put a RINEX navigation file (any name: .YYn, .YYg, .YYf, *_MN.rnx, ...) "
                        "in the folder or supplemental/, or pass --nav FILE (or --sp3 FILE [--clk FILE])")
    return nav, precise


def load_raw_trace(folder: Path, log: Path, src: RawSources, *, signals=None, truth: str = "auto",
                   fix_truth_height: bool = True, min_sats: int = 1, name: str | None = None) -> Trace:
    """Read ``log``, compute satellite states from the navigation, attach interpolated truth."""
    from fusion.prepare.raw_trace import raw_to_trace

    try:
        nav, precise = _navigation(folder, src)
    except DataError:
        read_raw(log, None)         # a log with nothing to solve says so before asking for navigation
        raise
    raw = read_raw(log, nav.glonass_channels() if nav is not None else None)
    trace = raw_to_trace(raw, nav, signals=signals, precise=precise, min_sats=min_sats, iono_free=src.iono_free,
                         name=name or trace_folder_name(folder))
    del raw     # the raw rows' memory serves the truth reader (fresh pages are slow to touch)
    if truth != "none":
        trace.truth = _optional_truth(folder, trace, truth, fix_truth_height)
    return trace


def _optional_truth(folder: Path, trace: Trace, truth: str, fix_truth_height: bool) -> np.ndarray | None:
    """:func:`_truth`; found rather than asked for (``truth`` auto), a truth file that cannot be used (unreadable,
    no overlap) costs the accuracy figures, not the run: a warning, a count (``truth_unusable``), no truth."""
    try:
        return _truth(folder, trace, truth, fix_truth_height)
    except DataError as exc:
        if truth != "auto":
            raise
        warnings.warn(f"{exc}; solved without truth (no accuracy figures)", stacklevel=2)
        count_skip(trace.skipped, "truth_unusable", 1)
        return None


def _truth(folder: Path, trace: Trace, truth: str, fix_truth_height: bool) -> np.ndarray | None:
    """(E, 3) truth interpolated at the epochs (SPAN NMEA first when ``truth`` is auto/nmea)."""
    from fusion.prepare.load import _span_file
    from fusion.io.nmea import read_span_nmea

    t = trace.t_ms
    nmea = _span_file(folder, folder.name) if truth in ("auto", "nmea") else None
    if truth == "nmea" and nmea is None:
        raise DataError(f"{folder}: truth='nmea' but no supplemental/SPAN_*.nmea[.gz] file")
    if nmea is not None:
        span = read_span_nmea(nmea, ref_gps_ms=int(t[0]), skipped=trace.skipped)
        out = interp_gapped(t, span["t_ms"].to_numpy(), llh_ecef(span))
        check_overlap(t, span["t_ms"].to_numpy(), out, Path(trace.name), nmea)
        return out
    csv = next((folder / n for n in ("ground_truth.csv", "ground_truth.csv.gz") if (folder / n).is_file()), None)
    if csv is None:
        return None
    df = read_truth_csv(csv, trace.skipped)
    if fix_truth_height and _is_gsdc2021(csv):
        warn_outside_bay_area(df, csv)
        df = df.assign(height_m=df["height_m"] - GSDC2021_TRUTH_HEIGHT_ERROR_M)
    out = interp_gapped(t, df["t_ms"].to_numpy(), llh_ecef(df), CSV_MAX_GAP_MS)
    check_overlap(t, df["t_ms"].to_numpy(), out, Path(trace.name), csv)
    return out


def _is_gsdc2021(csv: Path) -> bool:
    """GSDC 2021 truth (millisSinceGpsEpoch column) carries the 63 m height error; 2022/23 does not."""
    import pandas as pd
    return "millisSinceGpsEpoch" in pd.read_csv(csv, nrows=0).columns
