"""The evaluation report: metrics tables (per trace and pooled), figures and ``report.md``.

Output layout (``gnssfuse evaluate --out REPORT_DIR``; :mod:`fusion.evaluate` runs the modes)::

    report.md                     ties everything together (relative links)
    metrics.csv / metrics.md      one row per (trace, mode) plus pooled "ALL" rows
    figures/*.png                 CDFs, box plots, trajectories, error vs time (pooled ones with > 1 trace)
    <trace>/<mode>/estimates.csv  the ``gnssfuse run`` format, + metrics.json
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from fusion.eval import plots
from fusion.eval.metrics import summarize
from fusion.eval.summary import DATUM, LEARNED_WORDS, bridged_words, incremental_words, skip_words
from fusion.run_types import ModeResult, RunOptions
from fusion.trace import Trace

#: Name of the pooled rows (all traces' epochs together) in the tables.
ALL = "ALL"
METRIC_KEYS = ["mae_n", "std_n", "mae_e", "std_e", "mae_d", "std_d", "h_p50", "h_p95", "gsdc_score"]
TABLE_COLUMNS = (["trace", "mode", "status", "epochs_total", "epochs_solved", "epochs_unsolved",
                  "epochs_scored"] + METRIC_KEYS + ["skipped_at_load"])


@dataclass
class TraceEval:
    """One trace evaluated in every requested mode.

    results: mode -> ModeResult (modes that failed are absent and listed in ``failed``).
    errors:  mode -> (E, 3) NED error [m] (NaN where unsolved or no truth); empty without truth.
    records: mode -> the record :func:`fusion.io.estimates.write_outputs` returned.
    """

    trace: Trace
    slug: str
    results: dict[str, ModeResult] = field(default_factory=dict)
    errors: dict[str, np.ndarray] = field(default_factory=dict)
    records: dict[str, dict] = field(default_factory=dict)
    failed: dict[str, str] = field(default_factory=dict)
    wls_reasons: dict[str, int] = field(default_factory=dict)
    figures: dict[str, Path] = field(default_factory=dict)   # kind -> PNG, once drawn
    wls_counts: dict[str, int] = field(default_factory=dict)  # fusion.estimate.wls.wls_counts


# ---------------------------------------------------------------------------- tables
def _skip_text(skipped: dict[str, int]) -> str:
    return ";".join(f"{k}={v}" for k, v in sorted(skipped.items()))


def metrics_table(evals: list[TraceEval], modes: list[str]) -> pd.DataFrame:
    """One row per (trace, mode) with the metrics of :func:`fusion.eval.metrics.summarize`, then one
    pooled row per mode (``trace == "ALL"``: every scored epoch of every trace together)."""
    rows = []
    for ev in evals:
        for mode in modes:
            row = {"trace": ev.trace.name, "mode": mode, "epochs_total": ev.trace.n_epochs,
                   "skipped_at_load": _skip_text(ev.trace.skipped)}
            if mode in ev.failed:
                row.update(status=f"failed: {ev.failed[mode]}")
            else:
                rec = ev.records[mode]
                solved = rec["epochs_solved"]
                row.update(epochs_solved=solved, epochs_unsolved=ev.trace.n_epochs - solved)
                m = rec["metrics"]
                if m is None:
                    row.update(status="no truth: metrics unavailable")
                else:
                    row.update(status="ok", epochs_scored=m["n"], **{k: m[k] for k in METRIC_KEYS})
            rows.append(row)
    for mode in modes:
        errs = [ev.errors[mode] for ev in evals if mode in ev.errors]
        have = [ev for ev in evals if mode in ev.records]
        total = sum(ev.trace.n_epochs for ev in evals)
        solved = sum(ev.records[mode]["epochs_solved"] for ev in have)
        row = {"trace": ALL, "mode": mode, "epochs_total": total, "epochs_solved": solved,
               "epochs_unsolved": sum(ev.trace.n_epochs for ev in have) - solved,
               "skipped_at_load": _skip_text(_sum_skips(evals))}
        if not have:
            row.update(status="failed on every trace", epochs_solved=None, epochs_unsolved=None)
        elif errs:
            m = summarize(np.concatenate(errs))
            # a mode that failed on some traces pools the others only: its ALL row is not the others' ALL rows
            part = "" if len(have) == len(evals) else f" over {len(have)} of {len(evals)} traces (failed on the rest)"
            row.update(status="ok" + part, epochs_scored=m["n"], **{k: m[k] for k in METRIC_KEYS})
        else:
            row.update(status="no truth: metrics unavailable")
        rows.append(row)
    df = pd.DataFrame(rows).reindex(columns=TABLE_COLUMNS)
    for c in ("epochs_total", "epochs_solved", "epochs_unsolved", "epochs_scored"):
        df[c] = df[c].astype("Int64")
    return df


def _sum_skips(evals: list[TraceEval]) -> dict[str, int]:
    out: dict[str, int] = {}
    for ev in evals:
        for k, v in ev.trace.skipped.items():
            out[k] = out.get(k, 0) + int(v)
    return out


def _fmt(x, spec: str = ".2f") -> str:
    return "n/a" if x is None or pd.isna(x) else format(x, spec)


def markdown_table(df: pd.DataFrame) -> str:
    """The metrics table as GitHub markdown: MAE ± std per axis, horizontal p50/p95, score."""
    head = ("| trace | mode | MAE N ± std [m] | MAE E ± std [m] | MAE D ± std [m] | horiz p50 [m] "
            "| horiz p95 [m] | GSDC score [m] | scored / solved / total epochs | skipped at load |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in df.itertuples(index=False):
        if str(r.status).startswith("ok"):
            axes = [f"{_fmt(getattr(r, f'mae_{a}'))} ± {_fmt(getattr(r, f'std_{a}'))}" for a in "ned"]
            tail = [_fmt(r.h_p50), _fmt(r.h_p95), _fmt(r.gsdc_score)]
        else:
            axes, tail = [r.status] + ["", ""], ["", "", ""]
        counts = f"{_fmt(r.epochs_scored, 'd')} / {_fmt(r.epochs_solved, 'd')} / {_fmt(r.epochs_total, 'd')}"
        name = f"**{r.trace}**" if r.trace == ALL else r.trace
        name += f" ({r.status[3:]})" if str(r.status).startswith("ok ") else ""
        lines.append("| " + " | ".join([name, r.mode, *axes, *tail, counts, r.skipped_at_load or "-"]) + " |")
    return "\n".join(lines)


# ---------------------------------------------------------------------------- figures
def write_trace_figures(ev: TraceEval, fig_dir: Path) -> dict[str, Path]:
    """One trace's PNGs (CDF, box, error vs time with truth; trajectory always): kind -> path."""
    f: dict[str, Path] = {}
    title = ev.trace.name
    t_s = (ev.trace.t_ms - ev.trace.t_ms[0]) / 1000.0
    if ev.errors:
        f["cdf"] = plots.plot_error_cdfs(ev.errors, fig_dir / f"{ev.slug}_cdf.png", title)
        f["box"] = plots.plot_error_boxes(ev.errors, fig_dir / f"{ev.slug}_box.png", title)
        f["time"] = plots.plot_error_vs_time(t_s, ev.errors, fig_dir / f"{ev.slug}_time.png", title)
    positions = {m: np.where(r.valid[:, None], r.pos, np.nan) for m, r in ev.results.items()}
    truth = ev.trace.truth if ev.trace.has_truth else None
    f["traj"] = plots.plot_trajectories(positions, truth, fig_dir / f"{ev.slug}_traj.png", title, t_s=t_s)
    return f


