"""smartLoc (libRSF text) reader: the shipped excerpt of Berlin Potsdamer Platz (tests/data), its
defects one at a time, and the whole drive from ../shared when present."""
from __future__ import annotations

import json
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest

from fusion.cli import main
from fusion.errors import DataError
from fusion.prepare.load import find_traces, load_trace, trace_name
from fusion.prepare.smartloc import DRIVE_START_GPS, UNKNOWN_START_GPS_MS, load_smartloc
from fusion.trace import SIGNALS

HEAD = Path(__file__).resolve().parents[1] / "data" / "smartloc_berlin_head"
DRIVE = "Berlin_Potsdamer_Platz"
INPUT = f"{DRIVE}_Input.txt"
GT = f"{DRIVE}_GT.txt"


def _lines(name: str) -> list[str]:
    return (HEAD / name).read_text().splitlines(keepends=True)


def _copy(tmp_path: Path, edit=None, drive: str = DRIVE) -> Path:
    """The excerpt in ``tmp_path/smartloc/<drive>``, its input lines passed through ``edit``."""
    d = tmp_path / "smartloc" / drive
    d.mkdir(parents=True)
    lines = _lines(INPUT)
    (d / f"{drive}_Input.txt").write_text("".join(edit(lines) if edit else lines))
    shutil.copy(HEAD / GT, d / f"{drive}_GT.txt")
    return d


def _pr_lines(lines: list[str]) -> list[int]:
    return [i for i, s in enumerate(lines) if s.startswith("pseudorange3")]


def test_excerpt_loads_with_every_field_in_place():
    tr = load_trace(HEAD, signals=None)
    pr = [s.split() for s in _lines(INPUT) if s.startswith("pseudorange3")]
    odo = [s.split() for s in _lines(INPUT) if s.startswith("odom3")]
    gt = [s.split() for s in _lines(GT)]
    assert tr.n_epochs == 6 and int(tr.mask.sum()) == len(pr) == 101
    week, tow = DRIVE_START_GPS[DRIVE]
    t0 = week * 604_800_000 + round(tow * 1000)
    assert list(tr.t_ms - t0) == [0, 300, 500, 700, 900, 1100]
    # the first line: GPS PRN 12, variance 25 m^2, C/N0 49
    first = pr[0]
    k = np.flatnonzero(tr.sat_id[0] == 1012)[0]
    assert tr.pr[0, k] == float(first[2]) and tr.pr_sigma[0, k] == 5.0 and tr.cn0[0, k] == 49
    np.testing.assert_array_equal(tr.sat_pos[0, k], [float(v) for v in first[4:7]])
    # GLONASS 320 -> slot 20 of constellation 3, signal GLO_G1, its trace-wide bias removed
    g = np.flatnonzero(tr.sat_id[0] == 3020)[0]
    assert SIGNALS[tr.signal[0, g]] == "GLO_G1" and abs(tr.pr[0, g] - float(pr[1][2])) < 50
    np.testing.assert_array_equal(tr.truth, [[float(v) for v in row[2:5]] for row in gt])
    np.testing.assert_array_equal(tr.odometry, [[float(v) for v in row[2:]] for row in odo])
    assert tr.skipped == {} and tr.name == "data/smartloc_berlin_head"


def test_glonass_bias_is_measured_not_assumed(tmp_path):
    """GLONASS ranges shifted by 100 m load to the same corrected pseudoranges."""
    def shift(lines):
        out = list(lines)
        for i in _pr_lines(lines):
            f = lines[i].split()
            if f[8] == "4":
                f[2] = repr(float(f[2]) + 100.0)
                out[i] = " ".join(f) + "\n"
        return out
    ref, shifted = load_trace(HEAD, signals=None), load_trace(_copy(tmp_path, shift), signals=None)
    glo = ref.mask & (ref.signal == SIGNALS.index("GLO_G1"))
    assert glo.sum() > 20
    np.testing.assert_allclose(shifted.pr[glo], ref.pr[glo], atol=1e-6)


