"""``gnssfuse evaluate``: tables, figures, report.md, no-truth traces, bad input; plots; run_all."""
from __future__ import annotations

import importlib.util
import json
import re
import shutil
import sys
import types
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from fusion import cli, modes
from fusion.io.estimates import ESTIMATE_COLUMNS, SIGMA_COLUMNS
from fusion.run_types import ModeResult, RunOptions
from fusion.geometry import geodetic2ecef, ned2ecef_vec
from fusion.eval.metrics import ned_errors, summarize
from fusion.eval import report
from fusion.eval.report import ALL, METRIC_KEYS, metrics_table
from fusion.evaluate import evaluate_trace
from fusion.trace import Trace, empty_trace

REPO = Path(__file__).resolve().parents[2]
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
N_EPOCHS = 200


def _need(path: Path) -> Path:
    if not path.is_dir():
        pytest.skip(f"shipped trace missing at {path}")
    return path


@pytest.fixture(scope="module")
def wls_report(tmp_path_factory, shipped_trace_dir):
    """One evaluate run on the first 200 epochs of the shipped trace (shared by several tests)."""
    trace_dir = _need(shipped_trace_dir)
    out = tmp_path_factory.mktemp("report")
    rc = cli.main(["evaluate", str(trace_dir), "--modes", "wls", "--out", str(out),
                   "--max-epochs", str(N_EPOCHS), "--no-progress"])
    return rc, out, trace_dir


def test_report_writes_tables_figures_and_report_md(wls_report):
    rc, out, _ = wls_report
    assert rc == 0
    for name in ("report.md", "metrics.csv", "metrics.md"):
        assert (out / name).is_file(), name
    figs = sorted((out / "figures").glob("*.png"))
    kinds = {p.stem.rsplit("_", 1)[-1] for p in figs}
    assert kinds == {"cdf", "box", "traj", "time"}
    assert not any(p.name.startswith("all_") for p in figs)      # one trace: no pooled figures
    for p in figs:
        assert p.read_bytes()[:8] == PNG_MAGIC and p.stat().st_size > 5000, p
    # report.md links every figure with a relative path that resolves, and links nothing missing
    md = (out / "report.md").read_text()
    links = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", md)
    assert sorted(out / link for link in links) == figs
    assert all(not Path(link).is_absolute() for link in links)
    for link in re.findall(r"\]\(([^)]+estimates\.csv)\)", md):
        assert (out / link).is_file()
    table = pd.read_csv(out / "metrics.csv")
    assert list(table.trace) == ["2021-04-28-US-MTV-1/Pixel4", ALL]
    assert (table.status == "ok").all()
    assert "MAE N ± std" in (out / "metrics.md").read_text()


def test_table_metrics_equal_summarize_of_estimates(wls_report):
    from fusion.prepare.load import load_trace

    _, out, trace_dir = wls_report
    trace = load_trace(trace_dir, min_sats=1)          # as evaluate loads it
    trace = trace.select(np.arange(min(N_EPOCHS, trace.n_epochs)))
    est = pd.read_csv(out / "2021-04-28-US-MTV-1_Pixel4" / "wls" / "estimates.csv")
    assert list(est.columns) == ESTIMATE_COLUMNS + SIGMA_COLUMNS          # WLS gives a covariance
    pos = np.full((trace.n_epochs, 3), np.nan)
    idx = np.searchsorted(trace.t_ms, est.gps_millis.to_numpy())
    assert np.array_equal(trace.t_ms[idx], est.gps_millis.to_numpy())
    pos[idx] = est[["x_m", "y_m", "z_m"]].to_numpy()
    expected = summarize(ned_errors(pos, trace.truth))
    table = pd.read_csv(out / "metrics.csv").set_index("trace")
    for key in METRIC_KEYS:
        for row in ("2021-04-28-US-MTV-1/Pixel4", ALL):  # one trace: pooled == per-trace
            # estimates.csv keeps 10 significant digits: ~1 mm at ECEF scale
            assert table.loc[row, key] == pytest.approx(expected[key], abs=2e-3), (row, key)
    assert table.loc[ALL, "epochs_scored"] == expected["n"]
    assert table.loc[ALL, "epochs_total"] == trace.n_epochs
    solved = len(est)
    assert table.loc[ALL, "epochs_solved"] == solved
    assert table.loc[ALL, "epochs_unsolved"] == trace.n_epochs - solved


