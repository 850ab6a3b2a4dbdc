"""``gnssfuse evaluate``: four traces in one process, in two worker processes (``--jobs 2``), and on a
two-worker Dask ``LocalCluster`` (``--scheduler``), same run.

Each setting runs the real command in a fresh process (``python -m fusion.cli evaluate ... --jobs N``,
imports and report writing included, ``OMP_NUM_THREADS=1`` so that one job is one core), twice,
alternating, and the better time counts (the machine may be shared; the CPU seconds of each setting,
every process it started included, and the load average are printed so that a slow wall clock can be
told from extra work). The Dask
settings, when dask is installed: a LocalCluster that the command starts itself (its workers' start
and imports counted: what ``--jobs 2`` would cost on Dask), and ``--scheduler`` on a LocalCluster
that this script started once (workers already up and warm from the earlier runs: the cost of
Dask's scheduling alone). The metrics tables of all settings must be identical; the script says so.

    OMP_NUM_THREADS=1 PYTHONPATH=. python benchmarks/bench_evaluate.py            # full traces
    OMP_NUM_THREADS=1 PYTHONPATH=. python benchmarks/bench_evaluate.py --quick    # 300 epochs each

Traces: four GSDC 2021 training drives from ``$GNSSFUSE_SHARED_DATA`` (default ``<repo>/../shared/data``),
or four copies of the shipped trace when that folder is absent.
"""
from __future__ import annotations

import argparse
import contextlib
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pandas as pd

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("GNSSFUSE_SHARED_DATA", REPO.parent / "shared" / "data"))
TRAIN = ("2020-05-14-US-MTV-1", "2020-06-05-US-MTV-1", "2020-09-04-US-SF-2", "2020-05-14-US-MTV-2")
SHIPPED = REPO / "data" / "gsdc2021" / "train" / "2021-04-28-US-MTV-1" / "Pixel4"
MODES = "wls,fused-nodnn"


def four_traces(tmp: Path) -> tuple[list[Path], str]:
    found = [SHARED / "gsdc2021" / "train" / t / "Pixel4" for t in TRAIN]
    if all(d.is_dir() for d in found):
        return found, "four GSDC 2021 training traces"
    copies = []
    for k in range(4):
        d = tmp / "data" / f"copy{k}" / "Pixel4"
        shutil.copytree(SHIPPED, d)
        copies.append(d)
    return copies, "four copies of the shipped trace"


#: ``gnssfuse evaluate`` on a two-worker Dask ``LocalCluster`` that the command starts and stops itself:
#: what ``--jobs 2`` would cost if Dask replaced ``fusion.parallel``'s own workers.
LOCAL_CLUSTER_DRIVER = """
import sys
from distributed import LocalCluster
from fusion.cli import main
with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster:
    rc = main(sys.argv[1:] + ["--scheduler", cluster.scheduler_address])
sys.exit(rc)
"""


def timed_evaluate(traces: list[Path], out: Path, how: list[str], max_epochs: int | None) -> tuple[float, float]:
    """(wall seconds, CPU seconds of the command and the workers it waited for) of ``evaluate`` with
    the options ``how`` (``["--jobs", "2"]``, ``["--scheduler", ADDRESS]``, or ``["local-cluster"]``:
    :data:`LOCAL_CLUSTER_DRIVER`)."""
    head = [sys.executable, "-c", LOCAL_CLUSTER_DRIVER] if how == ["local-cluster"] else \
        [sys.executable, "-m", "fusion.cli"]
    cmd = [*head, "evaluate", *map(str, traces), "--modes", MODES, "--out", str(out), "--no-progress"]
    cmd += [] if how == ["local-cluster"] else how
    if max_epochs:
        cmd += ["--max-epochs", str(max_epochs)]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}
    before = _children()
    cpu0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=REPO)
    elapsed = time.perf_counter() - t0
    _reap_orphans(before)
    cpu1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (cpu1.ru_utime - cpu0.ru_utime) + (cpu1.ru_stime - cpu0.ru_stime)
    if proc.returncode != 0:
        raise RuntimeError(f"evaluate {' '.join(how)} failed ({proc.returncode}): {proc.stderr.strip()[-500:]}")
    return elapsed, cpu


def _adopt_orphans() -> bool:
    """Make this process the child subreaper of its descendants (Linux): a process that outlives its
    parent (``--jobs``' forkserver, which has waited for the workers) becomes this one's child, and
    its CPU time, workers included, reaches ``RUSAGE_CHILDREN`` once reaped. False where not possible."""
    try:
        import ctypes
        return ctypes.CDLL(None, use_errno=True).prctl(36, 1, 0, 0, 0) == 0   # PR_SET_CHILD_SUBREAPER
    except (OSError, AttributeError):
        return False


