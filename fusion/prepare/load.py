"""Find and load traces: a ``<collection>/<phone>`` folder (or a file in one) -> :class:`~fusion.trace.Trace`.

The format is detected from the files: ``*_derived.csv[.gz]`` -> GSDC 2021, ``device_gnss.csv[.gz]``
-> GSDC 2022/23 (:mod:`fusion.io.gsdc`); failing those, a RINEX observation file or GnssLogger
log in the folder or its ``supplemental/`` (:mod:`fusion.prepare.raw_load`, with navigation from the
folder or the caller). Truth comes from the folder's ``ground_truth.csv`` or SPAN NMEA log
(:mod:`fusion.io.truth`). A smartLoc drive (``<drive>_Input.txt`` + ``<drive>_GT.txt``, libRSF text)
is read by :mod:`fusion.prepare.smartloc`.
"""
from __future__ import annotations

import warnings
from collections.abc import Iterator
from pathlib import Path

from fusion.errors import DataError, GnssfuseError
from fusion.io.gsdc import load_derived_2021, load_device_gnss
from fusion.prepare.raw_load import RawSources, load_raw_trace, raw_log_files
from fusion.prepare.smartloc import load_smartloc, smartloc_input
from fusion.io.truth import TRUTH_TOL_MS
from fusion.trace import Trace, trace_folder_name

def _csv_name(p: Path) -> str:
    """'x.csv' or 'x.csv.gz' -> 'x', else ''."""
    n = p.name
    for suf in (".csv.gz", ".csv"):
        if n.endswith(suf):
            return n[: -len(suf)]
    return ""


def _measurement_files(folder: Path) -> list[Path]:
    files = [p for p in folder.iterdir() if p.is_file()
             and ("_derived" in _csv_name(p) or _csv_name(p) == "device_gnss")]
    return sorted(files)


def _find_optional(folder: Path, stem: str) -> Path | None:
    for suf in (".csv", ".csv.gz"):
        if (folder / f"{stem}{suf}").is_file():
            return folder / f"{stem}{suf}"
    return None


def _span_file(folder: Path, phone: str) -> Path | None:
    sup = folder / "supplemental"
    if not sup.is_dir():
        return None
    cands = sorted(p for p in sup.iterdir() if p.name.startswith("SPAN_")
                   and (p.name.endswith(".nmea") or p.name.endswith(".nmea.gz")))
    if len(cands) > 1:
        cands = [p for p in cands if phone in p.name] or cands
        if len(cands) > 1:
            raise DataError(f"{sup}: several SPAN NMEA logs ({', '.join(p.name for p in cands)}); pass one")
    return cands[0] if cands else None


def _locate(path: Path) -> tuple[Path, Path, bool]:
    """(measurement file, its folder, whether it is the folder's only one) for a trace path."""
    if path.is_dir():
        files = _measurement_files(path)
        if not files:
            raise DataError(f"{path}: no *_derived.csv[.gz] or device_gnss.csv[.gz] measurement file, "
                            "RINEX observation file or GnssLogger log (also looked in supplemental/), "
                            "nor a smartLoc <drive>_Input.txt")
        if len(files) > 1:
            raise DataError(f"{path}: several measurement files ({', '.join(p.name for p in files)}); "
                            f"pass one of them")
        return files[0], path, True
    if path.is_file():
        stem = _csv_name(path)
        if "_derived" not in stem and stem != "device_gnss":     # raw logs were recognised by content before
            empty = " (the file is empty)" if path.stat().st_size == 0 else ""
            raise DataError(f"{path}: not a measurement file gnssfuse reads{empty}: a GSDC *_derived.csv[.gz] or "
                            "device_gnss.csv[.gz], a RINEX observation file or a GnssLogger log")
        return path, path.parent, len(_measurement_files(path.parent)) == 1
    raise DataError(f"{path}: no such trace folder or file")


