"""Where an experiment's cells run: this process, a local process pool, or a Dask cluster.

Cells are independent and seeded, so where one runs changes nothing in its numbers: the same function runs
each cell on a worker (one torch thread each) and its row comes back here, where it is kept at once
(``on_row``), whatever order the cells finish in, so a run stopped or a worker lost costs only the cells still
running.  On Dask a worker that dies mid-cell loses that cell, which the scheduler runs again on another worker.
A cell that raises is named in one error once the others are done (``on_fail`` is told its error at once, with
its traceback from the process that ran it), and stays to be redone on the next resume.

``scheduler`` is ``local:N`` (a LocalCluster of N worker processes on this machine) or a scheduler's address
(``tcp://host:8786``: a cluster whose workers see the run directory at the same path, a shared filesystem,
and have this project installed).  Nothing here needs ROS.
"""

from __future__ import annotations

import multiprocessing
import re
import signal
import socket
import threading
import uuid
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from contextlib import contextmanager
from typing import Any, TypeVar
from urllib.parse import urlsplit

Task = TypeVar("Task")
Row = dict[str, Any]
LOCAL = re.compile(r"^local:(\d+)$")
ADDRESS = re.compile(r"^(tcp|tls|inproc|ucx|ws|wss)://\S+$")


def check_scheduler(text: str) -> str:
    """``text`` if it names a scheduler (``local:N`` with N >= 1, or an address such as ``tcp://host:8786``);
    ValueError saying what is expected otherwise."""
    local = LOCAL.match(text)
    if (local and int(local.group(1)) >= 1) or ADDRESS.match(text):
        return text
    raise ValueError(f"scheduler must be local:N (N worker processes here, N >= 1) or a Dask scheduler address "
                     f"such as tcp://host:8786, got {text!r}")


def check_reachable(scheduler: str, timeout_s: float = 5.0) -> None:
    """ValueError unless something listens at a ``tcp://`` scheduler's address: checked before the source model
    is trained, not after (other schemes and ``local:N`` pass: only Dask itself can reach them)."""
    address = urlsplit(scheduler)
    if address.scheme != "tcp":
        return
    try:
        port = address.port
    except ValueError:
        port = None
    if not address.hostname or port is None:
        raise ValueError(f"scheduler {scheduler!r}: a tcp address names its host and port, e.g. tcp://host:8786")
    try:
        socket.create_connection((address.hostname, port), timeout=timeout_s).close()
    except OSError as err:
        raise ValueError(f"no Dask scheduler answers at {scheduler} ({err.strerror or err}): start one "
                         "(`dask scheduler`) or check the address") from None


class CellsFailed(RuntimeError):
    """Cells raised while the others ran and were kept: one error for all of them, each named, once the run is
    over (a resume runs them again)."""

    def __init__(self, failed: Sequence[str], total: int, where: str = "") -> None:
        super().__init__(f"{len(failed)} of {total} cells failed{where} (the others are kept; run again to redo "
                         f"these): {'; '.join(failed)}")
        self.failed = list(failed)


