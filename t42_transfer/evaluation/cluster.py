"""Where an experiment's cells run: this process, a local process pool, or a Dask cluster.

Cells are independent and seeded, so where one runs changes nothing in its numbers: the same function runs
each cell on a worker (one torch thread each) and its row comes back here, where it is kept at once
(``on_row``), so a run stopped or a worker lost costs only the cells still running.  On Dask a worker that
dies mid-cell loses that cell, which the scheduler runs again on another worker; a cell that fails for any
other reason is reported once the others are done and stays to be redone on the next resume.

``scheduler`` is ``local:N`` (a LocalCluster of N worker processes on this machine) or a scheduler's address
(``tcp://host:8786``: a cluster whose workers see the run directory at the same path, a shared filesystem,
and have this project installed).  Nothing here needs ROS.
"""

from __future__ import annotations

import multiprocessing
import re
import socket
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
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


def run_cells(fn: Callable[[Task], Row], tasks: Sequence[Task], on_row: Callable[[Task, Row], None],
              workers: int = 1, scheduler: str | None = None, bar: Any = None) -> None:
    """``fn(task)`` for every task, each row handed to ``on_row`` as it comes: serially (``workers == 1``), on a
    local process pool of ``workers``, or on the Dask ``scheduler``.  RuntimeError after the others when cells
    failed on Dask (their rows were never kept: a resume runs them again)."""
    if scheduler is not None:
        _run_on_dask(fn, tasks, on_row, check_scheduler(scheduler), bar)
    elif workers == 1 or len(tasks) <= 1:
        for task in tasks:
            on_row(task, fn(task))
    else:
        ctx = multiprocessing.get_context("fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn")
        with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
            for task, row in zip(tasks, pool.map(fn, tasks), strict=True):
                on_row(task, row)


@contextmanager
def dask_client(scheduler: str) -> Iterator[Any]:
    """A Dask client on ``scheduler`` (``local:N`` starts a LocalCluster of N single-threaded processes)."""
    from distributed import Client, LocalCluster

    local = LOCAL.match(scheduler)
    if local:
        with LocalCluster(n_workers=int(local.group(1)), threads_per_worker=1, processes=True,
                          dashboard_address=None) as cluster, Client(cluster) as client:
            yield client
    else:
        with Client(scheduler, timeout="30s") as client:
            yield client


def _run_on_dask(fn: Callable[[Task], Row], tasks: Sequence[Task], on_row: Callable[[Task, Row], None],
                 scheduler: str, bar: Any) -> None:
    from distributed import as_completed

    failed: list[str] = []
    with dask_client(scheduler) as client:
        # pure=False: every cell is its own task even if two tasks pickle alike; the key names the cell.
        futures = {client.submit(fn, task, pure=False, key=f"cell-{i}"): task for i, task in enumerate(tasks)}
        for future in as_completed(futures):
            task = futures[future]
            if future.status == "finished":
                on_row(task, future.result())
            else:
                failed.append(f"{future.key}: {future.exception()!r}")
            if bar is not None:
                running = sum(not f.done() for f in futures)
                bar.set_postfix(done=len(futures) - running - len(failed), failed=len(failed), running=running)
    if failed:
        raise RuntimeError(f"{len(failed)} of {len(tasks)} cells failed on {scheduler} (the others are kept; "
                           f"run again to redo these): {'; '.join(failed)}")
