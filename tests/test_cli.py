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


def test_unwritable_output_is_one_line_error(shipped_trace_dir, tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    assert main(["run", str(shipped_trace_dir), "--mode", "wls", "--out", str(blocker / "out")]) == 2
    err = capsys.readouterr().err
    assert "error" in err and err.strip().count("\n") == 0


def test_learned_part_flags_reach_the_run_options():
    import argparse

    from fusion.options import add_run_options, options_from_args

    p = argparse.ArgumentParser()
    add_run_options(p)
    o = options_from_args(p.parse_args([]))
    assert o.learned_prior and o.learned_sigmas and o.dnn_output is None
    o = options_from_args(p.parse_args(["--no-learned-prior", "--no-learned-sigmas", "--dnn-output", "correction"]))
    assert not o.learned_prior and not o.learned_sigmas and o.dnn_output == "correction"
    try:
        p.parse_args(["--dnn-output", "direct"])
    except SystemExit:
        pass
    else:
        raise AssertionError("--dnn-output direct was accepted")
