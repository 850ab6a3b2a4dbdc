"""Traces in parallel: :func:`map_traces` is the one entry (``evaluate``'s traces, its pooled figures,
and any later command that maps a function over traces), in this process (``jobs=1``), in worker
processes on this machine (``jobs`` > 1), or on a Dask cluster (``scheduler=ADDRESS``:
:mod:`fusion.cluster`).

Worker processes on this machine: one process per trace, at most ``jobs`` at a time, one thread each.

Workers are not forked from the caller (a forked child of a process that has already started torch or
OpenMP threads can deadlock): on Linux they fork from a *forkserver*, a fresh single-threaded process that
has imported the pipeline once (:data:`PRELOAD`: numpy, pandas, matplotlib, GTSAM), so a worker starts in
milliseconds instead of re-importing for a second or more; elsewhere they are spawned. The server and
its workers are limited to one BLAS/OpenMP/torch thread each, so ``--jobs N`` uses N cores, not N times
all of them. A trace whose worker raises, or dies, is reported as a failure of that trace alone;
the others go on. (Not a Dask ``LocalCluster`` for ``--jobs``: started by each command, its spawned
workers import everything anew, and ``benchmarks/bench_evaluate.py`` measures it slower than these
forked workers; Dask serves ``--scheduler``, a cluster that is already running.)
"""
from __future__ import annotations

import multiprocessing
import os
import sys
import time
import traceback
import warnings
from collections.abc import Callable, Sequence
from multiprocessing.connection import wait

from tqdm import tqdm

from fusion.errors import GnssfuseError

_THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMEXPR_NUM_THREADS")


def _one_thread() -> None:
    """First thing in a worker: one thread for BLAS/OpenMP and torch, which read these variables when
    first imported (after this, in a fresh spawned process; importing torch here would cost every
    worker seconds even when no mode needs it)."""
    for var in _THREAD_VARS:
        os.environ[var] = "1"
    if "torch" in sys.modules:  # pragma: no cover - not in a spawned worker, but cheap to be sure
        sys.modules["torch"].set_num_threads(1)


def plain_warnings() -> None:
    """In a worker: warnings as the command prints its own, one line without Python's source location."""
    warnings.formatwarning = lambda message, *args, **kwargs: f"gnssfuse: warning: {message}\n"


def check_pace(jobs: int, scheduler: str | None) -> None:
    """One-line errors for ``--jobs`` / ``--scheduler`` values no run can use (every command that takes
    them checks here, before any work)."""
    if jobs < 1:
        raise GnssfuseError("--jobs must be >= 1")
    if scheduler is not None and jobs > 1:
        raise GnssfuseError("--jobs and --scheduler exclude each other (the cluster's workers set the pace)")


def map_traces(func: Callable, args: Sequence[tuple], jobs: int = 1, progress: bool = False,
               costs: Sequence[float] | None = None, scheduler: str | None = None) -> list:
    """``[func(*a) for a in args]``, results in the order of ``args``: in this process when ``jobs``
    is 1, in ``jobs`` worker processes at a time when more, on the Dask cluster whose scheduler is at
    ``scheduler`` when given (``jobs`` is then not used: the cluster's workers set the pace).

    ``func`` must be importable by name (a module-level function). An exception in one call becomes
    that call's result as the string ``"<type>: <message>"`` (:func:`failure`), a worker's death as
    ``"the worker process died (...)"``. ``costs`` (one per call, any unit): a guess of each call's
    run time; the costliest calls start first, so that a long one does not start last and leave the
    other workers idle (longest-processing-time-first scheduling).
    """
    check_pace(jobs, scheduler)
    if scheduler is None and jobs == 1:         # one at a time: the order of args, whatever the costs
        return [guarded(func, *a) for a in tqdm(args, desc="traces", disable=not progress)]
    order = list(range(len(args)))
    if costs is not None:
        order.sort(key=lambda i: -costs[i])
    if scheduler is not None:
        from fusion.cluster import map_on_cluster
        return map_on_cluster(func, args, order, scheduler, progress)
    return _in_processes(func, args, order, jobs, progress)


def _in_processes(func: Callable, args: Sequence[tuple], order: list[int], jobs: int, progress: bool) -> list:
    """:func:`map_traces` with ``jobs`` > 1: the environment set for one-thread workers around :func:`_schedule`."""
    ctx = _context()
    saved = {v: os.environ.get(v) for v in _THREAD_VARS}
    os.environ.update({v: "1" for v in _THREAD_VARS})      # inherited by the forkserver when it starts
    try:
        return _schedule(func, args, order, jobs, ctx, progress)
    finally:
        _restore(saved)


def _restore(saved: dict) -> None:
    """Put back the environment variables ``saved`` (name -> value, None: was unset)."""
    for v, old in saved.items():
        if old is None:
            os.environ.pop(v, None)
        else:
            os.environ[v] = old


#: What the forkserver imports once for all workers: the evaluate job and the graph (GTSAM), not torch
#: (a process that has imported torch is best not forked from; ``dnn`` / ``fused`` workers import it).
PRELOAD = ["fusion.evaluate", "fusion.estimate.graph.fuse"]


def _context():
    """A forkserver preloaded with the pipeline where the platform has one, else spawn."""
    if "forkserver" in multiprocessing.get_all_start_methods():
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload(PRELOAD)
        return ctx
    return multiprocessing.get_context("spawn")


