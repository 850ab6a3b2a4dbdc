"""``--scheduler ADDRESS``: ``gnssfuse evaluate``'s traces and ``gnssfuse adapt``'s teachers on a Dask cluster,
with the same results as one process."""
from __future__ import annotations

import os
import shutil
import socket
import sys
import time

import pytest

from fusion.cli import main
from fusion.parallel import map_traces


def _traces(tmp_path, shipped_trace_dir):
    """Two good copies of the shipped trace, and a broken one between them."""
    dirs = [tmp_path / "data" / name / "Pixel4" for name in ("a", "bad", "b")]
    for d in dirs[::2]:
        shutil.copytree(shipped_trace_dir, d)
    dirs[1].mkdir(parents=True)
    (dirs[1] / "Pixel4_derived.csv").write_text("millisSinceGpsEpoch,svid\n1,2\n")
    return dirs


@pytest.fixture(scope="module")
def cluster():
    """A two-worker, one-thread-each ``LocalCluster`` of processes (spawned, as on a real cluster)
    whose scheduler gives a task up after one worker death (Dask retries three times by default,
    restarting a worker each time: slow for a test) and gives a worker no more tasks than it has threads
    (worker-saturation 1.0, as the README asks of a cluster; Dask's default 1.1 lets a one-thread worker
    queue a second task)."""
    dask = pytest.importorskip("dask")
    distributed = pytest.importorskip("distributed")
    with dask.config.set({"distributed.scheduler.allowed-failures": 0,
                          "distributed.scheduler.worker-saturation": 1.0}):
        with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                      dashboard_address=":0") as local:
            yield local.scheduler_address


def test_scheduler_gives_the_metrics_of_jobs_1_and_a_bad_trace_stops_nothing(tmp_path, shipped_trace_dir,
                                                                              cluster, capsys):
    dirs = _traces(tmp_path, shipped_trace_dir)
    common = ["evaluate", *map(str, dirs), "--modes", "wls,fused-nodnn", "--max-epochs", "100", "--no-progress"]
    assert main([*common, "--out", str(tmp_path / "one"), "--jobs", "1"]) == 2
    capsys.readouterr()
    assert main([*common, "--out", str(tmp_path / "dask"), "--scheduler", cluster]) == 2
    err = capsys.readouterr().err
    assert f"could not evaluate {dirs[1]}" in err and "lacks column(s)" in err   # reported, and alone:
    one, dask = ((tmp_path / r / "metrics.csv").read_bytes() for r in ("one", "dask"))
    assert one == dask and b"a/Pixel4" in dask and b"b/Pixel4" in dask and b"fused-nodnn" in dask
    # the workers wrote each trace's estimates and figures into the same --out
    assert (tmp_path / "dask" / "b_Pixel4" / "fused-nodnn" / "metrics.json").is_file()
    assert sorted(p.name for p in (tmp_path / "one" / "figures").iterdir()) == \
        sorted(p.name for p in (tmp_path / "dask" / "figures").iterdir())


def _dies_on_two(x: int):
    if x == 2:
        os._exit(3)             # as a segfault or the OOM killer would: no exception, no cleanup
    if x == 4:
        raise ZeroDivisionError("a bug on one call")
    return 10 * x


def test_a_dying_worker_costs_only_its_own_call_on_a_cluster(cluster):
    out = map_traces(_dies_on_two, [(i,) for i in range(6)], scheduler=cluster, costs=[1, 1, 9, 1, 1, 1])
    assert out[2] == "the worker process died (each of the 1 Dask workers that ran it)"
    assert out[4] == "ZeroDivisionError: a bug on one call"
    assert [out[i] for i in (0, 1, 3, 5)] == [0, 10, 30, 50]


def _started_at(x: int, busy_s: float = 0.5) -> tuple[int, float]:
    t = time.time()             # a wall clock: the workers are other processes
    time.sleep(busy_s)
    return x, t


def test_results_keep_their_order_on_a_cluster_whatever_the_costs(cluster):
    """Calls go out costliest first, but when each starts on a cluster is the scheduler's business (a
    worker joining late, Dask's queueing): only the order of the results is promised, and every call runs.
    The start order itself is tested without a cluster (tests/test_evaluate_jobs.py)."""
    out = map_traces(_started_at, [(i, 0.1) for i in range(4)], scheduler=cluster, costs=[1.0, 30.0, 2.0, 7.0])
    assert [x for x, _ in out] == [0, 1, 2, 3] and all(t > 0 for _, t in out)


class _Cluster:
    """A stand-in for a ``distributed.Client`` whose scheduler and workers answer ``find_spec`` as given."""

    def __init__(self, on_scheduler, on_workers):
        self.on_scheduler, self.on_workers = on_scheduler, on_workers

    def run_on_scheduler(self, func, name):
        return self.on_scheduler

    def run(self, func, name):
        if isinstance(self.on_workers, Exception):
            raise self.on_workers
        return self.on_workers