def _children() -> set[int]:
    """Process ids whose parent is this process (from /proc; empty elsewhere)."""
    me, out = str(os.getpid()), set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if fields[1] == me:
            out.add(int(stat.parent.name))
    return out


def _reap_orphans(before: set[int], timeout_s: float = 30.0) -> None:
    """Wait for the children that the last command left (adopted orphans), not those in ``before``
    (the running cluster's processes)."""
    deadline = time.monotonic() + timeout_s
    left = _children() - before
    while left and time.monotonic() < deadline:
        for pid in list(left):
            try:
                if os.waitpid(pid, os.WNOHANG)[0] == pid:
                    left.discard(pid)
            except ChildProcessError:
                left.discard(pid)
        time.sleep(0.02)


def _settings(address: str | None) -> dict[str, list[str]]:
    """Setting name -> ``timed_evaluate``'s ``how``; the Dask ones only when dask is installed."""
    out = {"--jobs 1": ["--jobs", "1"], "--jobs 2": ["--jobs", "2"]}
    if address:
        out[LOCAL] = ["local-cluster"]
        out[WARM] = ["--scheduler", address]
    return out


LOCAL = "on a Dask LocalCluster of 2 workers started by the command"
WARM = "--scheduler on a running Dask LocalCluster of 2 workers"


def _running_cluster(stack: contextlib.ExitStack) -> str | None:
    """The address of a two-worker LocalCluster that lives as long as ``stack``; None without dask."""
    try:
        from distributed import LocalCluster
    except ImportError:
        return None
    cluster = stack.enter_context(LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                               dashboard_address=":0"))
    return cluster.scheduler_address


def run(quick: bool = False, repeats: int = 2) -> list[dict]:
    max_epochs = 300 if quick else None
    with tempfile.TemporaryDirectory() as tmp, contextlib.ExitStack() as stack:
        tmp = Path(tmp)
        traces, what = four_traces(tmp)
        all_cpu = _adopt_orphans()
        settings = _settings(_running_cluster(stack))
        # alternate the settings so that a change in the machine's load hits both alike
        runs: dict[str, list] = {name: [] for name in settings}
        for k in range(repeats):
            for j, (name, how) in enumerate(settings.items()):
                runs[name].append(timed_evaluate(traces, tmp / f"r{j}_{k}", how, max_epochs))
        times = {name: min(w for w, _ in r) for name, r in runs.items()}
        cpu = {name: min(c for _, c in r) for name, r in runs.items()}
        tables = [(tmp / f"r{j}_0" / "metrics.csv").read_bytes() for j in range(len(settings))]
    load = os.getloadavg()[0]
    note = (f"{what}, modes {MODES}, {'first 300 epochs' if quick else 'all epochs'}, {os.cpu_count()} CPUs, "
            f"load average {load:.1f} after the runs (best of {repeats}); metrics.csv identical: "
            f"{all(t == tables[0] for t in tables)}")
    recs = [{"name": f"evaluate {name}", "value": round(t, 2), "unit": "s", "note": note} for name, t in times.items()]
    recs.append({"name": "evaluate speed-up --jobs 2 vs 1", "value": round(times["--jobs 1"] / times["--jobs 2"], 2),
                 "unit": "x", "note": note})
    if LOCAL in times:
        recs.append({"name": "evaluate Dask LocalCluster (started by the command) vs --jobs 2", "unit": "x",
                     "value": round(times[LOCAL] / times["--jobs 2"], 2), "note": note + " (time ratio, > 1: slower)"})
    # CPU seconds, workers included: less sensitive to a shared machine's load than wall time. Without
    # the subreaper, --jobs 2's workers (the forkserver's children) are not seen, and a running
    # cluster's workers never are: those are left out.
    for name in settings:
        if name == "--jobs 1" or (all_cpu and name != WARM):
            recs.append({"name": f"evaluate CPU time {name}", "value": round(cpu[name], 2), "unit": "s",
                         "note": note + " (CPU seconds of the command and all its processes)"})
    return recs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="first 300 epochs of each trace")
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args()
    recs = run(args.quick, args.repeats)
    for r in recs:
        print(f"{r['name']:<80} {r['value']:>8} {r['unit']}")
    print(recs[0]["note"])


if __name__ == "__main__":
    main()
