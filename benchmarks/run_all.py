"""Run every benchmark and the accuracy comparison; write ``benchmarks/results.md``.

    python benchmarks/run_all.py [--quick] [--only wls,graph] [--skip-accuracy] [--update-readme]

1. Every ``benchmarks/bench_*.py`` runs in its own subprocess (a crash or a hang in one cannot take
   the others down) and reports records ``{name, value, unit, note}`` (convention: README.md here).
2. Accuracy: every available mode on the shipped trace and, when ``../shared/data`` (or
   ``$GNSSFUSE_SHARED_DATA``) is present, on its GSDC 2021 traces, via ``fusion.evaluate.evaluate``.
3. The goGPS WLS baseline (the paper's) scored with our metrics against its trace's truth, beside
   our WLS on the same trace.
4. ``--update-readme`` replaces the README text between ``<!-- results:start -->`` and
   ``<!-- results:end -->`` with the results tables.
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import os
import runpy
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run as a script from anywhere without installing
    sys.path.insert(0, str(REPO))

BENCH_DIR = Path(__file__).resolve().parent
SHIPPED_TRACE = REPO / "data" / "gsdc2021" / "train" / "2021-04-28-US-MTV-1" / "Pixel4"
SHARED_DATA = Path(os.environ.get("GNSSFUSE_SHARED_DATA", REPO.parent / "shared" / "data"))
GOGPS_TRACE = "gsdc2021/train/2020-05-14-US-MTV-1/Pixel4"
GOGPS_CSV = "gsdc2021/baselines/2020-05-14-US-MTV-1/Pixel4/goGPS_WLS.csv"
#: Line prefix a benchmark (or the child runner) prints before its JSON list of records.
JSON_PREFIX = "BENCH_JSON "
MARK_START, MARK_END = "<!-- results:start -->", "<!-- results:end -->"
ACCURACY_MODES = ("wls", "dnn", "fused-nodnn", "fused")


# ---------------------------------------------------------------------------- benchmark scripts
def discover(bench_dir: Path = BENCH_DIR, only: list[str] | None = None) -> list[Path]:
    """``bench_*.py`` in ``bench_dir`` (sorted); ``only`` keeps names like ``wls`` or ``bench_wls``."""
    found = sorted(bench_dir.glob("bench_*.py"))
    if only:
        want = {o if o.startswith("bench_") else f"bench_{o}" for o in only}
        found = [p for p in found if p.stem in want]
    return found


def parse_records(stdout: str) -> list[dict] | None:
    """Records from the last ``BENCH_JSON`` line of ``stdout`` (None when there is none)."""
    for line in reversed(stdout.splitlines()):
        if line.startswith(JSON_PREFIX):
            recs = json.loads(line[len(JSON_PREFIX):])
            if isinstance(recs, dict):
                recs = [recs]
            return [normalise(r) for r in recs]
    return None


def normalise(rec: dict) -> dict:
    """Check one record has the convention's keys; fill the optional ones."""
    if not isinstance(rec, dict) or "name" not in rec or "value" not in rec:
        raise ValueError(f"benchmark record needs 'name' and 'value': {rec!r}")
    return {"name": str(rec["name"]), "value": rec["value"], "unit": str(rec.get("unit", "")),
            "note": str(rec.get("note", ""))}


def _child(script: Path, quick: bool) -> int:
    """Run inside the subprocess: call ``run(quick=...)`` if the script has one, else run it as
    ``__main__`` (it must then print its own ``BENCH_JSON`` line). Any exception in ``run`` fails
    the script (a quick run is never silently retried at full size)."""
    spec = importlib.util.spec_from_file_location(script.stem, script)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    if hasattr(mod, "run"):
        recs = mod.run(quick=quick)
        print(JSON_PREFIX + json.dumps([normalise(r) for r in recs], default=float))
        return 0
    # No run(): the script's own __main__ with no arguments (it may not know --quick).
    sys.argv = [str(script)]
    try:
        runpy.run_path(str(script), run_name="__main__")
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    return 0