def _name(meas: Path, folder: Path, single: bool) -> str:
    return trace_folder_name(folder) if single else f"{folder.resolve().name}/{_csv_name(meas)}"


def trace_name(path: str | Path) -> str:
    """The name :func:`load_trace` gives the trace at ``path``, without reading it (the path itself
    when it is not a loadable trace)."""
    try:
        smartloc = smartloc_input(Path(path))
        if smartloc is not None:
            return trace_folder_name(smartloc.parent)
        return _name(*_locate(Path(path)))
    except DataError:
        return str(path)


def load_trace(path: str | Path, signals=("GPS_L1",), fix_truth_height: bool = True, truth: str = "auto",
               *, min_sats: int = 4, truth_tol_ms: float = TRUTH_TOL_MS,
               raw_sources: RawSources | None = None) -> Trace:
    """Load one trace: a ``<collection>/<phone>`` folder, or a measurement file inside one.

    Format is detected from the files (``<drive>_Input.txt`` -> smartLoc libRSF, :mod:`fusion.prepare.smartloc`;
    ``*_derived.csv[.gz]`` -> GSDC 2021, ``device_gnss.csv[.gz]`` -> GSDC 2022/23, else a raw log with navigation from ``raw_sources`` or the folder, see
    :mod:`fusion.prepare.raw_load`). ``signals``: names, or None for the format's default (GSDC: GPS L1;
    raw logs: every signal with ephemerides; smartLoc: every supported signal in the file). ``truth``: ``"auto"`` (SPAN NMEA when present, else
    ``ground_truth.csv``, else none), ``"csv"`` (ignore NMEA), ``"nmea"`` (require it), ``"none"``.
    The trace is named ``<collection>/<phone>`` after its folder, or ``<folder>/<stem>`` when that
    folder holds several measurement files (e.g. ``samples/Pixel4_derived``).
    """
    path = Path(path)
    if truth not in ("auto", "csv", "nmea", "none"):
        raise GnssfuseError(f"truth must be 'auto', 'csv', 'nmea' or 'none', got {truth!r}")
    smartloc = smartloc_input(path)
    if smartloc is not None:
        _say_unused(path, raw_sources)
        return load_smartloc(smartloc, signals=signals, truth=truth, min_sats=min_sats, truth_tol_ms=truth_tol_ms)
    raw = _raw_log(path)
    if raw is not None:
        return load_raw_trace(raw[0], raw[1], raw_sources or RawSources(), signals=signals, truth=truth,
                              fix_truth_height=fix_truth_height, min_sats=min_sats)
    signals = ("GPS_L1",) if signals is None else signals
    meas, folder, single = _locate(path)
    _say_unused(path, raw_sources)
    name = _name(meas, folder, single)
    stem = _csv_name(meas)

    # Truth beside the file: '<x>_ground_truth' pairs with '<x>_derived'; else the folder's one.
    truth_csv = None
    if truth in ("auto", "csv"):
        paired = _find_optional(folder, stem.replace("_derived", "_ground_truth")) if "_derived" in stem else None
        truth_csv = paired or (_find_optional(folder, "ground_truth") if single else None)

    if stem == "device_gnss":
        if truth == "nmea":
            raise DataError(f"{folder}: truth='nmea' is only for GSDC 2021 traces with a SPAN log")
        return load_device_gnss(meas, truth_csv, signals=signals, min_sats=min_sats,
                                truth_tol_ms=truth_tol_ms, name=name)
    nmea = None
    if truth in ("auto", "nmea") and single:
        nmea = _span_file(folder, folder.name)
    if truth == "nmea":
        if nmea is None:
            raise DataError(f"{folder}: truth='nmea' but no supplemental/SPAN_*.nmea[.gz] file")
        if not fix_truth_height:
            raise GnssfuseError("truth='nmea' already has correct heights; fix_truth_height=False contradicts it")
    return load_derived_2021(meas, truth_csv, nmea, signals=signals, fix_truth_height=fix_truth_height,
                             min_sats=min_sats, truth_tol_ms=truth_tol_ms, name=name)