def test_signal_selection_counts_what_it_drops():
    tr = load_trace(HEAD, signals=("GPS_L1",))
    n_glo = sum(1 for s in _lines(INPUT) if s.startswith("pseudorange3") and s.split()[8] == "4")
    assert set(SIGNALS[i] for i in np.unique(tr.signal[tr.mask])) == {"GPS_L1"}
    assert tr.skipped == {"rows_signal_not_selected": n_glo}


def test_bad_lines_are_counted_and_the_first_is_named(tmp_path):
    def spoil(lines):
        out = list(lines)
        i = _pr_lines(lines)
        out[i[0]] = "pseudorange3 0 1 2\n"                          # too few fields
        out[i[1]] = out[i[1]].replace("pseudorange3 0 ", "pseudorange3 zero ", 1)
        out[i[2]] = out[i[2]].replace("pseudorange3 0 ", "pseudorange3 inf ", 1)
        out.insert(i[3], "range7 1 2 3\n")
        return out
    d = _copy(tmp_path, spoil)
    with pytest.warns(UserWarning, match=rf"{INPUT}:{_pr_lines(_lines(INPUT))[0] + 1}: pseudorange3 line: wrong field count"):
        tr = load_trace(d, signals=None)
    assert tr.skipped == {"lines_wrong_field_count:pseudorange3": 1, "lines_nonnumeric:pseudorange3": 1,
                          "lines_nonfinite:pseudorange3": 1, "lines_unknown_type:range7": 1}
    assert int(tr.mask.sum()) == 101 - 3


def test_odometry_no_car_drives_is_skipped_and_named(tmp_path):
    """One odom3 line turning at 50 rad/s bent the whole graph's track (187 m against 12 m on the full drive):
    such a line is skipped, counted and named; the others stay, and its epoch takes the mean of the rows around
    it (a missing step broke the graph's odometry chain: 13.8 m, 11.7 m interpolated)."""
    odo = [i for i, s in enumerate(_lines(INPUT)) if s.startswith("odom3")]

    def spoil(lines):
        out = list(lines)
        f = out[odo[1]].split()
        f[7] = "50.0"                                                 # wz, after the time and five rates
        out[odo[1]] = " ".join(f) + "\n"
        return out
    with pytest.warns(UserWarning, match=rf"{INPUT}:{odo[1] + 1}: odometry no car drives .*1 such line"):
        tr = load_trace(_copy(tmp_path, spoil), signals=None)
    assert tr.skipped["odometry_rows_implausible"] == 1 and tr.skipped["epochs_odometry_interpolated"] == 1
    ref = load_trace(HEAD, signals=None).odometry
    assert np.isfinite(tr.odometry).all(axis=1).sum() == np.isfinite(ref).all(axis=1).sum()
    assert np.nanmax(np.abs(tr.odometry[:, 5])) < 3.0


def test_duplicates_exact_kept_once_conflicting_dropped(tmp_path):
    def dup(lines):
        i = _pr_lines(lines)
        differing = lines[i[1]].replace(lines[i[1]].split()[2], "19713469.5", 1)
        return lines[:i[0]] + [lines[i[0]], lines[i[0]], differing] + lines[i[0] + 1:]
    tr = load_trace(_copy(tmp_path, dup), signals=None)
    assert tr.skipped == {"duplicate_rows": 1, "conflicting_duplicate_rows": 2}
    assert int(tr.mask.sum()) == 101 - 1 and 3020 not in tr.sat_id[0][tr.mask[0]]


def test_unsupported_system_is_counted(tmp_path):
    def sbas(lines):
        i = _pr_lines(lines)[0]
        f = lines[i].split()
        f[7], f[8] = "120", "2"
        return lines[:i] + [" ".join(f) + "\n"] + lines[i:]
    tr = load_trace(_copy(tmp_path, sbas), signals=None)
    assert tr.skipped == {"rows_unsupported_system:2": 1}


