"""Nodes that leave the graph when they are done with, not when the garbage collector finds them.

rcl keeps one /rosout publisher per logger name, and finalizing any node of a name unregisters it.  A node
of the suite's that outlived its use (a refused one, a destroyed lifecycle node) was finalized by the garbage
collector at a moment of its own: until then it stayed on the graph as a second node of its name, and then it
took the /rosout publisher of a later node of that name, whose log lines silently stopped reaching /rosout.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable
from typing import Any, TypeVar

from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.lifecycle import LifecycleNode
from rclpy.node import Node

F = TypeVar("F", bound=Callable[..., None])
RCLError = _rclpy.RCLError


def _finalize(node: Any) -> None:
    """rclpy's own ``destroy_node``, then the lifecycle state machine, which holds the rcl node until it goes."""
    Node.destroy_node(node)
    state_machine = getattr(node, "_state_machine", None)
    if state_machine is not None:
        state_machine.destroy_when_not_in_use()


def destroyed_if_init_fails(init: F) -> F:
    """Decorate a node class's ``__init__``: if it raises once rclpy made the node (a bad parameter, a missing
    bag), the node is destroyed before the error goes on (with rclpy's own ``destroy_node``: a subclass's may
    need what was never built)."""

    @functools.wraps(init)
    def wrapper(self: Any, *args: Any, **kwargs: Any) -> None:
        try:
            init(self, *args, **kwargs)
        except BaseException:
            if getattr(self, "handle", None) is not None:  # the rcl node exists
                with contextlib.suppress(Exception):
                    _finalize(self)
            raise

    return wrapper  # type: ignore[return-value]


def lifecycle_state(node: LifecycleNode) -> str:
    """The lifecycle state's label (``unconfigured``, ``inactive``, ``active``, ``finalized``, a transition's):
    rclpy 7.1 keeps it in its state machine only."""
    return node._state_machine.current_state[1]


def _change_state_checked(node: LifecycleNode, answer: Callable[[Any, Any], Any], request: Any, response: Any) -> Any:
    """rclpy's ``change_state`` callback ``answer``, for a transition valid in the node's state only (by id; a
    label rclpy resolves in the current state itself); any other is answered ``success: false``."""
    transition = request.transition
    valid = {t[0]: t[1] for t in node._state_machine.available_transitions}
    if not transition.label and transition.id not in valid:
        return _refuse(node, response, f"transition id {transition.id}", valid)
    try:
        return answer(request, response)
    except RCLError as err:  # rcl refused it after all: the state is as it was
        return _refuse(node, response, f"transition {transition.label or transition.id} ({err})", valid)


def _refuse(node: LifecycleNode, response: Any, what: str, valid: dict[int, str]) -> Any:
    choices = ", ".join(f"{label} (id {i})" for i, label in valid.items()) or "none"
    node.get_logger().warning(f"change_state refused: {what} is not valid in state "
                              f"'{lifecycle_state(node)}'; valid now: {choices}")
    response.success = False
    return response


class DestroyableLifecycleNode(LifecycleNode):
    """rclpy's LifecycleNode, whose ``destroy_node`` leaves the graph at once: rclpy 7.1's leaves the rcl node
    to its state machine, which refers back to the node and so lives until the garbage collector runs.

    Its ``change_state`` service answers a transition not valid in the current state (configure while active, a
    lifecycle manager that lost a race with ``autostart``) ``success: false`` with a warning naming the valid
    ones: rclpy 7.1 raises rcl's "Transition is not registered" out of the service callback instead, and the
    runner takes an exception out of a callback for a bug and ends the process (a driver then lets the object
    go)."""

    def __init__(self, node_name: str, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        service = getattr(self, "_service_change_state", None)  # None: no communication interface
        if service is not None:
            service.callback = functools.partial(_change_state_checked, self, service.callback)

    @property
    def state(self) -> str:
        """The lifecycle state's label (:func:`lifecycle_state`)."""
        return lifecycle_state(self)

    def destroy_node(self) -> None:
        super().destroy_node()
        self._state_machine.destroy_when_not_in_use()
