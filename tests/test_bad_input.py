"""Bad input, end to end through ``gnssfuse run`` (and ``simulate`` for nav files).

Every case is a copy of the shipped trace (cut to its first ~400 epochs for speed) with one defect.
Each either ends with one line naming the file and the problem and exit code 2, or keeps the good
epochs at unchanged accuracy: the estimates of every epoch the defect does not touch are those of
the clean copy, and what was dropped is counted in metrics.json. The list of cases and their outcomes
is in notes/robust.md.
"""
from __future__ import annotations

import gzip
import json
import shutil

import numpy as np
import pandas as pd
import pytest

from fusion.cli import main
from fusion.prepare.load import load_trace

N_ROWS = 3000                                   # ~400 epochs of the shipped trace
DERIVED = "Pixel4_derived.csv"


# ---------------------------------------------------------------------------- fixtures and helpers
@pytest.fixture(scope="module")
def clean(shipped_trace_dir, tmp_path_factory):
    """(derived rows, truth rows, clean run's estimates, clean run's metrics.json)."""
    rows = pd.read_csv(shipped_trace_dir / f"{DERIVED}.gz", nrows=N_ROWS, dtype=str, keep_default_na=False)
    truth = pd.read_csv(shipped_trace_dir / "ground_truth.csv", dtype=str, keep_default_na=False)
    d = _write_trace(tmp_path_factory.mktemp("clean"), rows, truth)
    est, rec = _run_ok(d, tmp_path_factory.mktemp("clean_out"))
    return rows, truth, est, rec


def _write_trace(root, rows: pd.DataFrame, truth: pd.DataFrame, name: str = DERIVED):
    d = root / "2021-04-28-US-MTV-1" / "Pixel4"
    d.mkdir(parents=True, exist_ok=True)
    rows.to_csv(d / name, index=False, compression="gzip" if name.endswith(".gz") else None)
    truth.to_csv(d / "ground_truth.csv", index=False)
    return d


def _run(d, out, *extra):
    return main(["run", str(d), "--mode", "wls", "--out", str(out), *extra])


def _run_ok(d, out, *extra):
    assert _run(d, out, *extra) == 0
    est = pd.read_csv(out / "estimates.csv").set_index("gps_millis")
    return est, json.loads((out / "metrics.json").read_text())


def _one_line_error(capsys, *must_contain):
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "Traceback" not in err, err
    for text in must_contain:
        assert str(text) in err, err
    return err


def _same_except(est, ref, changed_ms=()):
    """Every epoch of ``ref`` not in ``changed_ms`` is in ``est`` with the same position."""
    keep = ref.index.difference(pd.Index(changed_ms))
    assert keep.isin(est.index).all()
    np.testing.assert_allclose(est.loc[keep, ["x_m", "y_m", "z_m"]], ref.loc[keep, ["x_m", "y_m", "z_m"]],
                               atol=1e-3, rtol=0)


def _weak_ms(d) -> list[int]:
    """Epochs of the trace in ``d`` that WLS checks against their neighbours (few satellites, or an
    undecided fault test): a change next to them may change them too."""
    from fusion.estimate.wls import NEIGHBOUR_CHECK_MAX_SATS, solve_wls
    tr = load_trace(d, min_sats=1)
    r = solve_wls(tr)
    return tr.t_ms[(r.n_used <= NEIGHBOUR_CHECK_MAX_SATS) | r.flagged].tolist()


def _epoch_ms(rows, i):
    """True receive time (GPS ms) of data row i: derived times are one epoch late."""
    return int(rows["millisSinceGpsEpoch"].iloc[i]) - 1000


