import subprocess
import sys

from fusion.cli import COMMANDS, main


def test_help_lists_every_command(capsys):
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    for name in COMMANDS:
        assert name in out


def test_unknown_command_exits_2(capsys):
    assert main(["frobnicate"]) == 2
    assert "unknown command" in capsys.readouterr().err


def test_run_on_missing_folder_is_one_line_error(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "fusion.cli", "run", str(tmp_path / "nope"),
                           "--mode", "wls", "--out", str(tmp_path / "o")],
                          capture_output=True, text=True)
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0 and "error" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_a_run_that_solves_no_epoch_is_refused_and_leaves_no_folder(shipped_trace_dir, tmp_path, capsys):
    """WLS above an 89 degree mask solves nothing: one line, exit 2, no export half-written, and the output
    folder the run made is gone again; a refused input leaves none either."""
    out = tmp_path / "o"
    assert main(["run", str(shipped_trace_dir), "--mode", "wls", "--elev-mask", "89", "--out", str(out),
                 "--export", "kml,gpx"]) == 2
    err = capsys.readouterr().err
    assert "solved none of its 1998 epochs" in err and err.strip().count("\n") == 0 and not out.exists()
    assert main(["run", str(tmp_path / "nope"), "--out", str(out)]) == 2
    assert not out.exists()
    out.mkdir()                                   # a folder that was there stays, even empty
    assert main(["run", str(tmp_path / "nope"), "--out", str(out)]) == 2 and out.is_dir()
    assert main(["run", str(tmp_path / "nope"), "--out", str(tmp_path / "a" / "b")]) == 2   # the parents it made too
    assert not (tmp_path / "a").exists()


def test_exports_of_an_earlier_run_are_removed_and_said(shipped_trace_dir, tmp_path, capsys):
    out = tmp_path / "o"
    assert main(["run", str(shipped_trace_dir), "--out", str(out), "--export", "kml,gpx"]) == 0
    (out / "estimates.txt").write_text("the user's own")
    capsys.readouterr()
    assert main(["run", str(shipped_trace_dir), "--out", str(out), "--export", "gpx"]) == 0
    assert "removed estimates.kml of an earlier run" in capsys.readouterr().out
    assert sorted(p.name for p in out.iterdir()) == ["estimates.csv", "estimates.gpx", "estimates.txt", "metrics.json"]


