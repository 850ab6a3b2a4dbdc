"""Traces in parallel processes: one worker process per job, one thread per worker.

Workers are *spawned* (not forked): a forked child of a process that has already started torch or
OpenMP threads can deadlock, and spawn behaves the same on Linux, macOS and Windows. Each worker
limits itself to one thread before anything heavy is imported, so ``--jobs N`` uses N cores, not
N times all of them. A trace whose worker raises, or dies, is reported as a failure of that trace;
the others go on.
"""
from __future__ import annotations

import multiprocessing
import os
import sys
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
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
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=jobs, mp_context=ctx, initializer=_one_thread) as pool:
        futures = {pool.submit(func, *a): i for i, a in enumerate(args)}
        for fut in tqdm(as_completed(futures), total=len(futures), desc="traces", disable=not progress):
            i = futures[fut]
            try:
                out[i] = fut.result()
            except BrokenProcessPool as exc:
                out[i] = f"worker failed: the worker process died ({exc})"
            except Exception as exc:  # noqa: BLE001 - one trace's crash must not stop the others
                out[i] = f"worker failed: {type(exc).__name__}: {exc}"
    return out
