"""Traces on a Dask cluster (``dask.distributed``): the ``--scheduler ADDRESS`` back end of
:func:`fusion.parallel.map_traces`.

Dask is an optional extra (``pip install gnssfuse[cluster]``) and is imported only here, only when a
scheduler is asked for. Each call runs as one Dask task through :func:`fusion.parallel.guarded`, so an
exception on a worker becomes that trace's one-line failure, as with ``--jobs``; a worker that dies
while running a call is Dask's to retry (``distributed.scheduler.allowed-failures`` times), after which
the call fails alone (``KilledWorker``). The workers must be able to import ``fusion``
(gnssfuse installed where they run) and see the input and output folders under the same paths (a
shared file system); they are best started with one thread each (``dask worker ADDRESS --nthreads
1``), since much of the pipeline is Python, which holds the GIL. How long to wait for
the scheduler is Dask's own setting ``distributed.comm.timeouts.connect`` (environment variable
``DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT``, default 30 s).
"""
from __future__ import annotations

import importlib.util
from collections.abc import Callable, Sequence

from tqdm import tqdm

from fusion.errors import GnssfuseError
from fusion.parallel import _one_thread, failure, guarded, one_line, plain_warnings


class ClusterError(GnssfuseError):
    """The Dask scheduler asked for cannot be used (dask missing, bad or unreachable address)."""


def _client(address: str):
    """A ``distributed.Client`` connected to ``address``, or a one-line :class:`ClusterError`."""
    try:
        from distributed import Client
    except ImportError:
        raise ClusterError("--scheduler needs dask.distributed, which is not installed: "
                           "pip install 'gnssfuse[cluster]'") from None
    if not address.strip():
        raise ClusterError("--scheduler needs an address, e.g. tcp://HOST:8786")
    try:
        client = Client(address, set_as_default=False)
    except (OSError, TimeoutError, ValueError) as exc:
        raise ClusterError(f"cannot reach the Dask scheduler at {address}: {exc}") from None
    try:
        check_environment(client, address)
    except BaseException:
        client.close()
        raise
    return client


def check_environment(client, address: str) -> None:
    """One round trip before any work: the scheduler (which unpickles the tasks) and every worker
    must import this module, i.e. have this gnssfuse installed; otherwise every trace would fail
    with the same paragraph from Dask."""
    try:
        where = {"the scheduler": client.run_on_scheduler(importlib.util.find_spec, __name__),
                 **client.run(importlib.util.find_spec, __name__)}
    except Exception as exc:  # noqa: BLE001 - whatever Dask raises, the run cannot start
        raise ClusterError(f"the Dask cluster at {address} did not answer: {type(exc).__name__}: "
                           f"{one_line(str(exc))}") from None
    missing = [str(w) for w, spec in where.items() if spec is None]
    if missing:
        raise ClusterError(f"{', '.join(missing)} of the Dask cluster at {address} cannot import {__name__}: "
                           "install this gnssfuse (with its [cluster] extra) where the scheduler and workers run")


def _on_worker(func: Callable, a: tuple):
    """On a Dask worker: ``func(*a)`` with one BLAS/torch thread, an exception becoming its failure line."""
    _one_thread()
    plain_warnings()
    return guarded(func, *a)


def map_on_cluster(func: Callable, args: Sequence[tuple], order: Sequence[int], address: str,
                   progress: bool = False) -> list:
    """``[func(*a) for a in args]`` on the Dask cluster whose scheduler is at ``address``, started in
    ``order`` (indices into ``args``), results in the order of ``args``; a call that fails (raises,
    or kills its worker past Dask's retries) has its one-line reason as result, as in
    :func:`fusion.parallel.map_traces`.

    Calls are handed to the scheduler only as worker threads free up (as many in flight as the
    cluster has threads, counted again after each call, so that workers that join are used), in
    ``order``, so that the costliest traces (first in ``order``) do not start last, and a worker does not
    hold a second trace queued behind the one it runs (which a crash of the first would take down too)
    provided the scheduler gives a worker no more tasks than threads: Dask's default worker-saturation
    (1.1) lets a one-thread worker queue a second one, so start the scheduler with
    ``DASK_DISTRIBUTED__SCHEDULER__WORKER_SATURATION=1.0`` (README).
    """
    todo = list(order)[::-1]
    out: list = [None] * len(args)
    with _client(address) as client:
        from distributed import as_completed
        running, index = as_completed(loop=client.loop), {}

        def fill() -> None:
            while todo and running.count() < max(1, sum(client.nthreads().values())):
                i = todo.pop()
                # pure=False: the same trace given twice is two calls, not one result
                fut = client.submit(_on_worker, func, args[i], pure=False)
                index[fut.key] = i
                running.add(fut)

        fill()
        with tqdm(total=len(args), desc="traces", disable=not progress) as bar:
            for fut in running:
                out[index[fut.key]] = _result(fut)
                bar.update()
                fill()
    return out


def _result(fut):
    """A finished future's value, or the failure line of what stopped it (a worker killed past the
    retries: ``KilledWorker``; a lost scheduler: cancelled)."""
    try:
        return fut.result()
    except Exception as exc:  # noqa: BLE001 - one trace's failure must not stop the others
        from distributed import KilledWorker
        if isinstance(exc, KilledWorker):       # its own text is a paragraph; the workers' logs say why
            return f"the worker process died (each of the {exc.allowed_failures + 1} Dask workers that ran it)"
        return failure(exc)
