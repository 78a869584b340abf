"""Shared fixtures: small synthetic trajectory sets and the location of the public real-hand files."""

from __future__ import annotations

import contextlib
import fcntl
import os
import random
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import IO, TYPE_CHECKING

import numpy as np
import pytest

from t42_transfer.conventions import ACTION_UNIT_RAD
from t42_transfer.data.bag import assign_start_times, write_bag
from t42_transfer.data.t42_real import REAL_FILES, real_data_dir
from t42_transfer.data.trajectory import Trajectory, TrajectorySet
from t42_transfer.ros.runner import announce_often, freeze_heap

sys.path.insert(0, str(Path(__file__).parent))  # test helpers (ros_rig)
# One OpenMP thread for torch here and in every process a test starts (node processes inherit the environment):
# on a busy 2-core machine a second thread waiting for a core costs 10-20x (200 epochs of the transfer server's
# training: 4.5-8.7 s with one thread, 71-98 s with two at load 8).  A value the caller set is kept.
os.environ.setdefault("OMP_NUM_THREADS", "1")
# Quick Fast DDS announcements here (the tests' own rig nodes) and in every node process a test starts, as `t42 up`
# and `t42 node` set them: a participant that starts after its peers is found within 0.5 s instead of up to 3 s.
announce_often()
if TYPE_CHECKING:
    from ros_rig import RosRig

MakeSet = Callable[..., TrajectorySet]


def _synthetic_set(
    lengths: Sequence[int] = (20, 25, 16),
    *,
    seed: int = 0,
    hand: str = "sim_a",
    angles: bool | None = None,
) -> TrajectorySet:
    """Random-walk episodes; ``angles=None`` gives actuator angles to every other episode only."""
    rng = np.random.default_rng(seed)
    reasons = ("length", "dropped", "overload", "lost_contact", "")
    episodes = []
    for i, steps in enumerate(lengths):
        actions = rng.uniform(-1.0, 1.0, size=(steps, 2))
        xy = np.cumsum(rng.normal(0.0, 0.4, size=(steps + 1, 2)), axis=0) + (10.0, 110.0)
        loads = np.array([100.0, -100.0]) + rng.normal(0.0, 5.0, size=(steps + 1, 2))
        known = angles if angles is not None else i % 2 == 0
        joint = np.vstack([[0.3, 0.3], 0.3 + ACTION_UNIT_RAD * np.cumsum(actions, axis=0)]) if known else None
        episodes.append(
            Trajectory(
                states=np.column_stack([xy, loads]),
                actions=actions,
                actuator_angles=joint,
                end_reason=reasons[i % len(reasons)],
                hand=hand,
            )
        )
    return TrajectorySet(assign_start_times(episodes), hand=hand)


@pytest.fixture(scope="session")
def make_set() -> MakeSet:
    """Factory for synthetic sets: ``make_set(lengths, seed=, hand=, angles=)``."""
    return _synthetic_set


@pytest.fixture(scope="session")
def small_set() -> TrajectorySet:
    """Three episodes (20, 25, 16 transitions), angles on the first and last."""
    return _synthetic_set()


@pytest.fixture(scope="module")
def episode(make_set) -> Trajectory:
    """One 60-transition episode with actuator angles."""
    return make_set((60,), angles=True)[0]


@pytest.fixture(scope="module")
def big_bag(tmp_path_factory, make_set) -> tuple[Path, TrajectorySet]:
    """A bag of about three 1 MiB MCAP chunks (rosbags' chunk size)."""
    data = make_set((450,) * 14, seed=7)
    return write_bag(tmp_path_factory.mktemp("big") / "bag", data), data


@pytest.fixture(scope="session")
def t42_real_dir() -> Path:
    """The public real T42 pickles: $T42_REAL_DATA or <repo>/../shared/data/t42_real; skips when absent."""
    directory = real_data_dir()
    if not all((directory / name).is_file() for name in REAL_FILES.values()):
        pytest.skip(
            f"real T42 test paths not found in {directory} (set T42_REAL_DATA); "
            "they are not redistributed with the project"
        )
    return directory


@pytest.fixture(scope="module", autouse=True)
def _heap_frozen() -> None:
    """At each module's start, freeze the heap, as each node process does (``freeze_heap``): the imports of every
    test module, then what the tests before left alive (session fixtures, pytest's records; the module fixtures
    before are torn down by then, and autouse, this runs before the module's own).  Unfrozen, a worker's full
    collections walked ~300k objects with the GIL held, 470-610 ms at the longest in a fast-suite run (87-166 ms
    frozen), stopping the rclpy nodes, emulated hands and timing checks tests run in this process.  What is
    frozen and later becomes cyclic garbage stays for the worker's life: a few objects a module, not a leak
    that grows with a test's length."""
    freeze_heap()