def jobs_asked(argv: list[str]) -> int:
    """The ``--jobs N`` / ``--jobs=N`` of a command line, read before its parser is imported; 1 when
    absent or not a number (the parser proper reports that)."""
    for i, arg in enumerate(argv):
        value = argv[i + 1] if arg == "--jobs" and i + 1 < len(argv) else arg[7:] if arg.startswith("--jobs=") else ""
        if value.isdigit():
            return int(value)
    return 1


def start_early() -> None:
    """Start the forkserver now, so that its imports overlap the caller's own (each takes a core for
    half a second or more); a no-op where workers are spawned."""
    ctx = _context()
    if ctx.get_start_method() != "forkserver":
        return
    saved = {v: os.environ.get(v) for v in _THREAD_VARS}
    os.environ.update({v: "1" for v in _THREAD_VARS})
    try:
        from multiprocessing import forkserver
        forkserver.ensure_running()
    finally:
        _restore(saved)


def _schedule(func: Callable, args: Sequence[tuple], order: list[int], jobs: int, ctx, progress: bool) -> list:
    """The scheduling loop of :func:`map_traces` with ``jobs`` > 1: calls started in ``order`` (indices into ``args``),
    results returned in the order of ``args``.

    Each call runs in a process of its own, at most ``jobs`` at a time, and sends its result back on a
    pipe of its own. The parent waits on those pipes only and starts no thread: a pipe that ends
    without a result is a process that died (killed, out of memory, a crash in C), charged to its own
    call alone. (Not ``concurrent.futures.ProcessPoolExecutor``: a worker's death breaks its whole
    pool, and on Python 3.11 its shutdown after a death can hang.)
    """
    out: list = [None] * len(args)
    todo = order[::-1]
    running: dict = {}                          # result pipe -> (index of the call, its process)
    exiting: list = []                          # processes that sent their result, not yet reaped
    try:
        with tqdm(total=len(args), desc="traces", disable=not progress) as bar:
            while todo or running:
                while todo and len(running) < jobs:
                    i = todo.pop()
                    _start(func, args[i], i, ctx, running)
                for pipe in wait(list(running)):
                    out[running[pipe][0]] = _collect(pipe, running[pipe][1])
                    exiting.append(running.pop(pipe)[1])   # popped only now: an interrupt still reaps it
                    bar.update()
                exiting = [p for p in exiting if p.exitcode is None]
    finally:
        for proc in [p for _, p in running.values() if p.pid is not None]:   # only when interrupted
            proc.kill()
            proc.join()
        _reap(exiting)
    return out


def _start(func: Callable, a: tuple, i: int, ctx, running: dict) -> None:
    """Start ``func(*a)`` in a new process, registered in ``running`` (result pipe -> (i, process))
    before it starts, so that an interrupt cannot leave it unreaped."""
    reader, writer = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child, args=(func, a, writer))
    running[reader] = (i, proc)
    proc.start()
    writer.close()                  # the child's copy is now the only one: its death ends the pipe


def _collect(pipe, proc):
    """The result a child sent on ``pipe``, or the one-line reason it sent none (the pipe ended
    before a message, or in the middle of one: the child died). A child that sent its result is not
    waited for here: its exit (tens of milliseconds of interpreter shutdown) overlaps the next call."""
    try:
        return pipe.recv()
    except (EOFError, OSError):
        proc.join()
        return f"the worker process died (exit code {proc.exitcode})"
    finally:
        pipe.close()


#: Seconds a child that has sent its result gets to exit before it is killed (a stray non-daemon
#: thread would otherwise keep it, and the caller, waiting).
EXIT_GRACE_S = 30.0


def _reap(procs: list) -> None:
    """Wait for children that have sent their results to exit; kill the ones that do not."""
    deadline = time.monotonic() + EXIT_GRACE_S
    for proc in procs:
        proc.join(max(0.0, deadline - time.monotonic()))
        if proc.exitcode is None:
            proc.kill()
            proc.join()


def _child(func: Callable, a: tuple, pipe) -> None:
    """In the child: ``func(*a)`` with one thread, its result (or failure line) sent on ``pipe``."""
    _one_thread()
    plain_warnings()
    result = guarded(func, *a)
    try:
        pipe.send(result)
    except Exception as exc:  # noqa: BLE001 - e.g. a result that cannot be pickled
        pipe.send(failure(exc))


def guarded(func: Callable, *a, **kw):
    """``func(*a, **kw)``, an exception becoming its one-line :func:`failure` (what a worker returns;
    also used in-process, so that one trace's bug loses no other trace's output)."""
    try:
        return func(*a, **kw)
    except Exception as exc:  # noqa: BLE001 - one trace's crash must not stop the others
        return failure(exc)


def failure(exc: BaseException) -> str:
    """The one-line result standing for a call that raised ``exc``. An exception that is not a
    :class:`GnssfuseError` (a user-facing problem with the input) is a bug: its traceback goes to
    stderr, since the one line alone would not locate it."""
    if not isinstance(exc, GnssfuseError):
        traceback.print_exception(exc, file=sys.stderr)
    return f"{type(exc).__name__}: {one_line(str(exc))}"


def one_line(text: str) -> str:
    """``text`` with its lines joined by spaces (some libraries' messages are paragraphs)."""
    return " ".join(line.strip() for line in text.splitlines() if line.strip())