def run_script(script: Path, quick: bool, timeout_s: float) -> tuple[list[dict], str, str]:
    """(records, error text, the script's stdout). The error is empty on success; records are
    empty on failure (the stdout is kept so a script's printed figures are not lost)."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", str(script)] + (["--quick"] if quick else [])
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
    env.setdefault("OMP_NUM_THREADS", "2")
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, env=env, cwd=REPO)
    except subprocess.TimeoutExpired as exc:
        out = exc.stdout.decode(errors="replace") if isinstance(exc.stdout, bytes) else (exc.stdout or "")
        return [], f"timed out after {timeout_s:.0f} s", out
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        tail = (proc.stderr.strip().splitlines() or ["(no stderr)"])[-1]
        return [], f"exit {proc.returncode}: {tail}", proc.stdout
    try:
        recs = parse_records(proc.stdout)
    except (ValueError, json.JSONDecodeError) as exc:
        return [], f"bad {JSON_PREFIX.strip()} line: {exc}", proc.stdout
    if recs is None:
        return [], f"printed no {JSON_PREFIX.strip()} line and has no run() (output below)", proc.stdout
    recs.append({"name": "wall time (whole script)", "value": round(wall, 2), "unit": "s", "note": ""})
    return recs, "", proc.stdout


# ---------------------------------------------------------------------------- accuracy
def available_modes(modes=ACCURACY_MODES) -> tuple[list[str], dict[str, str]]:
    """Modes whose module imports, and why the others are unavailable."""
    from fusion.errors import GnssfuseError
    from fusion.evaluate import check_modes

    ok, why = [], {}
    for m in modes:
        try:
            check_modes([m])
            ok.append(m)
        except GnssfuseError as exc:
            why[m] = str(exc)
    return ok, why


#: Traces with several constellations in their derived file, also scored with all of them.
MULTI_SIGNAL = {"2021-04-28-US-SJC-1/Pixel4"}
MULTI_SIGNALS = ("GPS_L1", "GLO_G1", "GAL_E1", "BDS_B1I")


def accuracy_traces(shared: Path = SHARED_DATA) -> list[Path]:
    """The shipped trace plus every shared GSDC 2021 train trace with a derived file."""
    traces = [SHIPPED_TRACE] if SHIPPED_TRACE.is_dir() else []
    if shared.is_dir():
        for d in sorted((shared / "gsdc2021" / "train").glob("*/*")):
            if d.is_dir() and list(d.glob("*_derived.csv*")):
                traces.append(d)
    # The shipped trace is also in the shared data: score each <collection>/<phone> once.
    seen, unique = set(), []
    for d in traces:
        key = d.parts[-2:]
        if key not in seen:
            seen.add(key)
            unique.append(d)
    return unique


def run_accuracy(traces: list[Path], modes: list[str], out_dir: Path, max_epochs: int | None,
                 signals: tuple[str, ...] = ("GPS_L1",)):
    """fusion.evaluate.evaluate over ``traces``; returns its metrics table (a DataFrame)."""
    from fusion.run_types import RunOptions
    from fusion.evaluate import evaluate

    df, failures = evaluate(traces, modes, out_dir, RunOptions(signals=signals), max_epochs=max_epochs,
                            progress=False)
    for path, msg in failures.items():
        print(f"accuracy: could not load {path}: {msg}", file=sys.stderr)
    return df


def trained_on(weights: Path | None = None) -> set[str]:
    """``<collection>/<phone>`` names of the real traces the (shipped) network was trained on.

    Read from the checkpoint's own record, so the table can never present in-sample rows as
    held-out ones. Empty when the weights cannot be loaded (the dnn modes are then unavailable).
    """
    try:
        from learned.infer import Corrector

        names = Corrector.load(weights).config.get("data", {}).get("traces", [])
    except Exception:  # noqa: BLE001 - any failure means "no DNN", reported elsewhere
        return set()
    return {n for n in names if not n.startswith("sim/")}


def drop_failed_modes(df, modes: list[str], why: dict[str, str]) -> tuple:
    """A mode that failed on every trace (e.g. no DNN weights yet) is unavailable, not a row.

    Returns new ``(df, modes, why)``: ``df`` without those modes' rows, ``modes`` without them and
    ``why`` plus their first failure message. The arguments are left unchanged, so one group's
    failures do not leak into the next group's modes or note."""
    from fusion.eval.report import ALL

    modes, why = list(modes), dict(why)
    for m in df[(df.trace == ALL) & (df.status == "failed on every trace")]["mode"]:
        first = df[(df["mode"] == m) & (df.trace != ALL)].status.iloc[0]
        why[m] = first.removeprefix("failed: ")
        df = df[df["mode"] != m]
        if m in modes:
            modes.remove(m)
    return df, modes, why