@pytest.fixture(scope="module")
def one_torch_thread() -> Iterator[None]:
    """One torch thread: on a busy 2-core machine a second OpenMP thread waiting for a core costs 10x."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="session")
def source_model(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A source model trained for 1 epoch on the source fixture bag, with its workspace (read-only: shared by the
    suite tests, which would each train the same one)."""
    import torch

    from t42_transfer.data.bag import read_bag
    from t42_transfer.models.checkpoint import save_model
    from t42_transfer.models.training import TrainConfig, train_transition_model
    from t42_transfer.planning.workspace import Workspace

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        data = read_bag(Path(__file__).resolve().parents[1] / "bags" / "source_small")
        model, _ = train_transition_model(data, TrainConfig(epochs=1))
    finally:
        torch.set_num_threads(threads)
    path = tmp_path_factory.mktemp("source") / "source.safetensors"
    return save_model(model, path, method="source", extra={"workspace": Workspace.from_trajectories(data).to_dict()})


# --------------------------------------------------------------------------- ROS 2 (rclpy)
_DOMAIN_LOCKS = Path(os.environ.get("TMPDIR", "/tmp")) / "t42-ros-domains"
DOMAIN_REST_S = 25.0
"""How long a domain rests after a test let it go before another test takes it: a node process killed at a test's
end stays on the others' graphs until its discovery lease runs out (Fast DDS: 20 s), and a later test on the domain
would see its servers beside its own."""


@contextlib.contextmanager
def _own_domain(env: pytest.MonkeyPatch) -> Iterator[int]:
    """A ROS_DOMAIN_ID no other test (of this run or a parallel one) holds or let go of in the last
    :data:`DOMAIN_REST_S` (while every domain rests, any free one), set in ``env`` with discovery on LOCALHOST (node
    processes a test starts inherit both), held until the block ends.  A domain whose holder was killed (its lock
    free, its file still saying held) starts its rest when found so."""
    _DOMAIN_LOCKS.mkdir(parents=True, exist_ok=True)
    ids = list(range(1, 200))
    random.SystemRandom().shuffle(ids)
    for rested in (True, False):
        for domain in ids:
            handle = open(_DOMAIN_LOCKS / f"{domain}.lock", "a+")  # (its text: when it was let go, or HELD)
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
                handle.seek(0)
                text = handle.read()
                if text == _HELD:  # its holder was killed: its nodes may still be on the graph
                    _write(handle, repr(time.time()))
                    raise OSError("let go just now")
                if rested and time.time() - float(text or 0.0) < DOMAIN_REST_S:
                    raise OSError("resting")
            except (OSError, ValueError):
                handle.close()
                continue
            _write(handle, _HELD)
            env.setenv("ROS_DOMAIN_ID", str(domain))
            env.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
            try:
                yield domain
            finally:
                _write(handle, repr(time.time()))
                handle.close()
            return
    pytest.fail("no free ROS domain id")


_HELD = "held"


def _write(handle: IO[str], text: str) -> None:
    handle.seek(0)
    handle.truncate()
    handle.write(text)
    handle.flush()


@pytest.fixture
def ros_domain(monkeypatch: pytest.MonkeyPatch) -> Iterator[int]:
    """The test's own ROS domain (:func:`_own_domain`) for the test."""
    with _own_domain(monkeypatch) as domain:
        yield domain


@pytest.fixture
def ros(ros_domain: int, request: pytest.FixtureRequest) -> Iterator[RosRig]:
    """rclpy in this process on the test's own domain: add nodes, spin until a condition; all torn down after.

    One executor thread, as ``t42 node`` gives most nodes; ``@pytest.mark.executor_threads(n)`` asks for
    a MultiThreadedExecutor (as the transfer server's process has), ``@pytest.mark.events_executor`` for
    rclpy's EventsExecutor (as the driver's process has).
    """
    from ros_rig import RosRig

    marker = request.node.get_closest_marker("executor_threads")
    events = request.node.get_closest_marker("events_executor") is not None
    rig = RosRig(ros_domain, threads=marker.args[0] if marker else 1, events=events)
    try:
        yield rig
    finally:
        rig.shutdown()


@pytest.fixture(scope="module")
def module_ros_domain() -> Iterator[int]:
    """As :func:`ros_domain`, held for a whole module: for nodes its tests share (one emulated hand that needs a
    5 s grasp before any test can use it, say)."""
    with pytest.MonkeyPatch.context() as env, _own_domain(env) as domain:
        yield domain


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--record-file-seconds", metavar="PATH", type=Path,
                     help="write each test file's seconds as JSON (test/file_seconds.json orders the parallel batch)")


def pytest_configure(config: pytest.Config) -> None:
    from file_order import FileSeconds

    path = config.getoption("record_file_seconds")
    if path is not None and not hasattr(config, "workerinput"):  # the controller hears every worker's reports
        config.pluginmanager.register(FileSeconds(path), "file_seconds")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """In xdist's workers, the files longest first (:mod:`file_order`): the order they report is the order the
    files are handed out in, with ``--no-loadscope-reorder``."""
    from file_order import load_seconds, order_items

    if hasattr(config, "workerinput"):
        order_items(items, load_seconds())


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo) -> Iterator[pytest.TestReport]:
    """Each phase's report on its item (``item.report_call``...): a fixture shared by tests learns whether the
    test that used it passed."""
    report = yield
    setattr(item, f"report_{report.when}", report)
    return report