#: The pooled figures: kind -> plotting function ``(errors, path, title) -> path``.
POOLED = {"cdf": plots.plot_error_cdfs, "box": plots.plot_error_boxes}


def pooled_figure(kind: str, errors: dict[str, np.ndarray], path: Path, title: str) -> Path:
    """One pooled figure (a worker's job with ``--jobs``)."""
    return POOLED[kind](errors, path, title)


def write_pooled_figures(evals: list[TraceEval], fig_dir: Path, jobs: int = 1) -> dict[str, Path]:
    """Every trace's epochs together (CDF, box): kind -> path; empty unless at least two traces have
    truth (one trace's pooled figure would repeat its own). With ``jobs`` > 1 the figures are drawn
    in that many worker processes (a second each: it would be serial time)."""
    if sum(1 for ev in evals if ev.errors) < 2:
        return {}
    pooled: dict[str, list[np.ndarray]] = {}
    for ev in evals:
        for m, e in ev.errors.items():
            pooled.setdefault(m, []).append(e)
    if not pooled:
        return {}
    errors = {m: np.concatenate(v) for m, v in pooled.items()}
    title = f"all traces with truth ({sum(1 for ev in evals if ev.errors)})"
    args = [(kind, errors, fig_dir / f"all_{kind}.png", title) for kind in POOLED]
    from fusion.parallel import guarded, map_traces
    drawn = ([guarded(pooled_figure, *a) for a in args] if jobs == 1
             else map_traces(pooled_figure, args, min(jobs, len(args))))
    for a, d in zip(args, drawn):
        if isinstance(d, str):      # the tables and report.md are still written without it
            warnings.warn(f"{a[2]}: not drawn: {d}", stacklevel=2)
    return {a[0]: d for a, d in zip(args, drawn) if not isinstance(d, str)}