def load_gogps(csv: Path) -> tuple[np.ndarray, np.ndarray]:
    """goGPS_WLS.csv -> (t_ms (N,) int64, ECEF (N, 3) with NaN rows where goGPS had no fix).

    ``GPS Time[s]`` is whole GPS seconds on the same time scale as the truth's
    ``millisSinceGpsEpoch`` / 1000. goGPS solves at the whole second, not at the phone's epoch
    (x.442 s on this trace): scored against truth interpolated to t, the horizontal p50 is lowest
    at an offset of 0-20 ms and grows by ~2.5 m per 100 ms either way (checked at -600..+1500 ms).
    """
    import pandas as pd

    df = pd.read_csv(csv)
    need = ["GPS Time[s]", "ECEF X[m]", "ECEF Y[m]", "ECEF Z[m]"]
    missing = [c for c in need if c not in df.columns]
    if missing:
        from fusion.errors import DataError

        raise DataError(f"{csv}: missing column(s) {missing}")
    t_ms = np.round(df["GPS Time[s]"].to_numpy(float) * 1000).astype(np.int64)
    return t_ms, df[need[1:]].to_numpy(float)


def interp_truth(truth_t_ms: np.ndarray, truth_ecef: np.ndarray, t_ms: np.ndarray,
                 max_gap_ms: float = 1500.0) -> np.ndarray:
    """Truth linearly interpolated to ``t_ms`` (N, 3); NaN outside the truth span or across gaps
    (epochs without truth count as gaps)."""
    from fusion.io.truth import interp_gapped

    ok = np.isfinite(truth_ecef).all(1)
    return interp_gapped(np.asarray(t_ms), truth_t_ms[ok], truth_ecef[ok], max_gap_ms)


def gogps_comparison(shared: Path = SHARED_DATA) -> list[dict] | None:
    """goGPS WLS and our WLS on the goGPS trace, both scored with fusion.eval.metrics. None if absent."""
    from fusion.prepare.load import load_trace
    from fusion.eval.metrics import ned_errors, summarize
    from fusion.estimate.wls import estimate_wls
    from fusion.eval.metrics import mode_metrics
    from fusion.modes import solve_initial
    from fusion.run_types import RunOptions

    csv, trace_dir = shared / GOGPS_CSV, shared / GOGPS_TRACE
    if not (csv.is_file() and trace_dir.is_dir()):
        return None
    # min_sats=1 as gnssfuse run / evaluate load: the epoch counts match the accuracy tables.
    trace = load_trace(trace_dir, min_sats=1)
    t_ms, est = load_gogps(csv)
    truth_at_gogps = interp_truth(trace.t_ms, trace.truth, t_ms)
    rows = [{"method": "goGPS WLS (paper's baseline, its own epochs, truth interpolated)",
             "total": int(t_ms.size), **summarize(ned_errors(est, truth_at_gogps))}]
    opts = RunOptions()
    ours = estimate_wls(trace, solve_initial(trace, opts), opts)
    skips = ", ".join(f"{k}={v}" for k, v in trace.skipped.items())
    rows.append({"method": f"gnssfuse WLS ({opts.wls_weighting} weights, {opts.elev_mask_deg:g} deg mask)"
                 + (f"; loader skipped {skips}" if skips else ""), "total": trace.n_epochs,
                 **mode_metrics(trace, ours)})
    return rows