# ---------------------------------------------------------------------------- refused: exit 2, one line
@pytest.mark.parametrize("change, message", [
    (lambda r: r.drop(columns=["rawPrM"]), "lacks column(s) rawPrM"),
    (lambda r: r.rename(columns={"rawPrM": "raw_pr_m"}), "lacks column(s) rawPrM"),
    (lambda r: r.iloc[:0], "has a header but no data rows"),
    (lambda r: r.assign(rawPrM="n/a"), "no usable measurement row"),
])
def test_refused_tables(clean, tmp_path, capsys, change, message):
    rows, truth, _, _ = clean
    d = _write_trace(tmp_path, change(rows), truth)
    assert _run(d, tmp_path / "o") == 2
    _one_line_error(capsys, d / DERIVED, message)


@pytest.mark.parametrize("content, message", [
    (b"", "is empty"),
    (bytes(range(256)) * 40, "not text (binary data at byte 0)"),
    (b"\x1f\x8b\x08\x00" + b"\xff" * 300, "corrupt gzip"),
])
def test_refused_files(clean, tmp_path, capsys, content, message):
    rows, truth, _, _ = clean
    d = _write_trace(tmp_path, rows, truth)
    (d / DERIVED).write_bytes(content)
    assert _run(d, tmp_path / "o") == 2
    _one_line_error(capsys, d / DERIVED, message)