def write_figures(evals: list[TraceEval], fig_dir: Path, jobs: int = 1) -> dict[str, dict[str, Path]]:
    """All PNGs: per trace (CDF, box, trajectory, error vs time) and, with two traces or more, pooled (CDF, box).

    Returns section -> figure kind -> path; section is a trace slug or ``ALL``. Per-trace figures
    already drawn (``TraceEval.figures``, e.g. by a worker process) are not drawn again.
    """
    figs = {ev.slug: ev.figures or write_trace_figures(ev, fig_dir) for ev in evals}
    pooled = write_pooled_figures(evals, fig_dir, jobs)
    if pooled:
        figs[ALL] = pooled
    return figs


# ---------------------------------------------------------------------------- report.md
FIG_CAPTIONS = {
    "cdf": "Error CDFs (|N|, |E|, |D|, horizontal)",
    "box": "Quantile box plots of signed N/E/D errors",
    "traj": "Trajectories in a local east/north frame",
    "time": "Error vs time",
}


def _trace_section(ev: TraceEval, figs: dict[str, str]) -> list[str]:
    """report.md's section of one trace: what WLS did, its estimates and its figures (kind -> link)."""
    lines = [f"## {ev.trace.name}", ""]
    if ev.wls_reasons:
        lines += [f"WLS epochs not solved, by reason: {skip_words(ev.wls_reasons)}", ""]
    if ev.wls_counts:
        c = ev.wls_counts
        lines += [f"WLS fault detection and exclusion: {c['excluded_measurements']} measurements excluded "
                  f"in {c['epochs_with_exclusions']} epochs; {c['epochs_fault_undecided']} epochs where the "
                  f"test could not decide (kept, Huber-weighted); {c['epochs_clock_predicted']} three-satellite "
                  "epochs solved with the clock interpolated from their neighbours.", ""]
    for mode, rec in ev.records.items():
        info = (rec or {}).get("info") or {}
        said = [f"{mode}: {words(info)}." for key, words in LEARNED_WORDS if key in info]
        said += [f"{mode}: {bridged_words(info)}."] if info.get("epochs_bridged") else []
        said += [f"{mode}: {inc}."] if (inc := incremental_words(info)) else []
        lines += said + [""] if said else []
    if not ev.errors:
        lines += ["No ground truth: metrics unavailable; estimates are still written.", ""]
    lines += ["Estimates: " + ", ".join(f"[{m}]({ev.slug}/{m}/estimates.csv)" for m in ev.results), ""]
    for kind, link in figs.items():
        lines += [f"### {FIG_CAPTIONS[kind]}", "", f"![{kind}]({link})", ""]
    return lines