def run_cells(fn: Callable[[Task], Row], tasks: Sequence[Task], on_row: Callable[[Task, Row], None],
              workers: int = 1, scheduler: str | None = None, bar: Any = None, name: Callable[[Task], str] = str,
              key: Callable[[Task], str] | None = None,
              on_fail: Callable[[Task, BaseException], None] | None = None) -> None:
    """``fn(task)`` for every task, each row handed to ``on_row`` as it comes: serially (``workers == 1``), on a
    local process pool of ``workers``, or on the Dask ``scheduler``.

    A task that raises does not stop the others: CellsFailed once they ran, naming each failed task by
    ``name(task)``; ``on_fail(task, error)`` is called as each fails (a pool's error has the worker's traceback as
    its cause, Dask's the worker's frames as its own; :func:`traceback.format_exception` shows both).  An error of
    ``on_row`` or ``on_fail`` (a full disk) or Ctrl-C stops the run at once, its workers with it; the rows handed
    over so far stay kept.  ``key(task)`` (default ``name``) tells a task from the run's others;
    with an id of this call it is the task's Dask key, so two runs sharing a scheduler never share a result.
    """
    failed: list[str] = []

    def fail(task: Task, err: BaseException) -> None:
        failed.append(f"{name(task)}: {err!r}")
        if on_fail is not None:
            on_fail(task, err)
        if bar is not None:
            bar.set_postfix(failed=len(failed))

    if scheduler is not None:
        _run_on_dask(fn, tasks, on_row, fail, check_scheduler(scheduler), key or name)
    elif workers == 1 or len(tasks) <= 1:
        for task in tasks:
            try:
                row = fn(task)
            except Exception as err:  # any error of one cell (a bug, a numerical error, memory): the others run on
                fail(task, err)
                continue
            on_row(task, row)
    else:
        _run_on_pool(fn, tasks, on_row, fail, workers)
    if failed:
        raise CellsFailed(failed, len(tasks), "" if scheduler is None else f" on {scheduler}")


@contextmanager
def _interrupts_ignored() -> Iterator[None]:
    """SIGINT ignored while child processes start (where this thread may set it): they inherit that."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _worker_signals() -> None:
    """Pool workers leave Ctrl-C (sent to the whole process group) to the parent, which stops them and keeps the
    rows that came back: no worker prints a traceback.  They end on the SIGTERM that stops them whatever handler
    the parent had when they were forked (one that only sets a flag let a worker finish its cell first)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _run_on_pool(fn: Callable[[Task], Row], tasks: Sequence[Task], on_row: Callable[[Task, Row], None],
                 fail: Callable[[Task, BaseException], None], workers: int) -> None:
    """The tasks on a local pool of ``workers`` processes, each row kept as soon as it is back (not in task order:
    a kill then loses only the cells still running)."""
    ctx = multiprocessing.get_context("fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn")
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_worker_signals)
    try:
        futures = {pool.submit(fn, task): task for task in tasks}
        for future in as_completed(futures):
            error = future.exception()
            if error is None:
                on_row(futures[future], future.result())
            else:  # the cell's own error, or BrokenProcessPool for a worker that died (a resume redoes it)
                fail(futures[future], error)
    except BaseException:  # Ctrl-C or on_row's error: the workers stop now, not after every queued cell
        for process in list((getattr(pool, "_processes", None) or {}).values()):  # (no public way before 3.14)
            process.terminate()
        raise
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


@contextmanager
def dask_client(scheduler: str) -> Iterator[Any]:
    """A Dask client on ``scheduler`` (``local:N`` starts a LocalCluster of N single-threaded processes)."""
    from distributed import Client, LocalCluster

    local = LOCAL.match(scheduler)
    if local:
        with _interrupts_ignored():  # its processes inherit that, and leave Ctrl-C to this one (no tracebacks)
            cluster = LocalCluster(n_workers=int(local.group(1)), threads_per_worker=1, processes=True,
                                   dashboard_address=None)
        with cluster, Client(cluster) as client:
            yield client
    else:
        with Client(scheduler, timeout="30s") as client:
            yield client


def _run_on_dask(fn: Callable[[Task], Row], tasks: Sequence[Task], on_row: Callable[[Task, Row], None],
                 fail: Callable[[Task, BaseException], None], scheduler: str, key: Callable[[Task], str]) -> None:
    from distributed import as_completed as completed

    run = uuid.uuid4().hex  # keys unique to this run: another run on the scheduler never gets these results
    with dask_client(scheduler) as client:
        futures = {client.submit(fn, task, key=f"{key(task)}-{run}"): task for task in tasks}
        for future in completed(futures):
            if future.status == "finished":
                on_row(futures[future], future.result())
            else:
                fail(futures[future], future.exception())
