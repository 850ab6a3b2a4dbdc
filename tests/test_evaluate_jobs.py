"""``gnssfuse evaluate --jobs N``: traces in parallel processes, same tables as one process."""
from __future__ import annotations

import multiprocessing
import os
import shutil
import struct
import time
from pathlib import Path

import pandas as pd
import pytest

import fusion.evaluate
from fusion.cli import main
from fusion.errors import GnssfuseError
from fusion.parallel import _collect, jobs_asked, map_traces
from fusion.run_types import RunOptions


def _traces(tmp_path, shipped_trace_dir):
    """Two good copies of the shipped trace and one broken one between them."""
    dirs = []
    for name in ("a", "b"):
        d = tmp_path / "data" / name / "Pixel4"
        shutil.copytree(shipped_trace_dir, d)
        dirs.append(d)
    bad = tmp_path / "data" / "bad" / "Pixel4"
    bad.mkdir(parents=True)
    (bad / "Pixel4_derived.csv").write_text("millisSinceGpsEpoch,svid\n1,2\n")
    return [dirs[0], bad, dirs[1]]


def test_jobs_2_gives_the_metrics_of_jobs_1_and_a_bad_trace_stops_nothing(tmp_path, shipped_trace_dir, capsys):
    dirs = _traces(tmp_path, shipped_trace_dir)
    tables, figures = {}, {}
    for jobs in (1, 2):
        out = tmp_path / f"report{jobs}"
        rc = main(["evaluate", *map(str, dirs), "--modes", "wls", "--out", str(out), "--max-epochs", "300",
                   "--no-progress", "--jobs", str(jobs)])
        assert rc == 2                                  # the broken trace is reported ...
        err = capsys.readouterr().err
        assert f"could not evaluate {dirs[1]}" in err and "lacks column(s)" in err
        tables[jobs] = pd.read_csv(out / "metrics.csv")
        assert set(tables[jobs].trace) == {"a/Pixel4", "b/Pixel4", "ALL"}   # ... the others are not lost
        assert (out / "a_Pixel4" / "wls" / "metrics.json").is_file()
        assert "WLS fault detection and exclusion:" in (out / "report.md").read_text()
        figures[jobs] = sorted(p.name for p in (out / "figures").iterdir())
        assert {"all_cdf.png", "all_box.png", "a_Pixel4_traj.png"} <= set(figures[jobs])
    pd.testing.assert_frame_equal(tables[1], tables[2])
    assert figures[1] == figures[2]           # the pooled ones drawn by workers too


def test_jobs_must_be_positive(tmp_path, shipped_trace_dir, capsys):
    assert main(["evaluate", str(shipped_trace_dir), "--out", str(tmp_path / "r"), "--jobs", "0"]) == 2
    assert "--jobs must be >= 1" in capsys.readouterr().err


def _dies_on_two(x: int):
    if x == 2:
        os._exit(3)             # as a segfault or the OOM killer would: no exception, no cleanup
    if x == 3:
        return lambda: x        # a result that cannot be sent back
    return 10 * x


def test_a_dying_worker_costs_only_its_own_call():
    """A worker that dies, or whose result cannot be pickled, fails its own call only; more jobs
    than calls is fine."""
    for jobs in (2, 9):
        out = map_traces(_dies_on_two, [(i,) for i in range(6)], jobs=jobs)
        assert out[2] == "the worker process died (exit code 3)"
        assert "pickle" in out[3]
        assert [out[i] for i in (0, 1, 4, 5)] == [0, 10, 40, 50]


def _warning_line(x: int) -> str:
    import warnings
    return warnings.formatwarning(f"trace {x}: something to say", UserWarning, "somewhere.py", 7)


def test_a_workers_warning_is_one_plain_line():
    """Workers print warnings as the command does (their stderr is the forkserver's, so the line is
    checked where it is made)."""
    assert map_traces(_warning_line, [(1,), (2,)], jobs=2) == [f"gnssfuse: warning: trace {x}: something to say\n"
                                                                 for x in (1, 2)]


def _started_at(x: int) -> tuple[int, int]:
    t = time.monotonic_ns()     # one clock for all processes of the machine
    time.sleep(0.5)
    return x, t


def test_the_costliest_calls_start_first_and_results_keep_their_order():
    costs = [1.0, 30.0, 2.0, 7.0]
    out = map_traces(_started_at, [(i,) for i in range(4)], jobs=2, costs=costs)
    assert [x for x, _ in out] == [0, 1, 2, 3]
    started = sorted(range(4), key=lambda i: out[i][1])
    assert set(started[:2]) == {1, 3} and set(started[2:]) == {0, 2}    # two at a time
    out = map_traces(_started_at, [(i,) for i in range(4)], jobs=1, costs=costs)
    assert sorted(range(4), key=lambda i: out[i][1]) == [0, 1, 2, 3]    # one at a time: as given