def calibration_lines(evals: list[TraceEval], modes: list[str]) -> list[str]:
    """report.md's calibration table: per trace and mode with a covariance, the share of errors within 1 and
    2 sigma per NED axis (a Gaussian: 0.68 / 0.95); no lines when no mode has a covariance."""
    rows = []
    for ev in evals:
        for mode in modes:
            m = (ev.records.get(mode) or {}).get("metrics") or {}
            if "within1sigma_n" in m:
                one = " / ".join(f"{m[f'within1sigma_{a}']:.2f}" for a in "ned")
                two = " / ".join(f"{m[f'within2sigma_{a}']:.2f}" for a in "ned")
                rows.append(f"| {ev.trace.name} | {mode} | {one} | {two} | {m['n_cov']} |")
    if not rows:
        return []
    return ["## Calibration", "", "Share of the errors within 1 and 2 of the mode's own sigmas, per NED axis "
            "(a Gaussian: 0.68 and 0.95); judge per trace and axis.", "",
            "| trace | mode | within 1 sigma N / E / D | within 2 sigma N / E / D | epochs |",
            "|---|---|---|---|---|", *rows, ""]


def write_report_md(out_dir: Path, df: pd.DataFrame, evals: list[TraceEval], figs: dict,
                    modes: list[str], opts: RunOptions, argv: list[str],
                    load_failures: dict[str, str]) -> Path:
    def rel(p: Path) -> str:
        return Path(p).relative_to(out_dir).as_posix()

    ok = df[(df.trace != ALL) & (df.status == "ok")]
    lines = [
        "# gnssfuse evaluation report", "",
        f"Command: `gnssfuse evaluate {' '.join(argv)}`", "",
        f"Modes: {', '.join(modes)}. Signals: {', '.join(opts.signals or ['format default'])}. Elevation mask: "
        f"{opts.elev_mask_deg:g} deg. DNN weights: {opts.weights or 'shipped'}; DNN passes: "
        f"{opts.dnn_passes}; incremental graph: {opts.incremental}.", "",
        "Every mode starts from the same WLS solution (receiver clock estimated, never taken from "
        "truth); truth is used only for the metrics below. Errors are in the NED frame of the truth "
        f"point. {DATUM} MAE ± std is the mean and standard deviation of the absolute per-axis error. "
        "GSDC score = (horizontal p50 + p95) / 2. The **ALL** rows pool every scored epoch of "
        "every trace.", "",
    ]
    if len(ok):
        kaggle = ok.groupby("mode", sort=False)["gsdc_score"].mean()
        lines += ["Kaggle-style score (mean over traces of each trace's GSDC score): "
                  + ", ".join(f"{m} {kaggle[m]:.2f} m" for m in modes if m in kaggle.index), ""]
    lines += ["## Metrics", "", markdown_table(df), "",
              "Machine-readable: [metrics.csv](metrics.csv). Epoch counts: *scored* have truth and a "
              "solution, *solved* have a solution; *skipped at load* are rows/epochs the loader "
              "dropped, by reason.", ""]
    lines += calibration_lines(evals, modes)
    if load_failures:
        lines += ["## Traces that could not be evaluated", ""]
        lines += [f"- `{p}`: {msg}" for p, msg in load_failures.items()] + [""]
    failed = [(ev.trace.name, m, msg) for ev in evals for m, msg in ev.failed.items()]
    if failed:
        lines += ["## Modes that failed", ""] + [f"- {t} / {m}: {msg}" for t, m, msg in failed] + [""]
    if ALL in figs:
        lines += ["## All traces", ""]
        for kind, p in figs[ALL].items():
            lines += [f"### {FIG_CAPTIONS[kind]}", "", f"![{kind}]({rel(p)})", ""]
    for ev in evals:
        lines += _trace_section(ev, {k: rel(p) for k, p in figs.get(ev.slug, {}).items()})
    lines += [f"CDF x-axes and error-vs-time y-axes stop at the {plots.CDF_CLIP_PCT:g}th percentile of the "
              "pooled errors (the curves use every epoch; each panel states how many points lie beyond). "
              "Box plots: box Q1–Q3 with the median, whiskers at 1.5×IQR, outliers as dots; outliers beyond the "
              "plotted range are counted in the panel title.", ""]
    path = out_dir / "report.md"
    path.write_text("\n".join(lines))
    return path
