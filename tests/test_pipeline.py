"""The `gnssfuse run` contract on the shipped real trace (wls mode; other modes test themselves)."""
import gzip
import json
import shutil

import numpy as np
import pandas as pd
import pytest

from fusion.cli import main
from fusion.geometry import geodetic2ecef
from fusion.prepare.load import load_trace
from fusion.eval.metrics import ned_errors, summarize
from fusion.io.estimates import ESTIMATE_COLUMNS, SIGMA_COLUMNS
from fusion.modes import run_modes
from fusion.run_types import RunOptions


def test_run_wls_writes_contract_files(shipped_trace_dir, tmp_path, capsys):
    assert main(["run", str(shipped_trace_dir), "--mode", "wls", "--out", str(tmp_path)]) == 0
    est = pd.read_csv(tmp_path / "estimates.csv")
    # the contract's columns, then the 1-sigma N/E/D of modes with a covariance (WLS has one)
    assert list(est.columns) == ESTIMATE_COLUMNS + SIGMA_COLUMNS
    sig = est[SIGMA_COLUMNS].to_numpy()
    assert np.isfinite(sig).mean() > 0.95 and (sig[np.isfinite(sig)] > 0).all()
    assert np.nanmedian(sig[:, 2]) > np.nanmedian(sig[:, 0])        # vertical is the weak axis of a fix
    trace = load_trace(shipped_trace_dir)
    assert 0.95 * trace.n_epochs <= len(est) <= trace.n_epochs
    # Geodetic and ECEF columns describe the same points.
    xyz = geodetic2ecef(est[["lat_deg", "lon_deg", "height_m"]].to_numpy())
    np.testing.assert_allclose(xyz, est[["x_m", "y_m", "z_m"]].to_numpy(), atol=1e-3)
    # gps_millis are true receive times: they line up with the ground truth's times (1 s shift removed).
    truth_ms = pd.read_csv(shipped_trace_dir / "ground_truth.csv")["millisSinceGpsEpoch"].to_numpy()
    gap = np.abs(est["gps_millis"].to_numpy()[:, None] - truth_ms[None, :]).min(axis=1)
    assert np.median(gap) < 5
    rec = json.loads((tmp_path / "metrics.json").read_text())
    assert rec["mode"] == "wls" and rec["epochs_solved"] == len(est)
    # metrics.json equals metrics recomputed from the written estimates.
    idx = np.searchsorted(trace.t_ms, est["gps_millis"].to_numpy())
    again = summarize(ned_errors(est[["x_m", "y_m", "z_m"]].to_numpy(), trace.truth[idx]))
    assert rec["metrics"]["h_p50"] == pytest.approx(again["h_p50"], abs=1e-3)
    assert "h p50" in capsys.readouterr().out


def test_all_modes_share_one_wls(shipped_trace_dir, monkeypatch):
    import fusion.modes as pl
    from fusion.estimate.wls import estimate_wls

    trace = load_trace(shipped_trace_dir).select(np.arange(50))
    calls, given = [], []
    real = pl.solve_initial
    monkeypatch.setattr(pl, "solve_initial", lambda *a, **k: calls.append(1) or real(*a, **k))

    def spy_mode(tr, wls, opts):
        given.append(wls)
        return estimate_wls(tr, wls, opts)

    monkeypatch.setattr(pl, "spy_mode", spy_mode, raising=False)
    monkeypatch.setitem(pl.MODES, "spy", "fusion.modes:spy_mode")
    res = run_modes(trace, ["wls", "spy"], RunOptions())
    assert len(calls) == 1 and len(given) == 1
    np.testing.assert_array_equal(res["wls"].pos, res["spy"].pos)
    assert res["wls"].pos.shape == (50, 3)


def test_unknown_mode_and_signal_are_clear_errors(shipped_trace_dir, tmp_path, capsys):
    assert main(["run", str(shipped_trace_dir), "--mode", "wls", "--signals", "GPS_L9",
                 "--out", str(tmp_path)]) == 2
    assert "GPS_L9" in capsys.readouterr().err