# ---------------------------------------------------------------------------- markdown
def _f(x, spec=".2f") -> str:
    try:
        return "n/a" if x is None or not np.isfinite(float(x)) else format(float(x), spec)
    except (TypeError, ValueError):
        return str(x)


def bench_markdown(results: dict[str, tuple[list[dict], str, str]], tail_lines: int = 40) -> str:
    """Records as one table; for scripts without records, their error and last output lines."""
    lines = ["| benchmark | figure | value | unit | note |", "|---|---|---|---|---|"]
    raw = []
    for script, (recs, err, stdout) in results.items():
        if err:
            lines.append(f"| {script} | **no records** | | | {err.replace('|', '/')} |")
            if stdout.strip():
                tail = "\n".join(stdout.rstrip().splitlines()[-tail_lines:])
                raw += [f"<details><summary>{script} output</summary>", "", "```", tail, "```",
                        "", "</details>", ""]
        for r in recs:
            v = r["value"]
            val = _f(v, ".4g") if isinstance(v, (int, float)) else str(v)
            lines.append(f"| {script} | {r['name']} | {val} | {r['unit']} | {r['note'].replace('|', '/')} |")
    return "\n".join(lines + ([""] + raw if raw else []))


def accuracy_markdown(df) -> str:
    from fusion.eval.report import markdown_table

    return markdown_table(df)