def test_unknown_drive_is_placed_at_the_gps_epoch_with_a_warning(tmp_path):
    d = _copy(tmp_path, drive="Elsewhere")
    with pytest.warns(UserWarning, match="GPS time of smartLoc drive 'Elsewhere' is unknown"):
        tr = load_trace(d, signals=None)
    assert tr.t_ms[0] == UNKNOWN_START_GPS_MS and tr.truth is not None


@pytest.mark.parametrize("content, message", [
    ("", "file is empty"),
    ("odom3 0 5 0 0 0 0 0 1 1 1 1 1 1\n", "no usable pseudorange3 line"),
])
def test_unusable_input_is_one_line_error(tmp_path, content, message):
    d = tmp_path / "smartloc" / DRIVE
    d.mkdir(parents=True)
    (d / INPUT).write_text(content)
    with pytest.raises(DataError, match=message) as err:
        load_trace(d)
    assert INPUT in str(err.value) and "\n" not in str(err.value)


def test_truth_is_optional_and_can_be_ignored(tmp_path):
    d = _copy(tmp_path)
    assert load_smartloc(d / INPUT, truth="none").truth is None
    (d / GT).unlink()
    assert load_trace(d, signals=None).truth is None
    with pytest.raises(DataError, match="truth='nmea'"):
        load_smartloc(d / INPUT, truth="nmea")


def test_found_named_and_selected_like_any_trace(tmp_path):
    d = _copy(tmp_path)
    assert find_traces(tmp_path) == [d]
    assert trace_name(d) == f"smartloc/{DRIVE}"
    tr = load_trace(d, signals=None)
    sub = tr.select(np.array([0, 2, 5]))
    np.testing.assert_array_equal(sub.odometry, tr.odometry[[0, 2, 5]])


@pytest.mark.parametrize("mode, extra", [("wls", []), ("fused-nodnn", []), ("fused-nodnn", ["--odometry"])])
def test_cli_runs_and_scores_the_excerpt(tmp_path, mode, extra, capsys):
    assert main(["run", str(HEAD), "--mode", mode, "--out", str(tmp_path), *extra]) == 0
    rec = json.loads((tmp_path / "metrics.json").read_text())
    assert rec["epochs_solved"] == 6
    assert ("odometry_steps" in rec["info"]) == bool(extra)


# ---------------------------------------------------------------------------- the whole drive (../shared)
@pytest.fixture(scope="module")
def berlin(shared_data):
    d = shared_data / "smartloc" / DRIVE
    if not d.is_dir():
        pytest.skip(f"{d} not present")
    return d


def test_whole_drive_loads_every_line(berlin):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tr = load_trace(berlin, signals=None, min_sats=1)
    assert (tr.n_epochs, int(tr.mask.sum()), tr.skipped) == (1372, 20038, {})
    assert np.isfinite(tr.truth).all() and np.isfinite(tr.odometry).all()


def test_whole_drive_odometry_helps_the_graph(berlin):
    """The odometry factor must improve the pseudorange-only graph on the real drive (GSDC score and horizontal p95)."""
    from fusion.eval.metrics import mode_metrics
    from fusion.modes import run_modes
    from fusion.estimate.graph.config import GraphConfig
    from fusion.run_types import RunOptions

    tr = load_trace(berlin, signals=None, min_sats=1)
    off = run_modes(tr, ["fused-nodnn"], RunOptions(signals=None))["fused-nodnn"]
    on = run_modes(tr, ["fused-nodnn"], RunOptions(signals=None, graph=GraphConfig(use_odometry=True)))["fused-nodnn"]
    m_off, m_on = mode_metrics(tr, off), mode_metrics(tr, on)
    assert on.valid.all() and on.info["odometry_steps"] == tr.n_epochs - 1
    assert m_on["gsdc_score"] < m_off["gsdc_score"] and m_on["h_p95"] < m_off["h_p95"]