def _no_truth_copy(src: Path, dst_root: Path, n_epochs: int = 60) -> Path:
    """The first epochs of the shipped derived file in a folder with no ground truth."""
    derived = next(src.glob("*_derived.csv*"))
    df = pd.read_csv(derived)
    first = np.sort(df.millisSinceGpsEpoch.unique())[:n_epochs]
    d = dst_root / "2099-01-01-NO-TRUTH" / "Pixel4"
    d.mkdir(parents=True)
    df[df.millisSinceGpsEpoch.isin(first)].to_csv(d / "Pixel4_derived.csv", index=False)
    return d


def test_trace_without_truth_still_writes_estimates(tmp_path, shipped_trace_dir):
    d = _no_truth_copy(_need(shipped_trace_dir), tmp_path)
    out = tmp_path / "out"
    rc = cli.main(["evaluate", str(d), "--modes", "wls", "--out", str(out), "--no-progress"])
    assert rc == 0
    est = pd.read_csv(out / "2099-01-01-NO-TRUTH_Pixel4" / "wls" / "estimates.csv")
    assert len(est) > 50 and np.isfinite(est[["x_m", "y_m", "z_m"]].to_numpy()).all()
    rec = json.loads((out / "2099-01-01-NO-TRUTH_Pixel4" / "wls" / "metrics.json").read_text())
    assert rec["metrics"] is None and rec["epochs_solved"] == len(est) and "excluded_measurements" in rec["info"]
    table = pd.read_csv(out / "metrics.csv")
    assert table.status.str.startswith("no truth").all()
    assert table[METRIC_KEYS].isna().all().all()
    assert "metrics unavailable" in (out / "report.md").read_text()
    assert (out / "figures" / "2099-01-01-NO-TRUTH_Pixel4_traj.png").is_file()