def test_jobs_1_reports_an_unexpected_exception_as_that_traces_failure(tmp_path, shipped_trace_dir,
                                                                       capsys, monkeypatch):
    good = tmp_path / "data" / "a" / "Pixel4"
    shutil.copytree(shipped_trace_dir, good)
    buggy = tmp_path / "data" / "b" / "Pixel4"
    shutil.copytree(shipped_trace_dir, buggy)
    real = fusion.evaluate.load_and_run

    def load_and_run(d, *a, **k):
        if d == buggy:
            raise ZeroDivisionError("a bug on one trace")
        return real(d, *a, **k)

    monkeypatch.setattr(fusion.evaluate, "load_and_run", load_and_run)
    out = tmp_path / "report"
    rc = main(["evaluate", str(buggy), str(good), "--modes", "wls", "--out", str(out), "--max-epochs", "200",
               "--no-progress"])
    assert rc == 2
    err = capsys.readouterr().err
    assert f"could not evaluate {buggy}: ZeroDivisionError: a bug on one trace" in err
    assert "Traceback" in err and "load_and_run" in err         # a bug's traceback is not swallowed
    assert set(pd.read_csv(out / "metrics.csv").trace) == {"a/Pixel4", "ALL"}
    with pytest.raises(GnssfuseError, match=f"no trace could be evaluated: {buggy}: ZeroDivisionError"):
        fusion.evaluate.evaluate([buggy], ["wls"], tmp_path / "r2", RunOptions(), progress=False)


class _Ended:
    """A stand-in for a child process that has already exited."""
    pid, exitcode = 1, -9

    def join(self, timeout=None):
        pass


def test_a_pipe_cut_in_the_middle_of_a_message_is_a_dead_worker():
    """A worker killed while sending a large result leaves a length header and part of the message."""
    reader, writer = multiprocessing.Pipe(duplex=False)
    os.write(writer.fileno(), struct.pack("!i", 1_000_000) + b"only the start")
    writer.close()
    assert _collect(reader, _Ended()) == "the worker process died (exit code -9)"


def test_jobs_read_before_the_parser():
    assert jobs_asked(["a", "--jobs", "3", "--out", "x"]) == 3
    assert jobs_asked(["--jobs=2"]) == 2
    assert jobs_asked(["--jobs", "two"]) == 1 and jobs_asked(["--jobs"]) == 1 and jobs_asked([]) == 1


def test_two_traces_of_one_name_are_told_apart(tmp_path, shipped_trace_dir):
    """Two phones' folders of the same <collection>/<phone> name in one run: each row names its folder beside the
    first, so the table does not hold two rows no one can tell apart."""
    copy = tmp_path / "other" / shipped_trace_dir.parent.name / shipped_trace_dir.name
    shutil.copytree(shipped_trace_dir, copy)
    out = tmp_path / "ev"
    assert main(["evaluate", str(shipped_trace_dir), str(copy), "--modes", "wls", "--max-epochs", "50",
                 "--out", str(out)]) == 0
    names = pd.read_csv(out / "metrics.csv").trace.tolist()
    assert names[0] == "2021-04-28-US-MTV-1/Pixel4" and names[1] == f"2021-04-28-US-MTV-1/Pixel4 ({copy})"
    # a raw log, whose folder's name evaluate derives from its path before loading it, keeps its own name alone
    from fusion.io.rinex_nav import default_nav_path
    raw = tmp_path / "drive" / "phone"
    raw.mkdir(parents=True)
    shutil.copy(Path(__file__).parent / "data" / "pixel5_head.21o", raw / "x.21o")
    assert main(["evaluate", str(raw), "--modes", "wls", "--nav", str(default_nav_path()), "--out",
                 str(tmp_path / "raw")]) == 0
    assert pd.read_csv(tmp_path / "raw" / "metrics.csv").trace.tolist()[0] == "drive/phone"
    # the same --out again with one trace: the earlier run's second trace folder and figures go, with a word
    (out / "notes.txt").write_text("mine")
    with pytest.warns(UserWarning, match="removed an earlier evaluation's outputs \\(2 trace folder"):
        assert main(["evaluate", str(copy), "--modes", "wls", "--max-epochs", "50", "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["2021-04-28-US-MTV-1_Pixel4", "figures", "metrics.csv",
                                                     "metrics.md", "notes.txt", "report.md"]
    assert not list((out / "figures").glob("*_2_*"))