def test_corrupt_gzip_body_refused(clean, tmp_path, capsys):
    rows, truth, _, _ = clean
    d = _write_trace(tmp_path, rows, truth, name=f"{DERIVED}.gz")
    raw = bytearray((d / f"{DERIVED}.gz").read_bytes())
    raw[len(raw) // 2: len(raw) // 2 + 64] = b"\x00" * 64          # damage inside the deflate stream
    (d / f"{DERIVED}.gz").write_bytes(bytes(raw))
    assert _run(d, tmp_path / "o") == 2
    _one_line_error(capsys, d / f"{DERIVED}.gz", "corrupt gzip")


def test_truth_that_does_not_overlap(clean, tmp_path, capsys):
    rows, truth, _, _ = clean
    later = truth.assign(millisSinceGpsEpoch=(truth["millisSinceGpsEpoch"].astype(np.int64) + 86_400_000))
    d = _write_trace(tmp_path, rows, later)
    assert _run(d, tmp_path / "o") == 2
    _one_line_error(capsys, d / DERIVED, d / "ground_truth.csv", "do not overlap")


def test_corrupt_checkpoint(clean, tmp_path, capsys):
    rows, truth, _, _ = clean
    d = _write_trace(tmp_path, rows, truth)
    bad = tmp_path / "garbage.pt"
    bad.write_bytes(np.random.default_rng(0).bytes(4096))
    assert main(["run", str(d), "--mode", "dnn", "--weights", str(bad), "--out", str(tmp_path / "o")]) == 2
    _one_line_error(capsys, bad)


@pytest.mark.parametrize("content, message", [
    (b"\x00\x01garbage" * 50, "not a RINEX file"),
    (b"     3.04           N: GNSS NAV DATA    G: GPS              RINEX VERSION / TYPE\n", "END OF HEADER"),
])
def test_corrupt_nav_file(tmp_path, capsys, content, message):
    nav = tmp_path / "brdc.21n"
    nav.write_bytes(content)
    assert main(["simulate", "--nav", str(nav), "--out", str(tmp_path / "sim"), "--epochs", "5"]) == 2
    _one_line_error(capsys, nav, message)


def test_a_missing_navigation_file_is_named_even_where_no_navigation_is_needed(clean, tmp_path, capsys):
    rows, truth, _, _ = clean
    d = _write_trace(tmp_path, rows, truth)
    assert _run(d, tmp_path / "o", "--nav", str(tmp_path / "nope.21n")) == 2
    _one_line_error(capsys, tmp_path / "nope.21n", "--nav file not found")
    assert _run(d, tmp_path / "o", "--nav", str(tmp_path)) == 2              # a folder given for a file
    _one_line_error(capsys, tmp_path, "--nav is a folder, not a file")


@pytest.mark.parametrize("content, message", [(b"", "(the file is empty)"), (b"hello\n", "reads: a GSDC")])
def test_a_file_that_is_no_measurement_file_is_not_called_a_gsdc_file(tmp_path, capsys, content, message):
    f = tmp_path / "x.21o"
    f.write_bytes(content)
    assert _run(f, tmp_path / "o") == 2
    err = _one_line_error(capsys, f, "not a measurement file gnssfuse reads", message)
    assert "derived file is" not in err


def test_a_log_without_measurements_says_so_before_asking_for_navigation(tmp_path, capsys):
    d = tmp_path / "drive" / "phone"
    d.mkdir(parents=True)
    (d / "gnss_log.txt").write_text("# Header Description:\n#\n# Fix,Provider,LatitudeDegrees\n"
                                    "Fix,gps,37.4,-122.1\n")
    assert _run(d, tmp_path / "o") == 2
    err = _one_line_error(capsys, d / "gnss_log.txt", "Raw,")
    assert "navigation" not in err


# ---------------------------------------------------------------------------- kept: the good part, counted
def test_non_numeric_and_nan_values_skip_their_rows(clean, tmp_path):
    rows, truth, ref, _ = clean
    bad = rows.copy()
    bad.loc[100, "rawPrM"] = "12a45"
    bad.loc[200, "ionoDelayM"] = ""
    bad.loc[300, "xSatPosM"] = "inf"
    est, rec = _run_ok(_write_trace(tmp_path, bad, truth), tmp_path / "o")
    assert rec["skipped"] == {"rows_nonnumeric:rawPrM": 1, "rows_missing:ionoDelayM": 1,
                              "rows_nonfinite:xSatPosM": 1}
    _same_except(est, ref, [_epoch_ms(rows, i) for i in (100, 200, 300)])


def test_duplicated_and_shuffled_rows_change_nothing(clean, tmp_path):
    rows, truth, ref, ref_rec = clean
    twice = pd.concat([rows, rows]).sample(frac=1.0, random_state=3)
    est, rec = _run_ok(_write_trace(tmp_path, twice, truth.iloc[::-1]), tmp_path / "o")
    assert rec["skipped"] == {"duplicate_rows": len(rows)}
    _same_except(est, ref)
    assert rec["metrics"] == ref_rec["metrics"]


def test_truncated_final_line_is_a_counted_skip(clean, tmp_path):
    rows, truth, ref, _ = clean
    d = _write_trace(tmp_path, rows, truth)
    text = (d / DERIVED).read_text()
    (d / DERIVED).write_text(text[: len(text) - 60])                  # cut inside the last row
    with pytest.warns(UserWarning, match="final line is truncated"):
        est, rec = _run_ok(d, tmp_path / "o")
    assert rec["skipped"] == {"truncated_final_line": 1}
    _same_except(est, ref, [_epoch_ms(rows, len(rows) - 1)])


def test_truncated_gzip_keeps_what_was_written(clean, tmp_path):
    rows, truth, ref, _ = clean
    d = _write_trace(tmp_path, rows, truth, name=f"{DERIVED}.gz")
    raw = (d / f"{DERIVED}.gz").read_bytes()
    (d / f"{DERIVED}.gz").write_bytes(raw[: len(raw) * 3 // 4])
    with pytest.warns(UserWarning) as warned:
        est, rec = _run_ok(d, tmp_path / "o")
    assert any("gzip stream ends early" in str(w.message) for w in warned)
    cut_line = rec["skipped"].pop("truncated_final_line", 0)          # unless the cut fell on a newline
    assert rec["skipped"] == {"truncated_gzip": 1} and cut_line == sum("final line" in str(w.message) for w in warned)
    assert 0.6 * len(ref) < len(est) < len(ref)
    last = est.index.max()
    _same_except(est, ref[ref.index < last])                         # the last epoch may be partial


def test_data_gap_keeps_the_other_epochs(clean, tmp_path):
    rows, truth, ref, _ = clean
    t = rows["millisSinceGpsEpoch"].astype(np.int64)
    gap = (t >= t.iloc[1000]) & (t < t.iloc[1000] + 60_000)            # one minute without data
    est, rec = _run_ok(_write_trace(tmp_path, rows[~gap], truth), tmp_path / "o")
    assert not rec["skipped"] and len(est) < len(ref)
    _same_except(est, ref[ref.index.isin(est.index)])


def test_receiver_clock_jump_moves_no_position(clean, tmp_path):
    rows, truth, ref, _ = clean
    jumped = rows.copy()
    after = np.arange(len(rows)) >= 1500
    jumped.loc[after, "rawPrM"] = (rows.loc[after, "rawPrM"].astype(float) + 299_792.458).map(repr)   # +1 ms
    d = _write_trace(tmp_path, jumped, truth)
    est, _ = _run_ok(d, tmp_path / "o")
    # epochs are solved on their own (a three-satellite epoch next to the jump may lose its clock; an
    # epoch with few satellites may lose the neighbour it was checked against)
    _same_except(est[est.index.isin(ref.index)], ref[ref.index.isin(est.index)], _weak_ms(d))
    assert len(est) >= len(ref) - 2


def test_outliers_are_excluded_and_counted(clean, tmp_path):
    rows, truth, ref, ref_rec = clean
    bad = rows.copy()
    hit = np.random.default_rng(0).random(len(rows)) < 0.05
    bad.loc[hit, "rawPrM"] = (rows.loc[hit, "rawPrM"].astype(float) + 200.0).map(repr)
    d = _write_trace(tmp_path, bad, truth)
    est, rec = _run_ok(d, tmp_path / "o")
    plain, _ = _run_ok(d, tmp_path / "p", "--wls-plain")
    hit_ms = sorted({_epoch_ms(rows, i) for i in np.flatnonzero(hit)})
    weak_ms = _weak_ms(d)
    _same_except(est, ref, hit_ms + weak_ms)           # epochs without a fault: untouched
    tr = load_trace(d, min_sats=1)
    truth = pd.DataFrame(tr.truth, index=tr.t_ms, columns=["x_m", "y_m", "z_m"])
    # the fault-free epochs the neighbour check may change keep their accuracy
    near = sorted(set(weak_ms) - set(hit_ms))
    assert len(near) > 20
    e_near = {name: np.linalg.norm(e.reindex(near)[["x_m", "y_m", "z_m"]] - truth.loc[near], axis=1)
              for name, e in (("clean", ref), ("robust", est))}
    assert np.nanmedian(e_near["robust"]) < np.nanmedian(e_near["clean"]) + 1.0
    err = {name: np.linalg.norm(e.reindex(hit_ms)[["x_m", "y_m", "z_m"]] - truth.loc[hit_ms], axis=1)
           for name, e in (("clean", ref), ("robust", est), ("plain", plain))}
    med = {k: float(np.nanmedian(v)) for k, v in err.items()}
    print(f"\n{len(hit_ms)} epochs with a +200 m fault, median 3-D error [m]: {med}")
    assert med["robust"] < med["clean"] + 5.0 and med["plain"] > med["clean"] + 50.0
    info = rec["info"]
    assert info["excluded_measurements"] > 0.5 * hit.sum() and info["epochs_fault_undecided"] > 0


def test_bad_truth_rows_are_skipped_and_counted(clean, tmp_path):
    rows, truth, ref, ref_rec = clean
    bad = pd.concat([truth, truth.iloc[[5]]]).sample(frac=1.0, random_state=1).reset_index(drop=True)
    bad.loc[bad.index[10], "latDeg"] = "north"
    _, rec = _run_ok(_write_trace(tmp_path, rows, bad), tmp_path / "o")
    assert rec["skipped"] == {"truth_duplicate_rows": 1, "truth_rows_nonnumeric:latDeg": 1}
    assert abs(rec["metrics"]["gsdc_score"] - ref_rec["metrics"]["gsdc_score"]) < 0.05