def _say_unused(path: Path, sources: RawSources | None) -> None:
    """Warn that navigation options given for a file that carries its own satellite states do nothing."""
    if sources is None:
        return
    given = [flag for flag, v in (("--nav", sources.nav), ("--sp3", sources.sp3), ("--clk", sources.clk),
                                  ("--iono-free", sources.iono_free)) if v]
    if given:
        warnings.warn(f"{path}: {', '.join(given)} not used: this file carries its satellites' positions and "
                      f"corrected pseudoranges (only RINEX observations and GnssLogger logs need navigation)")


def _raw_log(path: Path) -> tuple[Path, Path] | None:
    """(trace folder, raw log) when ``path`` is a raw log or a folder with one and no GSDC file. A log in (or a
    folder named) ``supplemental/`` belongs to the folder above, where its truth lies."""
    if path.is_file() and path.parent.name == "supplemental" and path in raw_log_files(path.parent.parent):
        return path.parent.parent, path
    if path.is_file() and path in raw_log_files(path.parent):
        return path.parent, path
    if path.is_dir() and path.name == "supplemental" and raw_log_files(path):
        path = path.parent
    if not path.is_dir() or _measurement_files(path):
        return None
    logs = raw_log_files(path)
    if len(logs) > 1:
        raise DataError(f"{path}: several raw logs ({', '.join(p.name for p in logs)}); pass one of them")
    return (path, logs[0]) if logs else None


def find_traces(root: str | Path, include_raw: bool = False) -> list[Path]:
    """Every loadable trace under ``root`` (a Kaggle-layout folder such as ``train/``, or a trace).

    Returns ``<collection>/<phone>`` folders holding one measurement file; folders holding several
    (e.g. ``samples/``) contribute each file, which :func:`load_trace` also accepts. Sorted.
    Folders with only a raw log (RINEX observations, GnssLogger) need navigation data to load, so
    they are listed only with ``include_raw`` - or when ``root`` itself is one (a trace the
    caller named). Raises :class:`DataError` when ``root`` does not exist or holds no trace.
    """
    root = Path(root)
    if not root.exists():
        raise DataError(f"{root}: no such folder")
    if root.is_file():
        return [root]
    found: list[Path] = []
    for folder in sorted({root, *(p for p in root.rglob("*") if p.is_dir())}):
        files = _measurement_files(folder)
        found.extend([folder] if len(files) == 1 else files)
        if not files and smartloc_input(folder) is not None:
            found.append(folder)
        # a raw-log folder (its logs may sit in supplemental/, which is not a trace of its own)
        if (include_raw or folder == root) and not files and folder.name != "supplemental" and raw_log_files(folder):
            found.append(folder)
    if not found:
        raise DataError(f"{root}: no trace found (no *_derived.csv[.gz], device_gnss.csv[.gz], RINEX "
                        "observation file or GnssLogger log below it)")
    return sorted(found)


def load_dataset(root: str | Path, signals=("GPS_L1",), fix_truth_height: bool = True, truth: str = "auto",
                 *, min_sats: int = 4, on_error: str = "raise") -> Iterator[Trace]:
    """Yield :func:`load_trace` of every trace :func:`find_traces` finds under ``root``.

    on_error: ``"raise"`` stops at the first bad trace; ``"skip"`` warns and goes on.
    """
    if on_error not in ("raise", "skip"):
        raise GnssfuseError(f"on_error must be 'raise' or 'skip', got {on_error!r}")
    for path in find_traces(root):
        try:
            yield load_trace(path, signals=signals, fix_truth_height=fix_truth_height, truth=truth,
                             min_sats=min_sats)
        except DataError as exc:
            if on_error == "raise":
                raise
            warnings.warn(f"skipping trace: {exc}", stacklevel=2)
