"""The evaluate job: compare modes on one or more traces and write a report folder (the command
line is :mod:`fusion.cli.evaluate`).

Every requested mode (``--modes``, any name in :data:`fusion.modes.MODES`) is run on the same trace
and the same WLS solution (:func:`fusion.modes.run_modes`), so a new mode can be requested here with
no change to this file. Truth is used only to score: never passed to a mode. The report's layout
is in :mod:`fusion.eval.report`.
"""
from __future__ import annotations

import re
import shutil
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
from tqdm import tqdm

from fusion.options import load_options
from fusion.errors import DataError, GnssfuseError
from fusion.estimate.wls import WlsResult, wls_counts
from fusion.eval.metrics import mode_metrics, trace_errors
from fusion.eval.report import (TraceEval, markdown_table, metrics_table, write_figures, write_report_md,
                                write_trace_figures)
from fusion.io.estimates import write_outputs
from fusion.prepare.load import load_trace, trace_name
from fusion.modes import MODES, get_mode, run_modes, solve_initial
from fusion.parallel import check_pace, map_traces
from fusion.run_types import RunOptions
from fusion.trace import Trace


def check_modes(modes: list[str]) -> None:
    """Fail before any work when a mode is unknown or its module cannot be imported."""
    for m in modes:
        get_mode(m)


def _slug(name: str, taken: set[str]) -> str:
    base = re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("_") or "trace"
    slug, k = base, 2
    while slug in taken:
        slug, k = f"{base}_{k}", k + 1
    taken.add(slug)
    return slug


def run_trace(trace: Trace, modes: list[str], opts: RunOptions, wls: WlsResult | None = None,
              progress: bool = True) -> TraceEval:
    """Run every mode on ``trace`` (one shared WLS) and keep the results; writes nothing.

    A mode that raises one of our input errors on this trace is recorded in ``failed`` and the
    others still run: one bad mode must not lose the rest of the report.
    """
    ev = TraceEval(trace=trace, slug="")
    wls = solve_initial(trace, opts) if wls is None else wls
    ev.wls_reasons = dict(getattr(wls, "reasons", {}) or {})
    if isinstance(wls, WlsResult):
        ev.wls_counts = wls_counts(wls)
    for mode in tqdm(modes, desc=f"  {trace.name}", leave=False, disable=not progress):
        try:
            ev.results[mode] = run_modes(trace, [mode], opts, wls=wls)[mode]
        except GnssfuseError as exc:
            ev.failed[mode] = str(exc)
    return ev


def write_trace(ev: TraceEval, out_dir: Path, slug: str) -> TraceEval:
    """Write each mode's estimates (+ metrics.json) under ``out_dir/slug`` and collect its errors."""
    ev.slug = slug
    for mode, result in ev.results.items():
        ev.records[mode] = write_outputs(out_dir / slug / mode, ev.trace, mode, result,
                                         mode_metrics(ev.trace, result))
        err = trace_errors(ev.trace, result)
        if err is not None:
            ev.errors[mode] = err
    return ev


def evaluate_trace(trace: Trace, modes: list[str], opts: RunOptions, out_dir: Path, slug: str,
                   wls: WlsResult | None = None, progress: bool = True) -> TraceEval:
    """:func:`run_trace` then :func:`write_trace`."""
    return write_trace(run_trace(trace, modes, opts, wls, progress), out_dir, slug)


def load_and_run(d: Path, slug: str, modes: list[str], opts: RunOptions, max_epochs: int | None,
                 fix_truth_height: bool, out_dir: Path, progress: bool = False) -> TraceEval | str:
    """One trace folder start to finish (what a worker process does): load, run every mode, write
    its estimates and figures under ``out_dir``; the :class:`TraceEval`, or the one-line reason the
    trace could not be loaded."""
    try:
        # min_sats=1: epochs with < 4 satellites reach the modes (the fused ones carry them)
        trace = load_trace(d, fix_truth_height=fix_truth_height, min_sats=1, **load_options(opts))
        if trace.n_epochs == 0:
            raise DataError(f"{d}: no epochs with {', '.join(opts.signals or ['the default signals'])} "
                            "measurements")
    except GnssfuseError as exc:
        return str(exc)
    if max_epochs is not None and trace.n_epochs > max_epochs:
        trace = trace.select(np.arange(max_epochs))
    if slug != _slug(trace_name(d), set()):     # run_all numbered it: another trace of its name is in the run
        trace.name = f"{trace.name} ({d})"
    ev = write_trace(run_trace(trace, modes, opts, progress=progress), out_dir, slug)
    ev.figures = write_trace_figures(ev, out_dir / "figures")
    return ev


