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