def test_missing_column_exits_2_naming_it(shipped_trace_dir, tmp_path, capsys):
    bad = tmp_path / "c" / "Pixel4"
    bad.mkdir(parents=True)
    with gzip.open(shipped_trace_dir / "Pixel4_derived.csv.gz", "rt") as f:
        df = pd.read_csv(f, nrows=500)
    df.drop(columns=["rawPrM"]).to_csv(bad / "Pixel4_derived.csv", index=False)
    shutil.copy(shipped_trace_dir / "ground_truth.csv", bad / "ground_truth.csv")
    assert main(["run", str(bad), "--mode", "wls", "--out", str(tmp_path / "o")]) == 2
    assert "rawPrM" in capsys.readouterr().err


def test_signal_names_accept_2023_spellings_and_all():
    from fusion.cli.run import build_parser
    from fusion.options import options_from_args
    from fusion.trace import SIGNALS

    parse = lambda s: options_from_args(build_parser().parse_args(["x", "--out", "o", "--signals", s]))  # noqa: E731
    assert parse("GPS_L1_CA,GAL_E1").signals == ("GPS_L1", "GAL_E1")
    assert parse("all").signals == SIGNALS


def test_signals_all_any_case():
    """Regression: ``--signals ALL`` (or "all" among other names) used to be an unknown signal."""
    from fusion.errors import GnssfuseError
    from fusion.cli.run import build_parser
    from fusion.options import options_from_args
    from fusion.trace import SIGNALS

    parse = lambda s: options_from_args(build_parser().parse_args(["x", "--out", "o", "--signals", s]))  # noqa: E731
    assert parse("ALL").signals == SIGNALS
    assert parse("All").signals == SIGNALS
    assert parse("GPS_L1, all").signals == SIGNALS
    with pytest.raises(GnssfuseError, match="unknown signal"):
        parse("GPS_L9")


def test_a_mode_that_cannot_import_is_unavailable_not_failed(monkeypatch):
    from fusion import modes as pipeline
    from fusion.errors import GnssfuseError, ModeUnavailableError

    monkeypatch.setitem(pipeline.MODES, "ghost", "fusion.no_such_module:estimate")
    monkeypatch.setitem(pipeline.MODES, "hollow", "fusion.modes:no_such_function")
    for name in ("ghost", "hollow"):
        with pytest.raises(ModeUnavailableError, match=f"mode '{name}' is unavailable"):
            pipeline.get_mode(name)
    with pytest.raises(GnssfuseError, match="unknown mode") as exc:
        pipeline.get_mode("nope")
    assert not isinstance(exc.value, ModeUnavailableError)


def test_an_epoch_a_mode_answers_nan_is_counted_unsolved(shipped_trace_dir, tmp_path, monkeypatch, capsys):
    """A mode whose answer is NaN where it calls the epoch valid (a network with NaN weights did) must not be
    said solved: the epochs counted are the rows estimates.csv writes."""
    import fusion.estimate.wls as wls_module
    from fusion import modes as pipeline

    def half_nan(trace, wls, opts):
        res = wls_module.estimate_wls(trace, wls, opts)
        res.pos = np.where((np.arange(trace.n_epochs) % 2 == 0)[:, None], res.pos, np.nan)
        return res
    monkeypatch.setattr(wls_module, "half_nan", half_nan, raising=False)
    monkeypatch.setitem(pipeline.MODES, "wls", "fusion.estimate.wls:half_nan")
    assert main(["run", str(shipped_trace_dir), "--mode", "wls", "--out", str(tmp_path)]) == 0
    rows = len(pd.read_csv(tmp_path / "estimates.csv"))
    assert json.loads((tmp_path / "metrics.json").read_text())["epochs_solved"] == rows
    assert f" {rows}/" in capsys.readouterr().out