def test_a_cluster_without_gnssfuse_is_one_error_before_any_work():
    pytest.importorskip("distributed")
    from fusion.cluster import ClusterError, check_environment
    spec = object()
    check_environment(_Cluster(spec, {"tcp://w1": spec, "tcp://w2": spec}), "tcp://s:1")
    with pytest.raises(ClusterError, match=r"^the scheduler, tcp://w2 of the Dask cluster at tcp://s:1 cannot "
                                           r"import fusion.cluster: install this gnssfuse"):
        check_environment(_Cluster(None, {"tcp://w1": spec, "tcp://w2": None}), "tcp://s:1")
    with pytest.raises(ClusterError, match=r"^the Dask cluster at tcp://s:1 did not answer: OSError: gone away$"):
        check_environment(_Cluster(spec, OSError("gone\n away")), "tcp://s:1")


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_an_unreachable_scheduler_is_a_one_line_error(tmp_path, shipped_trace_dir, capsys, monkeypatch):
    dask = pytest.importorskip("dask")
    pytest.importorskip("distributed")
    address = f"tcp://127.0.0.1:{_closed_port()}"
    with dask.config.set({"distributed.comm.timeouts.connect": "1s"}):
        t0 = time.monotonic()
        rc = main(["evaluate", str(shipped_trace_dir), "--out", str(tmp_path / "r"), "--no-progress",
                   "--scheduler", address])
    assert rc == 2 and time.monotonic() - t0 < 30
    err = capsys.readouterr().err
    assert err.startswith(f"gnssfuse evaluate: error: cannot reach the Dask scheduler at {address}: ")
    assert err.count("\n") == 1 and "Traceback" not in err
    assert main(["evaluate", str(shipped_trace_dir), "--out", str(tmp_path / "r"), "--scheduler", "localhost"]) == 2
    assert "cannot reach the Dask scheduler at localhost: missing port number" in capsys.readouterr().err


def test_scheduler_without_dask_is_a_one_line_error(tmp_path, shipped_trace_dir, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)       # as if not installed
    rc = main(["evaluate", str(shipped_trace_dir), "--out", str(tmp_path / "r"), "--no-progress",
               "--scheduler", "tcp://127.0.0.1:8786"])
    assert rc == 2
    assert capsys.readouterr().err == ("gnssfuse evaluate: error: --scheduler needs dask.distributed, which is "
                                       "not installed: pip install 'gnssfuse[cluster]'\n")


def test_jobs_and_scheduler_exclude_each_other(tmp_path, shipped_trace_dir, capsys):
    assert main(["evaluate", str(shipped_trace_dir), "--out", str(tmp_path / "r"), "--jobs", "2",
                 "--scheduler", "tcp://127.0.0.1:8786"]) == 2
    assert "--jobs and --scheduler exclude each other" in capsys.readouterr().err


def test_adapt_teachers_on_a_cluster_give_the_checkpoint_of_one_process(tmp_path, shipped_trace_dir, cluster,
                                                                         capsys, monkeypatch):
    from tests.learned.test_adapt import FEW, ONE, _copy_trace, _same_checkpoint

    two = [_copy_trace(shipped_trace_dir, tmp_path / "a"), _copy_trace(shipped_trace_dir, tmp_path / "b")]
    monkeypatch.chdir(tmp_path)                 # relative paths, which the workers cannot resolve as given
    rel = [str(p.relative_to(tmp_path)) for p in two]
    common = ["adapt", *rel, "--weights", str(ONE), "--max-epochs", str(FEW), "--epochs", "1", "--quiet"]
    assert main([*common, "--out", "one.pt"]) == 0
    assert main([*common, "--out", "dask.pt", "--scheduler", cluster]) == 0
    assert _same_checkpoint(tmp_path / "one.pt", tmp_path / "dask.pt")
    capsys.readouterr()
    assert main([*common, "--out", "x.pt", "--scheduler", cluster, "--jobs", "2"]) == 2
    assert "--jobs and --scheduler exclude each other" in capsys.readouterr().err


def test_options_name_absolute_files_for_the_workers(tmp_path, monkeypatch):
    from pathlib import Path

    from fusion.run_types import RunOptions

    monkeypatch.chdir(tmp_path)
    opts = RunOptions(weights=Path("w.pt"), nav=(Path("a.21n"), Path("b.21g")), sp3=Path("o.sp3"), clk=None)
    got = opts.with_absolute_paths()
    assert got.weights == tmp_path / "w.pt" and got.nav == (tmp_path / "a.21n", tmp_path / "b.21g")
    assert got.sp3 == tmp_path / "o.sp3" and got.clk is None and got.graph == opts.graph
    assert RunOptions().with_absolute_paths() == RunOptions()
