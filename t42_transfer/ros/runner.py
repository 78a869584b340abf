"""Run one registered node as a process: ROS arguments -> params -> transport -> node -> spin.

The process spins until SIGINT or SIGTERM (or, for a node with a ``finished``
property such as the explorer, until its work is done), then closes the node (a recorder
finishes its bag) and the transport and exits 0.  A bad command line or
parameter exits 2 with one ``t42: error: ...`` line and no traceback.  Logs go
to stderr in the ROS console format ``[INFO] [<unix time>] [<node>]: message``.
"""

from __future__ import annotations

import logging
import signal
import sys
import threading
from collections.abc import Sequence
from types import FrameType

from t42_transfer.nodes.registry import NODES
from t42_transfer.ros.backends import make_transport
from t42_transfer.ros.params import load_params, node_options, parse_ros_args

_NODE_LOGGERS = "t42_transfer.ros."


class RosFormatter(logging.Formatter):
    """``[LEVEL] [seconds.nanoseconds] [node]: message``, as rcutils prints by default."""

    def format(self, record: logging.LogRecord) -> str:
        name = record.name[len(_NODE_LOGGERS):] if record.name.startswith(_NODE_LOGGERS) else record.name
        level = {"WARNING": "WARN", "CRITICAL": "FATAL"}.get(record.levelname, record.levelname)
        text = f"[{level}] [{record.created:.9f}] [{name}]: {record.getMessage()}"
        if record.exc_info:
            text += "\n" + self.formatException(record.exc_info)
        return text


def configure_logging(level: int = logging.INFO) -> None:
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(RosFormatter())
    logging.basicConfig(level=level, handlers=[handler], force=True)


def _error(message: str) -> int:
    print(f"t42: error: {message}", file=sys.stderr)
    return 2


def run_node(name: str, argv: Sequence[str]) -> int:
    """Run node ``name`` of :data:`~t42_transfer.nodes.registry.NODES` with ROS arguments ``argv``; the exit code.

    SIGINT/SIGTERM are caught from the start, so a stop request during the (slow)
    imports and setup still ends in a clean close and exit 0.
    """
    stop = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        return _run(name, argv, stop)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _run(name: str, argv: Sequence[str], stop: threading.Event) -> int:
    spec = NODES.get(name)
    if spec is None:
        return _error(f"unknown node {name!r}; available: {', '.join(NODES)}")
    try:
        rest, ros_args = parse_ros_args(argv)
        if rest:
            raise ValueError(f"unexpected arguments {' '.join(rest)} (node options go after --ros-args)")
        node_name = ros_args.node_name or spec.default_name
        params = load_params(spec.params_class(), node_name, ros_args.params_files, ros_args.overrides)
        options = node_options(node_name, ros_args.params_files, ros_args.overrides)
        transport = make_transport(node_name)
    except ValueError as err:
        return _error(str(err))
    configure_logging()
    log = logging.getLogger(_NODE_LOGGERS + node_name)
    with transport:
        if options.use_sim_time:
            transport.use_sim_time()
        node = spec.node_class()(transport, params)
        try:
            log.info("running (%s); SIGINT or SIGTERM stops", type(transport).__name__)
            transport.spin(until=lambda: stop.is_set() or bool(getattr(node, "finished", False)))
        finally:
            node.close()
    log.info("shut down cleanly")
    return 0