def run_all(trace_dirs: list[Path], modes: list[str], opts: RunOptions, max_epochs: int | None,
            fix_truth_height: bool, progress: bool, jobs: int, out_dir: Path,
            scheduler: str | None = None) -> list[TraceEval | str]:
    """:func:`load_and_run` on every folder through :func:`fusion.parallel.map_traces` (here, in
    ``jobs`` processes, or on the Dask cluster at ``scheduler``). Output folders are named (slugs)
    here, before any work, so that they do not depend on where the traces run."""
    taken: set[str] = set()
    here = jobs == 1 and scheduler is None          # only then can a trace's own mode bars be shown
    # a cluster's workers have working directories of their own: absolute paths
    place = Path if scheduler is None else (lambda p: Path(p).absolute())
    opts = opts if scheduler is None else opts.with_absolute_paths()
    args = [(place(d), _slug(trace_name(d), taken), modes, opts, max_epochs, fix_truth_height, place(out_dir),
             progress and here) for d in trace_dirs]
    return map_traces(load_and_run, args, jobs, progress, costs=[_input_bytes(Path(d)) for d in trace_dirs],
                      scheduler=scheduler)


def _input_bytes(trace_dir: Path) -> int:
    """Bytes of the files under ``trace_dir``: the proxy for a trace's run time that orders the
    ``--jobs`` workers' calls (the longest first)."""
    try:
        return sum(f.stat().st_size for f in trace_dir.rglob("*") if f.is_file())
    except OSError:
        return 0


def once_each(trace_dirs: list[Path]) -> list[Path]:
    """The traces without repeats (the same path twice, e.g. from overlapping shell globs, would count twice in
    the ALL rows), each repeat warned about."""
    seen, out = set(), []
    for d in trace_dirs:
        key = Path(d).resolve()
        if key in seen:
            warnings.warn(f"{d}: given more than once; evaluated once", stacklevel=3)
            continue
        seen.add(key)
        out.append(d)
    return out


def clear_earlier_run(out_dir: Path) -> None:
    """Remove what an earlier ``evaluate`` wrote into ``out_dir`` (where its ``report.md`` is): its trace folders
    (each holding ``<mode>/metrics.json``, mode folders only), figures and tables, saying so, so that no trace or
    figure of that run passes for one of this; anything else in the folder stays."""
    tables = [out_dir / n for n in ("report.md", "metrics.csv", "metrics.md") if (out_dir / n).is_file()]
    if not (out_dir / "report.md").is_file():
        return                                              # no evaluation wrote here: touch nothing
    traces = [d for d in out_dir.iterdir() if d.is_dir() and any(d.glob("*/metrics.json"))
              and all(m.name in MODES for m in d.iterdir() if m.is_dir())]
    for d in traces + ([out_dir / "figures"] if (out_dir / "figures").is_dir() else []):
        shutil.rmtree(d)
    for f in tables:
        f.unlink()
    warnings.warn(f"{out_dir}: removed an earlier evaluation's outputs ({len(traces)} trace folder(s), its "
                  "figures and tables)", stacklevel=2)


def evaluate(trace_dirs: list[Path], modes: list[str], out_dir: Path, opts: RunOptions,
             max_epochs: int | None = None, fix_truth_height: bool = True, progress: bool = True,
             argv: list[str] | None = None, jobs: int = 1,
             scheduler: str | None = None) -> tuple[pd.DataFrame, dict[str, str]]:
    """Load, run, tabulate, plot and write the report. Returns (metrics table, load failures).

    A trace that fails to load is reported and skipped; only when none loads is it an error.
    ``jobs`` > 1 runs traces in that many worker processes (:mod:`fusion.parallel`), ``scheduler``
    (a Dask scheduler's address) on that cluster's workers (:mod:`fusion.cluster`); the tables are
    the same as with one process.
    """
    check_modes(modes)
    missing = [str(d) for d in trace_dirs if not Path(d).exists()]      # a folder, or a log / file in one
    if missing:
        raise DataError(f"trace folder(s) or file(s) not found: {', '.join(missing)}")
    trace_dirs = once_each(trace_dirs)
    if max_epochs is not None and max_epochs < 1:
        raise GnssfuseError("--max-epochs must be >= 1")
    check_pace(jobs, scheduler)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    clear_earlier_run(out_dir)
    outcomes = run_all(trace_dirs, modes, opts, max_epochs, fix_truth_height, progress, jobs, out_dir, scheduler)
    evals = [o for o in outcomes if not isinstance(o, str)]
    failures = {str(d): o for d, o in zip(trace_dirs, outcomes) if isinstance(o, str)}
    if not evals:
        raise DataError("no trace could be evaluated: " + "; ".join(f"{d}: {m}" for d, m in failures.items()))
    df = metrics_table(evals, modes)
    df.to_csv(out_dir / "metrics.csv", index=False, float_format="%.4f")
    (out_dir / "metrics.md").write_text(markdown_table(df) + "\n")
    figs = write_figures(evals, out_dir / "figures", jobs)
    write_report_md(out_dir, df, evals, figs, modes, opts, argv or [], failures)
    return df, failures
