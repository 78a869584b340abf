"""The graph's parameters for the view node's Foxglove clients (the Parameters capability): every node's
parameters, named as Foxglove and foxglove_bridge name them (``/namespace/node.parameter``), read and set through
each node's standard parameter services (``list_parameters``, ``get_parameters``, ``set_parameters``).

Calls come on the WebSocket server's threads and wait (``timeout_s`` each) for the answers the node's executor
takes in; a node that does not answer is left out.  A set is refused by the node as a ``ros2 param set`` would be
(read-only, out of range, a bad value: the node's own checks); whole numbers sent for a double parameter are taken
as doubles (JSON does not tell 1 from 1.0).
"""

from __future__ import annotations

import threading
from collections.abc import Iterable
from typing import Any

import foxglove
from rcl_interfaces.msg import ParameterType as RosType
from rcl_interfaces.srv import GetParameters, ListParameters, SetParameters
from rclpy.node import Node
from rclpy.parameter import Parameter as RosParameter
from rclpy.parameter import parameter_value_to_python

FLOAT_HINTS = {RosType.PARAMETER_DOUBLE: foxglove.ParameterType.Float64,
               RosType.PARAMETER_DOUBLE_ARRAY: foxglove.ParameterType.Float64Array}


def _split(name: str) -> tuple[str, str]:
    """``/ns/node.param.sub`` -> (``/ns/node``, ``param.sub``)."""
    node, dot, param = name.partition(".")
    if not dot or not node.startswith("/") or not param:
        raise ValueError(f"{name!r} is not /node.parameter")
    return node, param


class GraphParameters:
    """Reads and sets the parameters of every node in ``node``'s graph."""

    def __init__(self, node: Node, timeout_s: float = 2.0) -> None:
        self.node, self.timeout_s = node, timeout_s
        self._clients: dict[tuple[str, type], Any] = {}
        self._types: dict[str, int] = {}
        """Full name -> the ROS type last read (a set keeps it)."""
        self._lock = threading.Lock()

    def _call(self, fqn: str, srv: type, suffix: str, request: Any) -> Any:
        with self._lock:
            client = self._clients.get((fqn, srv))
            if client is None:
                client = self._clients[(fqn, srv)] = self.node.create_client(srv, f"{fqn}/{suffix}")
        if not client.wait_for_service(timeout_sec=self.timeout_s):
            return None
        done = threading.Event()
        future = client.call_async(request)
        future.add_done_callback(lambda _: done.set())
        return future.result() if done.wait(self.timeout_s) else None

    def node_names(self) -> list[str]:
        return sorted(f"{ns.rstrip('/')}/{name}" for name, ns in self.node.get_node_names_and_namespaces())

    def get(self, wanted: Iterable[str] = ()) -> list[foxglove.Parameter]:
        """The parameters named in ``wanted`` (none: every one of every node)."""
        wanted = set(wanted)
        found = []
        for fqn in self.node_names():
            if wanted and not any(w.startswith(fqn + ".") for w in wanted):
                continue
            listed = self._call(fqn, ListParameters, "list_parameters", ListParameters.Request())
            names = [] if listed is None else list(listed.result.names)
            request = GetParameters.Request(names=names)
            got = self._call(fqn, GetParameters, "get_parameters", request) if names else None
            for name, value in zip(names, [] if got is None else got.values, strict=False):
                full = f"{fqn}.{name}"
                if wanted and full not in wanted:
                    continue
                self._types[full] = value.type
                native = parameter_value_to_python(value)
                if value.type == RosType.PARAMETER_BYTE_ARRAY:
                    native = bytes(b[0] if isinstance(b, bytes) else b for b in native)
                found.append(foxglove.Parameter(full, value=native, type=FLOAT_HINTS.get(value.type)))
        return found

    def set(self, parameters: Iterable[foxglove.Parameter]) -> list[foxglove.Parameter]:
        """Ask each node to set its parameters; what they hold afterwards."""
        by_node: dict[str, list[Any]] = {}
        names = []
        for p in parameters:
            try:
                fqn, name = _split(p.name)
            except ValueError as err:
                self.node.get_logger().warning(f"parameter not set: {err}")
                continue
            value = p.get_value()
            if self._types.get(p.name) == RosType.PARAMETER_DOUBLE and isinstance(value, int) and \
                    not isinstance(value, bool):
                value = float(value)
            elif self._types.get(p.name) == RosType.PARAMETER_DOUBLE_ARRAY and isinstance(value, list):
                value = [float(v) for v in value]
            by_node.setdefault(fqn, []).append(RosParameter(name, value=value).to_parameter_msg())
            names.append(p.name)
        for fqn, msgs in by_node.items():
            answer = self._call(fqn, SetParameters, "set_parameters", SetParameters.Request(parameters=msgs))
            for msg, result in zip(msgs, [] if answer is None else answer.results, strict=False):
                if not result.successful:
                    self.node.get_logger().warning(f"{fqn}.{msg.name} not set: {result.reason}")
        return self.get(names)
