"""Traces in parallel processes: one worker process per job, one thread per worker.

Workers are not forked from the caller (a forked child of a process that has already started torch or
OpenMP threads can deadlock): on Linux they fork from a *forkserver*, a fresh single-threaded process that
has imported the pipeline once (:data:`PRELOAD`: numpy, pandas, matplotlib, GTSAM), so a worker starts in
milliseconds instead of re-importing for a second or more; elsewhere they are spawned. The server and
its workers are limited to one BLAS/OpenMP/torch thread each, so ``--jobs N`` uses N cores, not N times
all of them. A trace whose worker raises, or dies, is reported as a failure of that trace;
the others go on (a death breaks the pool, so the traces it interrupted run again, each alone).
"""
from __future__ import annotations

import multiprocessing
import os
import sys
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool

from tqdm import tqdm

_THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMEXPR_NUM_THREADS")


def _one_thread() -> None:
    """Worker initialiser: one thread for BLAS/OpenMP and torch, which read these variables when
    first imported (after this, in a fresh spawned process; importing torch here would cost every
    worker seconds even when no mode needs it)."""
    for var in _THREAD_VARS:
        os.environ[var] = "1"
    if "torch" in sys.modules:  # pragma: no cover - not in a spawned worker, but cheap to be sure
        sys.modules["torch"].set_num_threads(1)


def map_traces(func: Callable, args: Sequence[tuple], jobs: int, progress: bool = False) -> list:
    """``[func(*a) for a in args]`` in ``jobs`` spawned processes, results in the order of ``args``.

    ``func`` must be importable by name (a module-level function). An exception in one call becomes
    that call's result as the string ``"worker failed: <type>: <message>"``.
    """
    out: list = [None] * len(args)
    ctx = _context()
    saved = {v: os.environ.get(v) for v in _THREAD_VARS}
    os.environ.update({v: "1" for v in _THREAD_VARS})      # inherited by the forkserver when it starts
    try:
        return _run_pool(func, args, jobs, ctx, out, progress)
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


def _run_pool(func: Callable, args: Sequence[tuple], jobs: int, ctx, out: list, progress: bool) -> list:
    """The pool loop of :func:`map_traces`, filling ``out`` in the order of ``args``.

    A worker that dies (killed, out of memory, a crash in C) breaks the whole pool: every call not
    finished by then fails with it, and which of them killed the worker is unknown. Those calls are
    run again, each in a pool of its own, so that a death is charged to its own call only.
    """
    lost = []
    with ProcessPoolExecutor(max_workers=jobs, mp_context=ctx, initializer=_one_thread) as pool:
        futures = {pool.submit(func, *a): i for i, a in enumerate(args)}
        for fut in tqdm(as_completed(futures), total=len(futures), desc="traces", disable=not progress):
            i = futures[fut]
            try:
                out[i] = fut.result()
            except BrokenProcessPool:
                lost.append(i)
            except Exception as exc:  # noqa: BLE001 - one trace's crash must not stop the others
                out[i] = failure(exc)
    if lost:
        with ThreadPoolExecutor(max_workers=jobs) as threads:
            for i, result in zip(lost, threads.map(lambda i: _run_alone(func, args[i], ctx), lost)):
                out[i] = result
    return out


def _run_alone(func: Callable, a: tuple, ctx):
    """``func(*a)`` in a one-worker pool of its own; a failure becomes its one-line reason."""
    with ProcessPoolExecutor(max_workers=1, mp_context=ctx, initializer=_one_thread) as pool:
        try:
            return pool.submit(func, *a).result()
        except BrokenProcessPool as exc:
            return f"worker failed: the worker process died ({exc})"
        except Exception as exc:  # noqa: BLE001
            return failure(exc)


def failure(exc: BaseException) -> str:
    """The one-line result standing for a call that raised ``exc``."""
    return f"worker failed: {type(exc).__name__}: {exc}"
