"""Run one registered node as a process, as ``ros2 run`` does: rclpy parses ``--ros-args``.

``t42 node NAME [--ros-args ...]`` and the console script ``NAME`` (``ros2 run
t42_transfer NAME``) both end here.  rclpy takes the whole argument list
(remapping, namespaces, ``-p``, ``--params-file``, ``--log-level``,
``use_sim_time``); the node declares its parameters.  Once it is built, what its start-up left on the heap is
frozen out of garbage collection (:func:`freeze_heap`).  The node spins on the
executor :func:`make_executor` picks for it until SIGINT, SIGTERM or SIGHUP (its terminal or ssh session gone), or
until a
node with a ``finished`` property (the explorer) is done; then the node's
``close()`` runs (a recorder finishes its bag) and the process exits 0.  A bad
command line or parameter exits 2 with one ``t42: error: ...`` line.  An exception
out of a callback ends the spin, but ``close()`` still runs (a driver turns its
torque off) before it propagates (exit 1, with its traceback).
"""

from __future__ import annotations

import gc
import os
import signal
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from types import FrameType

from t42_transfer.nodes.registry import NODES
from t42_transfer.ros.exit_watchdog import ExitWatchdog

DISCOVERY_ENV = "ROS_AUTOMATIC_DISCOVERY_RANGE"
TEARDOWN_TIMEOUT_S = 8.0
"""How long releasing rclpy's handles may take after the node closed before the process exits regardless."""

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
"""What stops a node (and ``t42 up``) cleanly: Ctrl-C, ``kill``, and the terminal or ssh session closing (SIGHUP's
default would end the process at once, a driver's torque left on)."""
SUPERVISOR_ENV = "T42_SUPERVISOR_PID"
"""Set by ``t42 up`` for its children (:func:`stop_with_supervisor`)."""
RUNNING = "SIGINT or SIGTERM stops"
"""The end of a node's first log line once it runs (t42 up reads it: a node stopped before it is a start cut
short, not an unclean stop)."""


def make_executor(node_cls: type, context: object) -> object:
    """The executor a node class asks for with its ``executor_threads`` attribute (default 1), or its
    ``events_executor`` one.

    One thread (a SingleThreadedExecutor) unless the node has a callback that must run beside
    its others (the transfer server's long service call): rclpy's MultiThreadedExecutor spins
    without sleeping while a mutually exclusive callback runs and another of its group is ready
    (measured: a driver and a recorder in one such executor made 10 of 200 steps in 2 s), so it is
    used only where it is needed, with at least as many threads as such callbacks.  A node with
    ``events_executor = True`` (the Dynamixel driver, whose CPU per step is benchmarked against a bare
    servo loop) spins on rclpy's EventsExecutor, which builds no wait set at each wake; it awaits no
    coroutine callback in rclpy 7.1.6, so such a node has none.
    """
    from rclpy.executors import MultiThreadedExecutor, SingleThreadedExecutor

    if getattr(node_cls, "events_executor", False):
        from rclpy.experimental import EventsExecutor

        return EventsExecutor(context=context)
    threads = int(getattr(node_cls, "executor_threads", 1))
    if threads <= 1:
        return SingleThreadedExecutor(context=context)
    return MultiThreadedExecutor(num_threads=threads, context=context)


def keep_discovery_local(env: dict[str, str] | os._Environ[str] | None = None) -> str:
    """Set ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` unless the user chose a range, and quick announcements
    (:func:`announce_often`) unless the user gave Fast DDS a profile; the range in effect."""
    env = os.environ if env is None else env
    if not env.get(DISCOVERY_ENV):
        env[DISCOVERY_ENV] = "LOCALHOST"
    announce_often(env)
    return env[DISCOVERY_ENV]