def test_bad_trace_dir_exits_2_with_one_line(tmp_path, capsys):
    missing = tmp_path / "nope" / "Pixel4"
    rc = cli.main(["evaluate", str(missing), "--modes", "wls", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert len(err.splitlines()) == 1 and str(missing) in err
    assert not (tmp_path / "o" / "report.md").exists()


def test_unknown_mode_exits_2(tmp_path, capsys):
    rc = cli.main(["evaluate", str(tmp_path), "--modes", "wls,bogus", "--out", str(tmp_path / "o")])
    assert rc == 2 and "bogus" in capsys.readouterr().err


def test_one_bad_trace_keeps_the_good_ones(tmp_path, shipped_trace_dir, capsys):
    good = _no_truth_copy(_need(shipped_trace_dir), tmp_path)
    empty = tmp_path / "2099-01-02-EMPTY" / "Pixel4"
    empty.mkdir(parents=True)
    out = tmp_path / "out"
    rc = cli.main(["evaluate", str(good), str(empty), "--modes", "wls", "--out", str(out), "--no-progress"])
    assert rc == 2
    assert str(empty) in capsys.readouterr().err
    assert (out / "2099-01-01-NO-TRUTH_Pixel4" / "wls" / "estimates.csv").is_file()
    assert str(empty) in (out / "report.md").read_text()


def test_a_pooled_figure_that_fails_is_a_warning_not_a_lost_report(tmp_path, shipped_trace_dir, monkeypatch):
    def broken(errors, path, title):
        raise RuntimeError("no room to draw")

    monkeypatch.setitem(report.POOLED, "box", broken)
    out = tmp_path / "out"
    d = _need(shipped_trace_dir)
    copy = tmp_path / "2021-04-28-US-MTV-1-copy" / "Pixel4"       # pooled figures need two traces
    shutil.copytree(d, copy)
    with pytest.warns(UserWarning, match=r"all_box\.png: not drawn: RuntimeError: no room to draw"):
        rc = cli.main(["evaluate", str(d), str(copy), "--modes", "wls", "--out", str(out), "--max-epochs", "100",
                       "--no-progress"])
    assert rc == 0
    assert (out / "figures" / "all_cdf.png").is_file() and not (out / "figures" / "all_box.png").exists()
    assert "all_cdf.png" in (out / "report.md").read_text()


# ---------------------------------------------------------------- synthetic: a new mode, pooling
def _synthetic_trace(name: str, E: int, lat: float) -> Trace:
    kw = empty_trace(E, 4, name=name, with_truth=True)
    kw["t_ms"] = 1_300_000_000_000 + 1000 * np.arange(E, dtype=np.int64)
    llh = np.c_[lat + 1e-4 * np.arange(E), np.full(E, -122.0), np.full(E, 10.0)]
    kw["truth"] = geodetic2ecef(llh)
    return Trace(**kw)


def _offset_mode(trace, wls, opts):
    """A stand-in estimator: truth moved by a fixed NED offset (3, 4, -2) m, epoch 0 unsolved."""
    pos = trace.truth + ned2ecef_vec(np.array([3.0, 4.0, -2.0]), trace.truth)
    valid = np.ones(trace.n_epochs, bool)
    valid[0] = False
    return ModeResult(pos=np.where(valid[:, None], pos, np.nan), valid=valid)


def test_new_mode_needs_no_report_change_and_all_row_pools(tmp_path, monkeypatch):
    mod = types.ModuleType("gnssfuse_test_modes")
    mod.estimate_offset = _offset_mode
    monkeypatch.setitem(sys.modules, "gnssfuse_test_modes", mod)
    monkeypatch.setitem(modes.MODES, "offset", "gnssfuse_test_modes:estimate_offset")
    fake_wls = types.SimpleNamespace(reasons={})
    traces = [_synthetic_trace("c1/p", 11, 37.4), _synthetic_trace("c2/p", 21, 37.5)]
    evals = [evaluate_trace(t, ["offset"], RunOptions(), tmp_path, f"t{i}", wls=fake_wls,
                            progress=False) for i, t in enumerate(traces)]
    df = metrics_table(evals, ["offset"]).set_index("trace")
    for name in ("c1/p", "c2/p", ALL):
        row = df.loc[name]
        assert row.mae_n == pytest.approx(3.0, abs=1e-6) and row.mae_e == pytest.approx(4.0, abs=1e-6)
        assert row.mae_d == pytest.approx(2.0, abs=1e-6) and row.h_p95 == pytest.approx(5.0, abs=1e-6)
        assert row.std_n == pytest.approx(0.0, abs=1e-6)
    assert df.loc[ALL, "epochs_scored"] == 10 + 20
    assert df.loc[ALL, "epochs_unsolved"] == 2
    pooled = summarize(np.concatenate([ev.errors["offset"] for ev in evals]))
    assert df.loc[ALL, "gsdc_score"] == pytest.approx(pooled["gsdc_score"])
    assert (tmp_path / "t1" / "offset" / "estimates.csv").is_file()


def test_plots_handle_outliers_and_empty_input(tmp_path):
    from fusion.eval import plots

    rng = np.random.default_rng(0)
    err = rng.normal(0, 2, (500, 3))
    err[:3] = 1e5                      # absurd outliers must not set the axis range
    err[10:20] = np.nan                # unsolved epochs
    errors = {"a": err, "b": err * 0.5}
    p = plots.plot_error_boxes(errors, tmp_path / "box.png")
    assert p.read_bytes()[:8] == PNG_MAGIC
    lo, hi = plots.box_limits([e[np.isfinite(e[:, 0]), 0] for e in errors.values()])
    assert -20 < lo < -5 and 5 < hi < 20           # whiskers of N(0, 2) at ~ +-2.7 sigma, plus margin
    p = plots.plot_error_cdfs(errors, tmp_path / "cdf.png")
    assert p.read_bytes()[:8] == PNG_MAGIC
    assert plots.plot_error_cdfs({}, tmp_path / "empty_cdf.png").read_bytes()[:8] == PNG_MAGIC
    traj = plots.plot_trajectories({"a": np.full((3, 3), np.nan)}, None, tmp_path / "t.png")
    assert traj.read_bytes()[:8] == PNG_MAGIC
    en = plots.local_east_north(geodetic2ecef(np.array([[37.0, -122.0, 0.0], [37.001, -122.0, 0.0]])),
                                geodetic2ecef(np.array([37.0, -122.0, 0.0])))
    assert en[1, 0] == pytest.approx(0.0, abs=1e-3) and en[1, 1] == pytest.approx(110.96, abs=0.5)


def test_zooms_go_to_the_worst_separate_stretches(tmp_path, monkeypatch):
    from fusion.eval import plots

    t = np.arange(300.0)
    score = np.ones(300)
    score[[50, 55, 200, 120]] = [90.0, 80.0, 70.0, 60.0]     # 55 lies inside 50's zoom: not a second zoom
    assert plots.worst_stretches(t, score, n=3, half_s=15.0) == [50, 200, 120]
    assert plots.worst_stretches(t, np.full(300, np.nan)) == []
    # the score is the largest horizontal error of any mode: a mode 40 m east at epoch 7 is the worst
    llh = np.c_[37.0 + 1e-5 * np.arange(20), np.full(20, -122.0), np.zeros(20)]
    truth = geodetic2ecef(llh)
    off = truth.copy()
    off[7] += ned2ecef_vec(np.array([0.0, 40.0, 0.0]), truth[7])
    score = plots._stretch_score({"a": truth + 1.0, "b": off}, truth)
    assert int(np.argmax(score)) == 7 and score[7] == pytest.approx(40.0, abs=2.0)
    drawn = []
    monkeypatch.setattr(plots, "_trajectory_panels", lambda *a: drawn.append(a[8]))
    plots.plot_trajectories({"a": truth + 1.0, "b": off}, truth, tmp_path / "t.png", t_s=np.arange(20.0), n_zoom=2,
                            zoom_half_s=2.0)
    assert [k for k, _ in drawn[0]][0] == 7


def test_error_vs_time_draws_one_row_per_mode(tmp_path, monkeypatch):
    from fusion.eval import plots

    saved = []
    monkeypatch.setattr(plots, "_save", lambda fig, path: saved.append(fig) or path)
    errors = {m: np.random.default_rng(i).normal(size=(50, 3)) for i, m in enumerate(["wls", "dnn", "fused"])}
    plots.plot_error_vs_time(np.arange(50.0), errors, tmp_path / "x.png")
    axes = saved[0].axes
    assert len(axes) == 6 and [ax.get_ylabel() for ax in axes[::2]] == ["wls", "dnn", "fused"]
    # each panel: its own mode in colour on top, every other mode in grey
    for ax in axes:
        colours = [line.get_color() for line in ax.get_lines()]
        assert colours.count("0.8") == 2 and len(colours) == 3


# ---------------------------------------------------------------- benchmarks/run_all.py
def _run_all():
    spec = importlib.util.spec_from_file_location("run_all", REPO / "benchmarks" / "run_all.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_readme_results_section_is_replaced_between_markers(tmp_path):
    ra = _run_all()
    readme = tmp_path / "README.md"
    readme.write_text(f"# T\n\nintro\n\n{ra.MARK_START}\nold table\n{ra.MARK_END}\n\nafter\n")
    ra.update_readme(readme, "| new | table |\n")
    text = readme.read_text()
    assert "old table" not in text and "| new | table |" in text
    assert text.startswith("# T\n\nintro\n\n" + ra.MARK_START) and text.endswith(ra.MARK_END + "\n\nafter\n")
    ra.update_readme(readme, "| new | table |\n")          # idempotent
    assert readme.read_text() == text
    for bad in ("no markers", f"{ra.MARK_END} x {ra.MARK_START}", f"{ra.MARK_START}{ra.MARK_START}{ra.MARK_END}"):
        with pytest.raises(ValueError):
            ra.replace_between_markers(bad, "x")


BENCHES = {
    "bench_fn.py": "def run(quick=False):\n    return [{'name': 'speed', 'value': 2.5 if quick else 1.0, 'unit': 's'}]\n",
    "bench_line.py": "import json\nprint('hello')\nprint('BENCH_JSON ' + json.dumps([{'name': 'acc', 'value': 3, "
                     "'unit': 'm', 'note': 'n=5'}]))\n",
    "bench_text.py": "print('WLS took 0.01 s')\n",
    "bench_crash.py": "raise RuntimeError('boom')\n",
    # A TypeError inside a quick run must fail the script, not silently rerun it at full size.
    "bench_typeerr.py": "def run(quick=False):\n    if quick:\n        raise TypeError('bad quick')\n"
                        "    return [{'name': 'full', 'value': 9, 'unit': 's'}]\n",
}


def test_run_all_collects_records_and_survives_bad_scripts(tmp_path):
    ra = _run_all()
    bdir = tmp_path / "benches"
    bdir.mkdir()
    for name, code in BENCHES.items():
        (bdir / name).write_text(code)
    readme = tmp_path / "README.md"
    readme.write_text(f"x\n{ra.MARK_START}\n{ra.MARK_END}\n")
    results = tmp_path / "results.md"
    rc = ra.main(["--quick", "--skip-accuracy", "--bench-dir", str(bdir), "--results", str(results),
                  "--update-readme", str(readme)])
    assert rc == 0
    md = results.read_text()
    assert "| bench_fn.py | speed | 2.5 | s |" in md                   # run(quick=True) was called
    assert "| bench_line.py | acc | 3 | m | n=5 |" in md
    assert re.search(r"\| bench_text.py \| \*\*no records\*\* .*BENCH_JSON", md)
    assert "WLS took 0.01 s" in md                                     # its printed figure is kept
    assert re.search(r"\| bench_crash.py \| \*\*no records\*\* .*exit 1: RuntimeError: boom", md)
    assert re.search(r"\| bench_typeerr.py \| \*\*no records\*\* .*exit 1: TypeError: bad quick", md)
    assert "| bench_typeerr.py | full |" not in md
    assert "| bench_fn.py | speed | 2.5 | s |" in readme.read_text()
    assert ra.discover(bdir, only=["fn", "bench_line"]) == [bdir / "bench_fn.py", bdir / "bench_line.py"]


def test_drop_failed_modes_returns_new_values_and_leaves_its_arguments():
    ra = _run_all()
    from fusion.eval.report import ALL

    df = pd.DataFrame({"trace": ["t1", ALL, "t1", ALL], "mode": ["wls", "wls", "dnn", "dnn"],
                       "status": ["ok", "ok", "failed: no weights", "failed on every trace"]})
    modes, why = ["wls", "dnn"], {"fused": "no gtsam"}
    out, modes2, why2 = ra.drop_failed_modes(df, modes, why)
    assert set(out["mode"]) == {"wls"} and modes2 == ["wls"]
    assert why2 == {"fused": "no gtsam", "dnn": "no weights"}
    assert modes == ["wls", "dnn"] and why == {"fused": "no gtsam"}   # the next group starts afresh
    assert len(df) == 4


def test_interp_truth_and_gogps_loader(tmp_path):
    ra = _run_all()
    t = np.array([0, 1000, 2000, 5000], np.int64)
    xyz = np.array([[0, 0, 0], [10, 0, 0], [20, 0, 0], [50, 0, 0]], float)
    got = ra.interp_truth(t, xyz, np.array([500, 1500, 3000, 6000, -1]), max_gap_ms=1500)
    assert got[0, 0] == pytest.approx(5) and got[1, 0] == pytest.approx(15)
    assert np.isnan(got[2:]).all()          # across a 3 s gap, after the end, before the start
    csv = tmp_path / "g.csv"
    csv.write_text("Epoch index,GPS Time[s],ECEF X[m],ECEF Y[m],ECEF Z[m]\n1,100,1,2,3\n2,101,NaN,NaN,NaN\n")
    t_ms, est = ra.load_gogps(csv)
    assert t_ms.tolist() == [100_000, 101_000] and np.isnan(est[1]).all()


def test_gogps_baseline_is_scored_beside_our_wls(shared_data):
    rows = _run_all().gogps_comparison(shared_data)
    if rows is None:
        pytest.skip("goGPS baseline or its trace not in shared data")
    gogps, ours = rows
    assert gogps["n"] > 1600 and ours["n"] > 1600
    # both are metre-level smartphone WLS fixes; a time-convention slip would cost tens of metres
    assert gogps["h_p50"] < 6 and ours["h_p50"] < 6


def test_report_has_a_per_trace_per_axis_calibration_table_for_modes_with_a_covariance():
    from types import SimpleNamespace

    from fusion.eval.report import calibration_lines

    m = {"within1sigma_n": 0.7, "within1sigma_e": 0.4, "within1sigma_d": 0.6, "within2sigma_n": 0.95,
         "within2sigma_e": 0.8, "within2sigma_d": 0.9, "n_cov": 12}
    ev = SimpleNamespace(trace=SimpleNamespace(name="a/b"), records={"fused": {"metrics": m},
                                                                      "wls": {"metrics": {"n": 12}}})
    lines = calibration_lines([ev], ["wls", "fused"])
    assert "| a/b | fused | 0.70 / 0.40 / 0.60 | 0.95 / 0.80 / 0.90 | 12 |" in lines
    assert not any("| wls |" in ln for ln in lines)
    assert calibration_lines([SimpleNamespace(trace=ev.trace, records={"wls": {"metrics": {"n": 1}}})], ["wls"]) == []


def test_an_all_row_pooling_fewer_traces_says_so():
    """A mode that failed on some traces (fused with --odometry on phones that carry none) pools the others
    only: its ALL row says over how many, not a bare "ok" beside the modes that pooled every trace."""
    from fusion.eval.metrics import summarize
    from fusion.eval.report import TraceEval, markdown_table, metrics_table
    from fusion.trace import Trace, empty_trace

    def trace(name: str) -> Trace:
        return Trace(**{**empty_trace(3, 4, name=name), "t_ms": np.array([0, 1000, 2000])})
    err = np.full((3, 3), 0.5)
    record = {"epochs_solved": 3, "metrics": summarize(err)}
    a = TraceEval(trace=trace("a/b"), slug="a_b", errors={"wls": err, "fused": err},
                  records={"wls": record, "fused": record})
    c = TraceEval(trace=trace("c/d"), slug="c_d", errors={"wls": err}, records={"wls": record},
                  failed={"fused": "the trace carries no odometry"})
    table = metrics_table([a, c], ["wls", "fused"]).set_index(["trace", "mode"])
    assert table.loc[(ALL, "wls"), "status"] == "ok"
    assert table.loc[(ALL, "fused"), "status"] == "ok over 1 of 2 traces (failed on the rest)"
    assert table.loc[("c/d", "fused"), "status"] == "failed: the trace carries no odometry"
    row = next(ln for ln in markdown_table(metrics_table([a, c], ["wls", "fused"])).splitlines()
               if ln.startswith(f"| **{ALL}** (over 1 of 2 traces (failed on the rest)) | fused |"))
    assert "0.50 ± 0.00" in row                                       # the figures stay