def test_unwritable_output_is_one_line_error(shipped_trace_dir, tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    assert main(["run", str(shipped_trace_dir), "--mode", "wls", "--out", str(blocker / "out")]) == 2
    err = capsys.readouterr().err
    assert "error" in err and err.strip().count("\n") == 0


def test_learned_part_flags_reach_the_run_options():
    from tests.run_options import parse_run_options

    o = parse_run_options([])
    assert o.learned_prior and o.learned_sigmas and o.dnn_output is None
    assert o.learned_doppler and o.learned_bias
    o = parse_run_options(["--no-learned-prior", "--no-learned-sigmas", "--no-learned-doppler", "--dnn-output",
                           "correction"])
    assert not o.learned_prior and not o.learned_sigmas and not o.learned_doppler and o.dnn_output == "correction"
    assert o.learned_bias and not parse_run_options(["--no-learned-bias"]).learned_bias
    with pytest.raises(SystemExit):                  # an unknown output head is refused by the parser
        parse_run_options(["--dnn-output", "direct"])


# ---------------------------------------------------------------- what a new user meets
import argparse  # noqa: E402
import importlib  # noqa: E402
import json  # noqa: E402

import pytest  # noqa: E402


def _parsers():
    for name, (target, _) in COMMANDS.items():
        module = importlib.import_module(target.split(":")[0])
        yield name, module.build_parser(f"gnssfuse {name}")


def test_every_option_of_every_subcommand_has_help():
    missing = [f"{name} {a.option_strings or a.dest}" for name, p in _parsers() for a in p._actions
               if not isinstance(a, argparse._HelpAction) and not (a.help or "").strip()]
    assert not missing, missing


def test_every_subcommand_module_is_in_the_cli_package():
    assert all(target.startswith("fusion.cli.") for target, _ in COMMANDS.values())


def test_version(capsys):
    assert main(["--version"]) == 0
    out = capsys.readouterr().out.strip()
    assert out.startswith("gnssfuse ") and len(out.split()) == 2


def test_train_help_and_bad_options_do_not_import_torch():
    code = ("import sys\nfrom fusion.cli import main\n"
            "try:\n    main(['train', '--help'])\nexcept SystemExit:\n    pass\n"
            "print('torch' in sys.modules, 'learned' in sys.modules)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert proc.stdout.split()[-2:] == ["False", "False"] and "--guess-mix" in proc.stdout


def test_train_parser_matches_the_learned_side():
    from fusion.cli.train import OUTPUTS, build_parser
    from learned.features import CHANNELS
    from learned.forward import OUTPUTS as learned_outputs

    assert OUTPUTS == learned_outputs
    inputs_help = next(a.help for a in build_parser()._actions if a.dest == "inputs")
    assert ",".join(CHANNELS) in inputs_help


@pytest.mark.parametrize("cmd", ["run", "evaluate", "simulate"])
def test_out_that_is_a_file_names_out(cmd, shipped_trace_dir, tmp_path, capsys):
    blocker = tmp_path / "taken"
    blocker.write_text("a file")
    args = {"run": [str(shipped_trace_dir)], "evaluate": [str(shipped_trace_dir)], "simulate": ["--epochs", "5"]}[cmd]
    assert main([cmd, *args, "--out", str(blocker)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and f"--out {blocker}: is a file" in err and "Errno" not in err


def test_train_out_that_is_a_folder_names_out(tmp_path, capsys):
    assert main(["train", "--data", "toy", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and f"--out {tmp_path}: is a folder" in err


def test_out_under_a_file_names_out(shipped_trace_dir, tmp_path, capsys):
    blocker = tmp_path / "taken"
    blocker.write_text("a file")
    assert main(["run", str(shipped_trace_dir), "--out", str(blocker / "sub")]) == 2
    err = capsys.readouterr().err
    assert f"--out {blocker / 'sub'}" in err and "Errno" not in err


def _no_truth_copy(trace_dir, tmp_path):
    d = tmp_path / "2099-01-01-NO-TRUTH" / "Pixel4"
    d.mkdir(parents=True)
    for f in trace_dir.glob("*_derived.csv*"):
        (d / f.name).write_bytes(f.read_bytes())
    return d


def test_run_without_truth_writes_metrics_json(shipped_trace_dir, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["run", str(_no_truth_copy(shipped_trace_dir, tmp_path)), "--out", str(out)]) == 0
    rec = json.loads((out / "metrics.json").read_text())
    assert rec["metrics"] is None and rec["epochs_solved"] > 0 and rec["epochs_total"] >= rec["epochs_solved"]
    assert "excluded_measurements" in rec["info"] and rec["skipped"] == {}
    printed = capsys.readouterr().out
    assert "skipped while loading: nothing" in printed and "metrics.json" in printed


def test_skip_counts_print_as_words():
    from fusion.eval.summary import skip_words

    assert skip_words({}) == "nothing"
    assert skip_words({"rows_nonnumeric:rawPrM": 2, "conflicting_duplicate_rows": 84, "zero": 0}) == \
        "84 conflicting duplicate rows, 2 rows nonnumeric (rawPrM)"


def test_evaluate_takes_a_measurement_file_as_run_does(shipped_trace_dir, tmp_path, capsys):
    f = shipped_trace_dir / "Pixel4_derived.csv.gz"
    assert main(["evaluate", str(f), "--modes", "wls", "--max-epochs", "30", "--out", str(tmp_path / "r")]) == 0
    assert "2021-04-28-US-MTV-1/Pixel4" in (tmp_path / "r" / "metrics.csv").read_text()
    assert main(["evaluate", str(tmp_path / "nope"), "--modes", "wls", "--out", str(tmp_path / "r2")]) == 2
    assert "trace folder(s) or file(s) not found" in capsys.readouterr().err


def test_a_trace_given_twice_is_evaluated_once(shipped_trace_dir, tmp_path):
    twice = [str(shipped_trace_dir), str(shipped_trace_dir) + "/"]
    with pytest.warns(UserWarning, match="given more than once; evaluated once"):
        assert main(["evaluate", *twice, "--modes", "wls", "--max-epochs", "30", "--out", str(tmp_path / "r")]) == 0
    rows = [l for l in (tmp_path / "r" / "metrics.csv").read_text().splitlines() if "2021-04-28-US-MTV-1/Pixel4" in l]
    assert len(rows) == 1


def test_a_relative_trace_folder_is_named_after_its_collection(shipped_trace_dir, monkeypatch):
    from fusion.prepare.load import trace_name

    monkeypatch.chdir(shipped_trace_dir)
    assert trace_name(".") == "2021-04-28-US-MTV-1/Pixel4"


def test_no_escape_codes_when_stderr_is_not_a_terminal(shipped_trace_dir, tmp_path):
    proc = subprocess.run([sys.executable, "-m", "fusion.cli", "evaluate", str(shipped_trace_dir), "--modes", "wls",
                           "--max-epochs", "30", "--out", str(tmp_path / "r")], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert "\x1b" not in proc.stderr + proc.stdout and "\r" not in proc.stderr + proc.stdout


def test_the_run_summary_says_what_the_network_and_the_graph_did():
    from fusion.eval.summary import run_summary

    info = {"learned_epochs_asked": 10, "learned_meas_asked": 80, "learned_meas_out_of_range": 3,
            "learned_meas_unseen_signal": 12, "learned_epochs_guard_shrunk": 2, "learned_epochs_guard_off": 1,
            "epochs_bridged": 4, "longest_bridge_s": 4.0, "doppler_sigmas_raised": 25}
    text = run_summary({"trace": "a/b", "epochs_solved": 10, "epochs_total": 10, "mode": "fused", "skipped": {},
                        "info": info})
    assert "sigmas raised where the measurements disagreed among themselves beyond them: 25 doppler" in text
    assert "asked at 10 epochs, 80 measurements" in text and "3 measurements with inputs outside" in text
    assert "12 measurements of signals it cannot read" in text and "switched off in 1" in text
    assert "4 epochs bridged" in text and "longest stretch 4 s" in text and "widened" not in text
    assert "Doppler head" not in text and "drift of its own" not in text and "carrier phase ties" not in text
    text = run_summary({"trace": "a/b", "epochs_solved": 10, "epochs_total": 10, "mode": "fused", "skipped": {},
                        "info": {**info, "carrier_calibrated": 7}})
    assert "sigmas of the 7 epochs carrier phase ties to a neighbour: calibrated as such" in text
    text = run_summary({"trace": "a/b", "epochs_solved": 10, "epochs_total": 10, "mode": "fused", "skipped": {},
                        "info": {**info, "bridged_widened": 3}})
    assert "longest stretch 4 s; the sigmas of 3 widened where the graph without Doppler and carrier disagreed" in text
    info.update(doppler_drift_jump_mps=0.471)
    text = run_summary({"trace": "a/b", "epochs_solved": 10, "epochs_total": 10, "mode": "fused", "skipped": {},
                        "info": info})
    assert "jumps around its course by 0.47 m/s (1 sigma) each epoch: each epoch's Doppler got a drift of its own" in text
    info.update(doppler_drift_jump_mps=None)           # too few well-known epochs to tell: nothing said
    text = run_summary({"trace": "a/b", "epochs_solved": 10, "epochs_total": 10, "mode": "fused", "skipped": {},
                        "info": info})
    assert "drift of its own" not in text
    info.update(learned_doppler_sigmas=70, learned_doppler_out_of_range=5, learned_doppler_unseen_system=9,
                learned_doppler_likely_outliers=2)
    text = run_summary({"trace": "a/b", "epochs_solved": 10, "epochs_total": 10, "mode": "fused", "skipped": {},
                        "info": info})
    assert "sigmas of 70 pseudorange rates (2 likely outliers)" in text
    assert "5 with inputs outside the training range and 9 of constellations it never saw" in text
    info.update(learned_move_h_p50_m=0.814, learned_move_h_p95_m=2.5)
    text = run_summary({"trace": "a/b", "epochs_solved": 10, "epochs_total": 10, "mode": "fused", "skipped": {},
                        "info": info})
    assert "moved the solution by 0.81 m horizontally at the median epoch (2.50 m at the 95th percentile)" in text


def test_incremental_runs_write_the_graphs_marginals(shipped_trace_dir, tmp_path, capsys):
    """ISAM2's estimate gets the same graph's marginals (fusion.estimate.graph.batch.marginals_at), calibrated
    as the batch solver's are: sigma columns, and the run says how many errors fall within them."""
    out = tmp_path / "inc"
    assert main(["run", str(shipped_trace_dir), "--mode", "fused-nodnn", "--incremental", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "no covariance from this run" not in printed and "errors within the mode's 1 sigma" in printed
    assert json.loads((out / "metrics.json").read_text())["covariance"] is True
    assert "sigma_n_m" in (out / "estimates.csv").read_text().splitlines()[0]


def test_the_report_says_per_mode_what_the_learned_parts_and_the_motion_model_did():
    import numpy as np

    from fusion.eval.report import TraceEval, _trace_section
    from fusion.trace import Trace, empty_trace

    info = {"learned_epochs_asked": 10, "learned_meas_asked": 80, "learned_doppler_sigmas": 70}
    ev = TraceEval(trace=Trace(**{**empty_trace(2, 4, name="a/b"), "t_ms": np.array([0, 1000])}), slug="a_b",
                   records={"wls": {"info": {}}, "fused": {"info": info},
                            "fused-nodnn": {"info": {"epochs_bridged": 120, "longest_bridge_s": 95.0}}})
    text = "\n".join(_trace_section(ev, {}))
    assert "fused: network: asked at 10 epochs, 80 measurements" in text
    assert "fused: Doppler head: sigmas of 70 pseudorange rates" in text and "wls:" not in text
    assert "fused-nodnn: 120 epochs bridged by the motion model (fewer than 4 satellites" in text and "longest stretch 95 s" in text
    assert "fused: 120" not in text and "fused: 0 epochs bridged" not in text
    from fusion.eval.summary import learned_words
    assert learned_words({**info, "learned_members": 3}).startswith("ensemble of 3 networks (guard counts: the most")
    assert "asked 2 times for the pseudorange sigmas" in learned_words({**info, "learned_sigma_passes": 2})
    assert "times for the pseudorange sigmas" not in learned_words({**info, "learned_sigma_passes": 1})
    assert "; 12 carrier-phase differences given at least twice" in learned_words(
        {**info, "learned_carrier_sigmas_raised": 12})
    assert "carrier-phase" not in learned_words(info)


# ---------------------------------------------------------------------------- start-up and exit cost of `run`
def test_run_wls_imports_nothing_heavy(shipped_trace_dir, tmp_path):
    """`run --mode wls` needs neither the network, nor GTSAM, nor the plotting stack: their imports
    (seconds for torch) must stay out of the wls path."""
    code = ("import sys\nfrom fusion.cli import main\n"
            f"assert main(['run', {str(shipped_trace_dir)!r}, '--mode', 'wls', '--out', {str(tmp_path / 'o')!r}]) == 0\n"
            "heavy = ('torch', 'gtsam', 'matplotlib', 'learned', 'scipy', 'fusion.estimate.graph.fuse')\n"
            "print('LOADED', [m for m in heavy if m in sys.modules])")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert "LOADED []" in proc.stdout


def test_subcommand_import_pauses_then_freezes_the_collector():
    import gc

    from fusion.cli import _import_quietly

    frozen = gc.get_freeze_count()
    try:
        for enabled in (True, False):
            (gc.enable if enabled else gc.disable)()
            assert _import_quietly("fusion.cli.run").main
            assert gc.isenabled() is enabled          # as it was
            assert gc.get_freeze_count() > frozen     # the imported objects are out of the collector's way
    finally:
        gc.enable()
        gc.unfreeze()


def test_entry_exits_at_once_after_run_only(shipped_trace_dir, tmp_path, monkeypatch):
    import fusion.cli as cli

    class Exited(Exception):
        pass

    def fake_exit(code):
        raise Exited(code)

    monkeypatch.setattr(cli.os, "_exit", fake_exit)
    monkeypatch.setattr(cli, "_children", lambda: False)
    monkeypatch.setattr(cli.threading, "active_count", lambda: 1)     # the test runner's own threads aside
    monkeypatch.setattr(sys, "argv", ["gnssfuse", "run", str(shipped_trace_dir), "--mode", "wls",
                                      "--out", str(tmp_path / "o")])
    with pytest.raises(Exited) as got:
        cli.entry()
    assert got.value.args == (0,) and (tmp_path / "o" / "estimates.csv").is_file()
    monkeypatch.setattr(sys, "argv", ["gnssfuse", "--version"])
    with pytest.raises(SystemExit) as normal:           # other commands: the ordinary exit
        cli.entry()
    assert normal.value.code == 0
    # a run that leaves a thread behind exits the ordinary way too (its exit handlers run)
    monkeypatch.setattr(cli.threading, "active_count", lambda: 2)
    monkeypatch.setattr(sys, "argv", ["gnssfuse", "run", str(shipped_trace_dir), "--mode", "wls",
                                      "--out", str(tmp_path / "o2")])
    with pytest.raises(SystemExit) as threaded:
        cli.entry()
    assert threaded.value.code == 0


def test_run_output_survives_the_quick_exit(shipped_trace_dir, tmp_path):
    """The process ends by os._exit after a run: what it printed to a pipe is flushed first."""
    out = tmp_path / "o"
    proc = subprocess.run([sys.executable, "-m", "fusion.cli", "run", str(shipped_trace_dir), "--mode", "wls",
                           "--out", str(out)], capture_output=True, text=True)
    assert proc.returncode == 0 and proc.stdout.rstrip().splitlines()[-1].startswith("wrote ")
    assert (out / "metrics.json").read_text().rstrip().endswith("}")


def test_freed_memory_is_kept_where_glibc_allows():
    import platform

    from fusion.cli import keep_freed_memory

    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        pytest.skip("mallopt is glibc's")
    assert keep_freed_memory() is True


@pytest.mark.parametrize("mask", ["95", "-10", "nan"])
def test_an_elevation_mask_outside_0_to_90_degrees_is_refused(shipped_trace_dir, tmp_path, capsys, mask):
    assert main(["run", str(shipped_trace_dir), "--elev-mask", mask, "--out", str(tmp_path / "o")]) == 2
    assert "between 0 and 90 degrees" in capsys.readouterr().err and not (tmp_path / "o").exists()


def test_flags_a_mode_does_not_read_are_said(shipped_trace_dir, tmp_path):
    """--incremental and --no-learned-prior act in graph / learned modes only: with wls, a warning says so."""
    from fusion.cli.run import build_parser as build_run_parser
    from fusion.options import flags_without_effect

    with pytest.warns(UserWarning, match="--incremental, --no-learned-prior have no effect in mode wls"):
        assert main(["run", str(shipped_trace_dir), "--incremental", "--no-learned-prior", "--out",
                     str(tmp_path / "o")]) == 0
    args = argparse.Namespace(incremental=True, weights=None, no_learned_prior=False, dnn_output="wls", dnn_passes=2)
    assert flags_without_effect(args, ["fused-nodnn"]) == ["--dnn-passes", "--dnn-output"]
    assert flags_without_effect(args, ["fused", "dnn"]) == []
    for mode in ("wls", "dnn", "fused-nodnn", "fused"):          # the defaults say nothing
        assert flags_without_effect(build_run_parser().parse_args(["x", "--out", "o"]), [mode]) == []


def test_navigation_for_a_file_that_carries_satellite_states_is_said(shipped_trace_dir, tmp_path):
    from fusion.io.rinex_nav import default_nav_path

    with pytest.warns(UserWarning, match="--nav not used: this file carries its satellites' positions"):
        assert main(["run", str(shipped_trace_dir), "--nav", str(default_nav_path()), "--out",
                     str(tmp_path / "o")]) == 0
    import warnings

    with warnings.catch_warnings(record=True) as seen:           # a path that is no trace: the error alone
        warnings.simplefilter("always")
        assert main(["run", str(tmp_path / "nope"), "--nav", str(default_nav_path()), "--out",
                     str(tmp_path / "o2")]) == 2
    assert not [w for w in seen if "not used" in str(w.message)]


def test_wls_sigmas_stay_metres_where_four_satellites_place_it(shipped_trace_dir, tmp_path):
    """Above a 30 degree mask the shipped trace's WLS epochs mostly have 4-5 satellites: its sigmas had
    shrunk to millimetres (0.00 of the errors within 1 sigma); the calibration must leave them metres."""
    import pandas as pd

    out = tmp_path / "o"
    assert main(["run", str(shipped_trace_dir), "--elev-mask", "30", "--out", str(out)]) == 0
    m = json.loads((out / "metrics.json").read_text())["metrics"]
    est = pd.read_csv(out / "estimates.csv")
    assert est["sigma_n_m"].min() > 1.0 and min(m[f"within1sigma_{a}"] for a in "ned") > 0.3    # measured 0.49
