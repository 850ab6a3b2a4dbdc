"""Traces in parallel processes: one process per trace, at most ``jobs`` at a time, one thread each.

Workers are not forked from the caller (a forked child of a process that has already started torch or
OpenMP threads can deadlock): on Linux they fork from a *forkserver*, a fresh single-threaded process that
has imported the pipeline once (:data:`PRELOAD`: numpy, pandas, matplotlib, GTSAM), so a worker starts in
milliseconds instead of re-importing for a second or more; elsewhere they are spawned. The server and
its workers are limited to one BLAS/OpenMP/torch thread each, so ``--jobs N`` uses N cores, not N times
all of them. A trace whose worker raises, or dies, is reported as a failure of that trace alone;
the others go on.
"""
from __future__ import annotations

import multiprocessing
import os
import sys
from collections.abc import Callable, Sequence
from multiprocessing.connection import wait

from tqdm import tqdm

_THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMEXPR_NUM_THREADS")


def _one_thread() -> None:
    """First thing in a worker: one thread for BLAS/OpenMP and torch, which read these variables when
    first imported (after this, in a fresh spawned process; importing torch here would cost every
    worker seconds even when no mode needs it)."""
    for var in _THREAD_VARS:
        os.environ[var] = "1"
    if "torch" in sys.modules:  # pragma: no cover - not in a spawned worker, but cheap to be sure
        sys.modules["torch"].set_num_threads(1)


def map_traces(func: Callable, args: Sequence[tuple], jobs: int, progress: bool = False,
               costs: Sequence[float] | None = None) -> list:
    """``[func(*a) for a in args]`` in ``jobs`` worker processes at a time, results in the order of ``args``.

    ``func`` must be importable by name (a module-level function). An exception in one call becomes
    that call's result as the string ``"worker failed: <type>: <message>"``. ``costs`` (one per call,
    any unit): a guess of each call's run time; the costliest calls start first, so that a long one
    does not start last and leave the other workers idle (longest-processing-time-first scheduling).
    """
    out: list = [None] * len(args)
    ctx = _context()
    saved = {v: os.environ.get(v) for v in _THREAD_VARS}
    os.environ.update({v: "1" for v in _THREAD_VARS})      # inherited by the forkserver when it starts
    try:
        order = sorted(range(len(args)), key=lambda i: -costs[i]) if costs is not None else range(len(args))
        return _schedule(func, args, list(order), jobs, ctx, out, progress)
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


def _schedule(func: Callable, args: Sequence[tuple], order: list[int], jobs: int, ctx, out: list,
              progress: bool) -> list:
    """The scheduling loop of :func:`map_traces`: calls started in ``order`` (indices into ``args``),
    results filling ``out`` in the order of ``args``.

    Each call runs in a process of its own, at most ``jobs`` at a time, and sends its result back on a
    pipe of its own. The parent waits on those pipes only and starts no thread: a pipe that ends
    without a result is a process that died (killed, out of memory, a crash in C), charged to its own
    call alone. (Not ``concurrent.futures.ProcessPoolExecutor``: a worker's death breaks its whole
    pool, and on Python 3.11 its shutdown after a death can hang.)
    """
    todo = order[::-1]
    running: dict = {}                          # result pipe -> (index of the call, its process)
    try:
        with tqdm(total=len(args), desc="traces", disable=not progress) as bar:
            while todo or running:
                while todo and len(running) < jobs:
                    i = todo.pop()
                    running.update(_start(func, args[i], i, ctx))
                for pipe in wait(list(running)):
                    i, proc = running.pop(pipe)
                    out[i] = _collect(pipe, proc)
                    bar.update()
    finally:
        for _, proc in running.values():        # only when interrupted
            proc.kill()
            proc.join()
    return out


def _start(func: Callable, a: tuple, i: int, ctx) -> dict:
    """Start ``func(*a)`` in a new process; returns {its result pipe: (i, the process)}."""
    reader, writer = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child, args=(func, a, writer))
    proc.start()
    writer.close()                  # the child's copy is now the only one: its death ends the pipe
    return {reader: (i, proc)}


def _collect(pipe, proc):
    """The result a finished child sent on ``pipe``, or the one-line reason it sent none."""
    try:
        result = pipe.recv()
    except EOFError:
        proc.join()
        return f"worker failed: the worker process died (exit code {proc.exitcode})"
    finally:
        pipe.close()
    proc.join()
    return result


def _child(func: Callable, a: tuple, pipe) -> None:
    """In the child: ``func(*a)`` with one thread, its result (or failure line) sent on ``pipe``."""
    _one_thread()
    try:
        result = func(*a)
    except Exception as exc:  # noqa: BLE001 - one trace's crash must not stop the others
        result = failure(exc)
    try:
        pipe.send(result)
    except Exception as exc:  # noqa: BLE001 - e.g. a result that cannot be pickled
        pipe.send(failure(exc))


def failure(exc: BaseException) -> str:
    """The one-line result standing for a call that raised ``exc``."""
    return f"worker failed: {type(exc).__name__}: {exc}"