FASTDDS_PROFILE_ENV = "FASTRTPS_DEFAULT_PROFILES_FILE"
"""The variable the Fast DDS of the rclpy wheels reads its default profile from (FASTDDS_... is not read)."""
QUICK_ANNOUNCEMENTS = """<?xml version="1.0" encoding="UTF-8" ?>
<!-- t42_transfer: participants announce themselves every 0.5 s (Fast DDS's default is 3 s), so a node that
     starts after its peers is found within half a second instead of at their next announcement. -->
<dds xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <profiles>
    <participant profile_name="t42_quick_announcements" is_default_profile="true">
      <rtps>
        <builtin>
          <discovery_config>
            <initialAnnouncements><count>5</count><period><nanosec>100000000</nanosec></period></initialAnnouncements>
            <leaseAnnouncement><sec>0</sec><nanosec>500000000</nanosec></leaseAnnouncement>
          </discovery_config>
        </builtin>
      </rtps>
    </participant>
  </profiles>
</dds>
"""


def announce_often(env: dict[str, str] | os._Environ[str] | None = None) -> str | None:
    """Point Fast DDS at :data:`QUICK_ANNOUNCEMENTS` unless a profile or another middleware was chosen; the
    profile file in effect (None: not Fast DDS's default profile of ours).

    Measured (bench/bench_startup.py): a participant that starts more than ~0.3 s after its peers is found only at
    their next announcement, every 3 s by default, so a suite whose torch-importing nodes start late came up
    after 6.4 s although they ran at 4.6 s; every process of a suite (and a test's rig) pays it."""
    env = os.environ if env is None else env
    if env.get(FASTDDS_PROFILE_ENV) or env.get("FASTDDS_DEFAULT_PROFILES_FILE"):
        return env.get(FASTDDS_PROFILE_ENV) or None
    if env.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp") != "rmw_fastrtps_cpp":
        return None
    import hashlib
    import tempfile

    digest = hashlib.sha256(QUICK_ANNOUNCEMENTS.encode()).hexdigest()[:12]
    path = Path(tempfile.gettempdir()) / f"t42_fastdds_{os.getuid()}_{digest}.xml"
    if not path.is_file():
        partial = path.with_name(f"{path.name}.{os.getpid()}.partial")
        partial.write_text(QUICK_ANNOUNCEMENTS)
        os.replace(partial, path)  # whole or absent, whoever else writes it at the same time
    env[FASTDDS_PROFILE_ENV] = str(path)
    return str(path)


def _error(message: str) -> int:
    print(f"t42: error: {message}", file=sys.stderr)
    return 2


def non_ros_args(argv: Sequence[str], what: str = "--ros-args") -> list[str]:
    """The arguments of ``argv`` outside its ``--ros-args`` part; ValueError ``bad <what>: ...`` for ROS arguments
    rcl cannot parse (a remapping to an invalid name, say), said before ``rclpy.init`` would raise an RCLError."""
    from rclpy.utilities import remove_ros_args

    try:
        return remove_ros_args(["t42", *argv])[1:]
    except Exception as err:  # rcl's parse error
        why = str(err).split(", at /")[0].removesuffix(" Error: error not set")  # (rcl's source line, no news)
        raise ValueError(f"bad {what}: {why}") from None


def run_node(name: str, argv: Sequence[str]) -> int:
    """Run node ``name`` of :data:`~t42_transfer.nodes.registry.NODES` with command line ``argv``; the exit code."""
    stop = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    # Caught from the start: a stop during the (slow) imports still ends in a clean close.
    previous = {sig: signal.signal(sig, on_signal) for sig in STOP_SIGNALS}
    stop_with_supervisor(stop)
    try:
        return _run(name, list(argv), stop)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


PR_SET_PDEATHSIG = 1


def stop_with_supervisor(stop: threading.Event) -> None:
    """A child of ``t42 up`` (:data:`SUPERVISOR_ENV` names its pid) gets SIGTERM when the supervisor dies, however
    it dies (SIGKILL, a crash), and so stops cleanly instead of running on orphaned (Linux: ``prctl``'s
    PR_SET_PDEATHSIG); one whose supervisor died before this ran stops at once.  The variable is taken out of the
    environment: a process this one starts is not ``t42 up``'s child."""
    supervisor = os.environ.pop(SUPERVISOR_ENV, "")
    if not supervisor.isdigit():
        return
    if sys.platform.startswith("linux"):
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
    if os.getppid() != int(supervisor):  # it died before the prctl: no signal will come
        stop.set()