def gogps_markdown(rows: list[dict]) -> str:
    lines = ["| method | MAE N ± std [m] | MAE E ± std [m] | MAE D ± std [m] | horiz p50 [m] | "
             "horiz p95 [m] | GSDC score [m] | scored / total epochs |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        axes = [f"{_f(r[f'mae_{a}'])} ± {_f(r[f'std_{a}'])}" for a in "ned"]
        lines.append(f"| {r['method']} | " + " | ".join(axes) + f" | {_f(r['h_p50'])} | {_f(r['h_p95'])} "
                     f"| {_f(r['gsdc_score'])} | {r['n']} / {r['total']} |")
    return "\n".join(lines)


def results_markdown(sections: list[tuple[str, str]], header: str = "") -> str:
    out = [header] if header else []
    for title, body in sections:
        out += [f"### {title}", "", body, ""]
    return "\n".join(out).rstrip() + "\n"


def replace_between_markers(text: str, new: str, start: str = MARK_START, end: str = MARK_END) -> str:
    """``text`` with everything between the markers replaced by ``new`` (markers kept).

    Raises ValueError when a marker is missing, repeated or out of order: a README without them
    must not be rewritten by guesswork.
    """
    if text.count(start) != 1 or text.count(end) != 1:
        raise ValueError(f"expected exactly one {start} and one {end}, found "
                         f"{text.count(start)} and {text.count(end)}")
    i, j = text.index(start) + len(start), text.index(end)
    if j < i:
        raise ValueError(f"{end} comes before {start}")
    return text[:i] + "\n" + new.strip("\n") + "\n" + text[j:]


def update_readme(readme: Path, new: str) -> None:
    readme.write_text(replace_between_markers(readme.read_text(), new))


# ---------------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="benchmarks/run_all.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="small sizes everywhere (minutes, not hours)")
    p.add_argument("--bench-dir", type=Path, default=BENCH_DIR, help="where the bench_*.py scripts are")
    p.add_argument("--only", default="", help="comma-separated benchmark names, e.g. wls,graph")
    p.add_argument("--skip-benchmarks", action="store_true", help="accuracy comparison only")
    p.add_argument("--skip-accuracy", action="store_true", help="benchmark scripts only")
    p.add_argument("--timeout", type=float, default=1800.0, help="per benchmark script [s]")
    p.add_argument("--max-epochs", type=int, default=None, help="accuracy: first N epochs per trace "
                   "(default: all; --quick: 300)")
    p.add_argument("--out", type=Path, default=REPO / "runs" / "benchmarks", help="report folder")
    p.add_argument("--results", type=Path, default=BENCH_DIR / "results.md")
    p.add_argument("--update-readme", nargs="?", const=REPO / "README.md", type=Path, default=None,
                   metavar="README", help="rewrite the results section between the markers")
    p.add_argument("--child", type=Path, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        return _child(args.child, args.quick)

    sections: list[tuple[str, str]] = []
    started = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    if not args.skip_benchmarks:
        results = {}
        for script in discover(args.bench_dir, only=[o for o in args.only.split(",") if o] or None):
            print(f"running {script.name} ...", flush=True)
            results[script.name] = run_script(script, args.quick, args.timeout)
            if results[script.name][1]:
                print(f"  {script.name} failed: {results[script.name][1]}", file=sys.stderr)
        sections.append(("Benchmarks", bench_markdown(results) if results else "No bench_*.py found."))
    if not args.skip_accuracy:
        modes, why = available_modes()
        traces = accuracy_traces()
        max_epochs = args.max_epochs or (300 if args.quick else None)
        if traces and modes:
            seen = trained_on()
            name = lambda d: "/".join(d.parts[-2:])  # noqa: E731
            held_out = [d for d in traces if name(d) not in seen]
            in_sample = [d for d in traces if name(d) in seen]
            multi = [d for d in held_out if name(d) in MULTI_SIGNAL]
            groups = [("held-out traces (never trained or tuned on)", held_out, ("GPS_L1",), "held_out"),
                      (f"held-out, multi-signal ({','.join(MULTI_SIGNALS)})", multi, MULTI_SIGNALS, "multi"),
                      ("training traces (IN-SAMPLE for dnn and fused: the shipped network was trained on "
                       "them and the graph tuned on them)", in_sample, ("GPS_L1",), "training")]
            common = (f"Modes {', '.join(modes)}; initial guess from WLS, clock estimated "
                      f"(honest protocol). " + (f"First {max_epochs} epochs per trace. " if max_epochs else ""))
            for title, group, signals, slug in groups:
                if not group:
                    continue
                print(f"accuracy: {slug}: modes {','.join(modes)} on {len(group)} trace(s) ...", flush=True)
                df, _, group_why = drop_failed_modes(
                    run_accuracy(group, list(modes), args.out / slug, max_epochs, signals), modes, why)
                note = (common + "".join(f"Mode {m} unavailable: {w}. " for m, w in group_why.items())
                        + f"Figures: `{os.path.relpath(args.out / slug / 'report.md', REPO)}`.")
                sections.append((f"Accuracy by mode: {title}", note + "\n\n" + accuracy_markdown(df)))
        else:
            sections.append(("Accuracy by mode", "No trace found (shipped trace missing, no shared data)."))
        gogps = gogps_comparison()
        if gogps is not None:
            sections.append(("goGPS WLS baseline vs gnssfuse WLS (2020-05-14-US-MTV-1 Pixel4)",
                             "Both scored with `fusion.eval.metrics` against the truth `fusion.prepare.load` "
                             "loads for the trace (SPAN NMEA where present, else ground_truth.csv with "
                             "the 63 m height fix). goGPS reports at whole GPS seconds; its truth "
                             "is interpolated to those times.\n\n" + gogps_markdown(gogps)))
    header = (f"Generated by `python benchmarks/run_all.py {' '.join(argv if argv is not None else sys.argv[1:])}`"
              f" on {started}.\n")
    text = results_markdown(sections, header)
    args.results.write_text("# gnssfuse benchmark results\n\n" + text)
    print(text)
    print(f"wrote {args.results}")
    if args.update_readme:
        update_readme(args.update_readme, text)
        print(f"updated {args.update_readme}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
