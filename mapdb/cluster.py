"""Where a command's tasks run: in this process, on a local Dask cluster, or on an existing one.

The one place that sets Dask up (``mapdb analyze --jobs/--scheduler``, and later ``mapdb build``).
:func:`open_client` gives ``None`` (run in this process, no Dask needed), a client of a
:class:`distributed.LocalCluster` of ``jobs`` single-threaded worker processes listening on the loopback
interface only, or a client of the scheduler at ``scheduler``; :func:`run_tasks` runs a function over a
list of argument tuples through either and yields each result as it completes; :func:`run_pool` runs tasks
on a cluster at most one a worker at a time, each ending task free to add more.

Dask is an optional extra: without it, asking for ``jobs`` or a ``scheduler`` raises a one-line
:class:`DaskMissingError` saying how to install it.  A scheduler that does not answer within
``timeout_s`` is a one-line :class:`SchedulerError`, not a hang.

Examples
--------
>>> with open_client(None, None) as client:
...     sorted(run_tasks(client, pow, [(2, 3), (3, 2)]))
[(0, 8), (1, 9)]
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any

from .errors import DaskMissingError, SchedulerError

__all__ = [
    "DEFAULT_TIMEOUT_S",
    "DaskMissingError",
    "SchedulerError",
    "open_client",
    "run_pool",
    "run_tasks",
    "worker_count",
]

# How long a scheduler (or a freshly started local cluster) may take to answer.
DEFAULT_TIMEOUT_S = 10.0
INSTALL_HINT = 'pip install "mapdb[dask]"'




def _distributed(what: str) -> Any:
    try:
        import distributed
    except ImportError:
        raise DaskMissingError(f"{what} needs dask.distributed, which is not installed: {INSTALL_HINT}") from None
    return distributed


@contextmanager
def open_client(jobs: int | None, scheduler: str | None, timeout_s: float = DEFAULT_TIMEOUT_S) -> Iterator[Any]:
    """A Dask client to run tasks on, or None to run them in this process.

    Parameters
    ----------
    jobs : int, optional
        Start a local cluster of this many worker processes (one thread each) on 127.0.0.1, closed on exit.
    scheduler : str, optional
        Address of a running ``dask.distributed`` scheduler (``tcp://HOST:PORT``); its workers must be able
        to read the files named in the tasks (a shared file system).
    timeout_s : float
        Seconds to wait for the scheduler (or the local cluster) before giving up.

    Raises
    ------
    ValueError
        If both ``jobs`` and ``scheduler`` are given, or ``jobs < 1``.
    DaskMissingError
        If either is given and dask.distributed is not installed.
    SchedulerError
        If the scheduler does not answer within ``timeout_s`` or its address is malformed.
    """
    if jobs is not None and scheduler is not None:
        raise ValueError("give --jobs (a local cluster) or --scheduler (an existing one), not both")
    if jobs is None and scheduler is None:
        yield None
        return
    if jobs is not None and jobs < 1:
        raise ValueError(f"jobs must be >= 1, got {jobs}")
    if scheduler is not None:
        with _remote_client(scheduler, timeout_s) as client:
            yield client
        return
    assert jobs is not None
    with _local_client(jobs, timeout_s) as client:
        yield client


@contextmanager
def _remote_client(address: str, timeout_s: float) -> Iterator[Any]:
    distributed = _distributed("--scheduler")
    try:
        client = distributed.Client(address, timeout=timeout_s, set_as_default=False)
    except (OSError, TimeoutError) as exc:
        raise SchedulerError(f"{address}: no Dask scheduler answered within {timeout_s:g} s "
                             f"({_first_line(exc)})") from None
    except (ValueError, TypeError) as exc:
        raise SchedulerError(f"{address}: not a Dask scheduler address ({_first_line(exc)}); "
                             "expected tcp://HOST:PORT") from None
    try:
        yield client
    finally:
        client.close()


@contextmanager
def _local_client(jobs: int, timeout_s: float) -> Iterator[Any]:
    distributed = _distributed("--jobs")
    # Workers are whole processes with one thread each (the matcher holds the GIL), listening on the loopback
    # interface only; the dashboard on a free port (None would still claim 8787), and only critical messages in
    # the log: stderr carries the progress bar and a command's one-line error, and a worker still running a task
    # when the cluster closes on an error logs its lost heartbeat as an error, with a traceback.
    cluster = distributed.LocalCluster(n_workers=jobs, threads_per_worker=1, processes=True, host="127.0.0.1",
                                       dashboard_address=":0", silence_logs=logging.CRITICAL)
    try:
        client = distributed.Client(cluster, timeout=timeout_s, set_as_default=False)
        try:
            client.wait_for_workers(jobs, timeout=timeout_s * max(1, jobs))
            yield client
        finally:
            client.close()
    finally:
        cluster.close()


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip() or exc.__class__.__name__
    return text.splitlines()[0][:200]


def worker_count(client: Any) -> int:
    """Worker threads a client's cluster has (1 for None: this process)."""
    if client is None:
        return 1
    workers = client.scheduler_info().get("workers", {})
    return max(1, sum(int(w.get("nthreads", 1)) for w in workers.values()))


def run_tasks(client: Any, fn: Callable[..., Any], tasks: Sequence[tuple[Any, ...]]) -> Iterator[tuple[int, Any]]:
    """``(i, fn(*tasks[i]))`` for every task, each as soon as it is done (in any order with a client).

    Without a client the tasks run here, one after another, in order.  A task's exception is raised
    here (a :class:`~mapdb.errors.MapdbError` raised on a worker keeps its type and message); the tasks
    not yet run are then cancelled.
    """
    if client is None:
        for i, args in enumerate(tasks):
            yield i, fn(*args)
        return
    import distributed

    # Keys name the tasks by position (pure=False gives each submission its own key anyway).
    futures = [client.submit(fn, *args, pure=False) for args in tasks]
    index = {future.key: i for i, future in enumerate(futures)}
    try:
        for future, result in distributed.as_completed(futures, loop=client.loop, with_results=True):
            yield index[future.key], result
    finally:
        client.cancel([f for f in futures if not f.done()])


def run_pool(client: Any, limit: int, tasks: list[Any], done: Callable[[Any, Any], list[Any]]) -> None:
    """Run ``tasks`` on the cluster, at most ``limit`` at a time, the next handed out as one ends: so that a task
    goes to the worker that is free, not to one still busy (``limit``: the workers).  Each task has ``fn`` and
    ``args`` (it runs ``fn(*args)``); ``done(task, result)`` is called here for each as it ends, and gives tasks
    to run after those waiting.  An exception ``done`` raises is raised here (the tasks running are then
    cancelled)."""
    import distributed

    waiting = list(tasks)
    running: dict[str, tuple[Any, Any]] = {}
    ended = distributed.as_completed(loop=client.loop, with_results=True)

    def hand_out() -> None:
        while waiting and len(running) < limit:
            task = waiting.pop(0)
            future = client.submit(task.fn, *task.args, pure=False)
            running[future.key] = (task, future)
            ended.add(future)

    try:
        hand_out()
        for future, result in ended:
            task, _ = running.pop(future.key)
            waiting.extend(done(task, result))
            hand_out()
    finally:
        client.cancel([future for _, future in running.values()])