def freeze_heap() -> None:
    """Collect once, then leave every object alive now out of all later collections (``gc.freeze``).

    A node's imports (torch, rclpy, numpy) leave ~300k objects the collector tracks, and each full collection
    walks them all with the GIL held: 150-250 ms in the suite's node processes, 1.2 s once on a loaded machine
    (measured with ``gc.callbacks``, 2026-12-07), every thread of the node stopped meanwhile: more than a
    driver's control period.  Frozen, they are never walked again; what the node makes from now on is
    collected as before.  (Objects frozen here that later become cyclic garbage are not freed: they were alive
    at start-up, and most live as long as the process; a model loaded at start-up and replaced later holds no
    cycle, so reference counting frees it.)"""
    gc.collect()
    gc.freeze()


def main() -> int:
    """Console script of every node: the node is the executable's name (``ros2 run t42_transfer mock_driver``)."""
    return run_node(Path(sys.argv[0]).stem, sys.argv[1:])


def _run(name: str, argv: list[str], stop: threading.Event) -> int:
    spec = NODES.get(name)
    if spec is None:
        return _error(f"unknown node {name!r}; available: {', '.join(NODES)}")
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    try:
        rest = non_ros_args(argv)
    except ValueError as err:
        return _error(str(err))
    if rest in (["-h"], ["--help"]):  # what ros2 param describe tells of a running node, before it runs
        from t42_transfer.ros.params import describe_params

        print(f"{name}: {spec.description}\nparameters (--ros-args -p NAME:=VALUE, or a --params-file):")
        print(describe_params(spec.node_class().params_class))
        return 0
    if rest:
        return _error(f"unexpected arguments {' '.join(rest)} (node options go after --ros-args; --help lists "
                      "the node's parameters)")
    context = rclpy.Context()
    try:
        rclpy.init(args=["t42"] + argv, context=context, signal_handler_options=SignalHandlerOptions.NO)
    except Exception as err:
        return _error(f"bad --ros-args: {err}")
    from t42_transfer.ros.params import undeclared_overrides

    node_cls = spec.node_class()
    executor = make_executor(node_cls, context)
    node = None
    status = 1  # what the process exits with should releasing rclpy's handles hang (an exception: 1)
    try:
        try:
            node = node_cls(context=context)
        except ValueError as err:
            status = _error(str(err))
            return status
        executor.add_node(node)
        freeze_heap()
        unknown = undeclared_overrides(node)
        if unknown:
            node.get_logger().warning(
                f"ignored, not parameters of this node: {', '.join(unknown)} (a typo? "
                f"`ros2 param list {node.get_fully_qualified_name()}` lists its parameters)")
        node.get_logger().info(f"running on {rclpy.get_rmw_implementation_identifier()}; {RUNNING}")
        try:
            while not stop.is_set() and not getattr(node, "finished", False):
                executor.spin_once(timeout_sec=0.1)
        except BaseException as err:  # a callback raised: the node still closes (a driver turns its torque off)
            node.get_logger().error(f"stopped by {err!r} from a callback; closing the node")
            node.close()  # (should this raise too, the first error stays its context)
            raise
        node.close()
        node.get_logger().info("shut down cleanly")
        status = 0
        return status
    finally:
        # The node's own work is closed above.  Releasing rclpy's handles can block inside the middleware
        # (seen in a busy graph, after "shut down cleanly", in rcl's node teardown) with the GIL held: a
        # native timer then prints where the process is stuck and exits with the node's own status.
        watchdog = ExitWatchdog()
        watchdog.arm(TEARDOWN_TIMEOUT_S, status)
        try:
            executor.shutdown(timeout_sec=5.0)
            if node is not None:
                node.destroy_node()
            if context.ok():
                rclpy.shutdown(context=context)
        finally:  # returned or raised: nothing hangs, and a raised error keeps its own exit
            watchdog.disarm()
