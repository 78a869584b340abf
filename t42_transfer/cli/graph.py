"""``t42 lifecycle``, ``t42 call``, ``t42 param``: the ``ros2 lifecycle``, ``ros2 service call`` and ``ros2 param``
a pip-installed ROS lacks (no ros2cli wheel), for the suite's lifecycle nodes, services and parameters; and the graph
node, Ctrl-C and name handling ``t42 topic`` and ``t42 reach`` (:mod:`t42_transfer.cli.topic`,
:mod:`t42_transfer.cli.reach`) share."""

from __future__ import annotations

import argparse
import contextlib
import os
import re
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any

import yaml

from t42_transfer.cli.args import float_arg

if TYPE_CHECKING:
    from rclpy.node import Node

OWNER_GRACE_S = 3.0
"""How long a node seen on the graph may take to show a service of its own before it is said to lack it."""
TRANSITIONS = ("configure", "activate", "deactivate", "cleanup", "shutdown")
"""The transitions ``t42 lifecycle set`` takes (``shutdown``: from whichever state the node is in)."""

INTERRUPTED = threading.Event()
"""Set by Ctrl-C while a command is on the graph: its loops stop at their next turn (:func:`stop_if_asked`).  A
KeyboardInterrupt raised wherever the program happens to be, inside rclpy's C++ calls too, came out as another
error there, or left an action client half-way."""


def stop_if_asked() -> None:
    """KeyboardInterrupt, at a point where stopping is safe, once Ctrl-C was pressed."""
    if INTERRUPTED.is_set():
        raise KeyboardInterrupt


@contextlib.contextmanager
def graph_node() -> Iterator[Node]:
    """A node of its own on the graph (local discovery unless chosen otherwise, as ``t42 up`` starts the suite);
    Ctrl-C sets :data:`INTERRUPTED` meanwhile."""
    from t42_transfer.ros.runner import keep_discovery_local

    keep_discovery_local()
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    context = rclpy.Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(f"t42_cli_{os.getpid()}", context=context)
    INTERRUPTED.clear()
    before = signal.signal(signal.SIGINT, lambda *_: INTERRUPTED.set())
    try:
        yield node
    except KeyboardInterrupt:  # Ctrl-C while waiting: the node goes on with what it was asked (a transfer, say)
        print("t42: interrupted: stopped waiting for the answer (the node still carries the request out)",
              file=sys.stderr)
        raise SystemExit(130) from None
    finally:
        signal.signal(signal.SIGINT, before)
        if node.executor is not None:
            node.executor.shutdown(timeout_sec=1.0)
        node.destroy_node()
        rclpy.shutdown(context=context)


ASK_AGAIN_S = 2.0
"""How long a read (a state, a parameter) waits for its answer before the same request goes out again: a server
drops its reply to a client whose reply subscription it has not yet matched (rmw_fastrtps waits 100 ms for it),
which a busy machine makes likely for a command's fresh client."""


def _call(node: Node, srv_type: Any, name: str, request: Any, wait_s: float, again: bool = False) -> Any:
    """``request`` to the service ``name``, once it is on the graph (ValueError after ``wait_s``); its answer.

    ``again``: the request only reads (a state, parameters), so it may be carried out twice: it is sent again each
    :data:`ASK_AGAIN_S` without an answer, and the first answer to any of them is taken."""
    from rclpy.executors import SingleThreadedExecutor

    client = node.create_client(srv_type, name)
    still_waiting = _waiting_for(node, name, wait_s, f"a {srv_type.__name__} service; ")
    while not client.wait_for_service(timeout_sec=0.2):
        shown = _served_types(node, absolute_name(name))
        if shown and _type_name(srv_type) not in shown:  # no client of this type ever matches it
            raise ValueError(f"{name}: a {', '.join(shown)} service, not a {_type_name(srv_type)}")
        still_waiting()
    futures = [client.call_async(request)]
    asked = time.monotonic()
    executor = node.executor
    if executor is None:  # one for the node's calls
        executor = SingleThreadedExecutor(context=node.context)
        executor.add_node(node)
    gone = None
    while not (answered := [f for f in futures if f.done()]):  # a transfer takes minutes: Ctrl-C stops the wait
        stop_if_asked()
        executor.spin_once(timeout_sec=0.2)
        now = time.monotonic()
        gone = None if client.service_is_ready() else (gone or now)
        if gone is not None and now - gone > OWNER_GRACE_S and not any(f.done() for f in futures):
            raise ValueError(f"{name}: the service left the graph before it answered")
        if again and gone is None and now - asked > ASK_AGAIN_S:
            futures.append(client.call_async(request))
            asked = now
    for future in futures:
        if not future.done():  # a request asked again: its answer, should it still come, is not waited for
            client.remove_pending_request(future)
    node.destroy_client(client)
    return answered[0].result()


def _waiting_for(node: Node, name: str, wait_s: float, kind: str = "") -> Callable[[], None]:
    """A check to call while waiting for the service ``name``: KeyboardInterrupt on Ctrl-C; ValueError when its
    node runs without it for :data:`OWNER_GRACE_S`, or after ``wait_s``.  ``kind`` goes into the message."""
    owner = absolute_name(name).rsplit("/", 1)[0]  # the node a node's own service (``/driver/get_state``) belongs to
    start, seen = time.monotonic(), None

    def check() -> None:
        nonlocal seen
        stop_if_asked()
        now = time.monotonic()
        running = owner in {f"{ns.rstrip('/')}/{n}" for n, ns in node.get_node_names_and_namespaces()}
        seen = (seen or now) if running else None  # (a node restarted by t42 up is looked for anew)
        if seen is not None and now - seen > OWNER_GRACE_S:  # the node is there, the service is not
            raise ValueError(f"{name}: {owner} runs but has no such service" + (f" ({kind[:-2]})" if kind else ""))
        if now - start > wait_s:
            raise ValueError(f"{name}: no such service on the graph after {wait_s:g} s ({kind}ROS_DOMAIN_ID "
                             f"{os.environ.get('ROS_DOMAIN_ID', '0')}; is the node running?)")

    return check


def _type_name(cls: Any) -> str:
    """``pkg/srv/Name`` of an rclpy service class, as the graph names it."""
    return f"{cls.__module__.split('.')[0]}/srv/{cls.__name__}"


def absolute_name(name: str, node: bool = False) -> str:
    """A node (``node``), service or topic name from the root namespace, where the command's own node is;
    ValueError for a name ROS refuses, which rclpy would raise as its own exception (a traceback) at the first
    client or publisher."""
    from rclpy.exceptions import NameValidationException
    from rclpy.validate_full_topic_name import validate_full_topic_name
    from rclpy.validate_namespace import validate_namespace
    from rclpy.validate_node_name import validate_node_name

    full = name if name.startswith("/") else "/" + name
    try:
        if node:
            namespace, _, base = full.rpartition("/")
            validate_namespace(namespace or "/")
            validate_node_name(base)
        else:
            validate_full_topic_name(full)
    except NameValidationException as err:  # "Invalid topic name: <why>:", the name, a caret under the fault
        why = str(err).splitlines()[0].split(": ", 1)[-1].removesuffix(":")
        raise ValueError(f"{name!r}: not a valid ROS name ({why})") from None
    return full


def _cmd_lifecycle(args: argparse.Namespace) -> int:
    from lifecycle_msgs.srv import ChangeState, GetAvailableTransitions, GetState

    target = absolute_name(args.node, node=True)
    with graph_node() as node:
        state = _call(node, GetState, f"{target}/get_state", GetState.Request(), args.wait, again=True)
        if args.transition is None:
            print(f"{target}: {state.current_state.label}")
            return 0
        available = _call(node, GetAvailableTransitions, f"{target}/get_available_transitions",
                          GetAvailableTransitions.Request(), args.wait, again=True).available_transitions
        labels = {t.transition.label: t.transition.id for t in available}
        wanted = [label for label in labels if label == args.transition
                  or (args.transition == "shutdown" and label.endswith("shutdown"))]
        if not wanted:
            raise ValueError(f"{target}: cannot {args.transition} from its state now; it can: "
                             f"{', '.join(sorted(labels)) or 'nothing'}")
        request = ChangeState.Request()
        request.transition.id = labels[wanted[0]]
        done = _call(node, ChangeState, f"{target}/change_state", request, args.wait).success
        state = _call(node, GetState, f"{target}/get_state", GetState.Request(), args.wait,
                      again=True).current_state.label
    print(f"{target}: {args.transition} {'done' if done else 'failed (the node logs why)'}; now {state}")
    return 0 if done else 1


def _cmd_call(args: argparse.Namespace) -> int:
    from msg_adapters import message_fields, message_from_fields

    service = absolute_name(args.service)
    typename, values = args.type, args.values
    if typename is not None and values is None and not _SERVICE_TYPE.fullmatch(typename):
        typename, values = None, typename  # ``t42 call /srv '{data: true}'``: the type is the graph's
    fields = yaml_value(values or "{}")
    srv = None if typename is None else _service_class(typename)  # a bad field is said before the graph
    request = None if srv is None else message_from_fields(srv.Request, fields, "request")
    with graph_node() as node:
        if srv is None:
            srv = _service_class(_graph_service_type(node, service, args.wait))
            request = message_from_fields(srv.Request, fields, "request")
        answer = message_fields(_call(node, srv, service, request, args.wait))
    if set(answer) == {"success", "message"}:  # std_srvs' Trigger and SetBool: one line
        print(f"{args.service}: {'success' if answer['success'] else 'failure'}: {answer['message']}")
    else:
        print(yaml.safe_dump(answer, sort_keys=False, width=120), end="")
    return 1 if answer.get("success") is False else 0


_SERVICE_TYPE = re.compile(r"[^\s{}\[\]:,]+/[^\s{}\[\]:,]+")
"""A TYPE as the user may have meant it (``pkg/srv/Name``, ``pkg/Name``, misspelt too), not YAML values."""


def _service_class(typename: str) -> Any:
    """rclpy's class of a service type, ``pkg/srv/Name`` or ``pkg/Name``."""
    from msg_adapters import rclpy_class

    if "/action/" in typename:
        raise ValueError(f"{typename}: an action's own service; t42 call takes services (the planner's action: "
                         "t42 reach)")
    package, _, name = typename.partition("/")
    full = typename if "/srv/" in typename else f"{package}/srv/{name}"
    try:
        srv = rclpy_class(full)
    except (ImportError, AttributeError, ValueError):
        srv = None
    if not hasattr(srv, "Request"):
        raise ValueError(f"{typename}: no such service type (pkg/srv/Name, e.g. std_srvs/srv/SetBool)")
    return srv


def _graph_service_type(node: Node, service: str, wait_s: float) -> str:
    """The type ``service`` shows on the graph, once it does (ValueError after ``wait_s``)."""
    still_waiting = _waiting_for(node, service, wait_s)
    while not (types := _served_types(node, service)):
        still_waiting()
        time.sleep(0.1)
    return types[0]


def _served_types(node: Node, service: str) -> list[str]:
    """The types some node serves ``service`` as (the graph-wide list holds its clients' types too)."""
    types: set[str] = set()
    for name, namespace in node.get_node_names_and_namespaces():
        with contextlib.suppress(Exception):  # a node that left meanwhile
            types.update(t for s, ts in node.get_service_names_and_types_by_node(name, namespace) if s == service
                         for t in ts)
    return sorted(types)


def yaml_value(values: str) -> Any:
    try:
        return yaml.safe_load(values)
    except yaml.YAMLError as err:
        raise ValueError(f"{values!r}: not YAML ({err})") from None


def _cmd_param(args: argparse.Namespace) -> int:
    from rcl_interfaces.msg import ParameterType
    from rcl_interfaces.srv import DescribeParameters, GetParameters, ListParameters, SetParameters
    from rclpy.parameter import Parameter, parameter_value_to_python

    target = absolute_name(args.node, node=True)
    with graph_node() as node:
        if args.name is None:  # as ros2 param dump: every parameter with its value
            listed = sorted(_call(node, ListParameters, f"{target}/list_parameters", ListParameters.Request(),
                                  args.wait, again=True).result.names)
            values = _call(node, GetParameters, f"{target}/get_parameters", GetParameters.Request(names=listed),
                           args.wait, again=True).values
            for name, value in zip(listed, values, strict=True):
                print(f"{name}: {parameter_value_to_python(value)}")
            return 0
        if args.value is None:
            values = _call(node, GetParameters, f"{target}/get_parameters", GetParameters.Request(names=[args.name]),
                           args.wait, again=True).values
            if not values or values[0].type == ParameterType.PARAMETER_NOT_SET:
                raise ValueError(f"{target}: has no parameter {args.name!r} (or it is not set)")
            print(f"{target} {args.name}: {parameter_value_to_python(values[0])}")
            return 0
        try:
            value = yaml.safe_load(args.value)  # as ros2 param set reads it: 2.5, true, [2.5, 2.5], text
            declared = _call(node, DescribeParameters, f"{target}/describe_parameters",
                             DescribeParameters.Request(names=[args.name]), args.wait, again=True).descriptors
            kind = declared[0].type if declared else ParameterType.PARAMETER_NOT_SET
            value = _as_declared(value, kind)
            arrays = (ParameterType.PARAMETER_BOOL_ARRAY, ParameterType.PARAMETER_INTEGER_ARRAY,
                      ParameterType.PARAMETER_DOUBLE_ARRAY, ParameterType.PARAMETER_STRING_ARRAY)
            if value == [] and kind in arrays:  # rclpy would type [] a byte array, which the node refuses
                message = Parameter(args.name, Parameter.Type(kind), []).to_parameter_msg()
            else:
                message = Parameter(args.name, value=value).to_parameter_msg()
        except (yaml.YAMLError, TypeError) as err:
            raise ValueError(f"{args.value!r}: not a parameter value ({err})") from None
        result = _call(node, SetParameters, f"{target}/set_parameters",
                       SetParameters.Request(parameters=[message]), args.wait).results[0]
    print(f"{target} {args.name}: " + ("set" if result.successful else f"refused: {result.reason}"))
    return 0 if result.successful else 1


def _as_declared(value: Any, declared: int) -> Any:
    """A whole number given for a double parameter (``1`` for ``1.0``, in a list too) as a double: what the user
    meant, which rclpy would refuse as an integer."""
    from rcl_interfaces.msg import ParameterType

    def whole(v: Any) -> bool:
        return isinstance(v, int) and not isinstance(v, bool)

    if declared == ParameterType.PARAMETER_DOUBLE and whole(value):
        return float(value)
    if declared == ParameterType.PARAMETER_DOUBLE_ARRAY and isinstance(value, list) and value and all(
            whole(v) or isinstance(v, float) for v in value):
        return [float(v) for v in value]
    return value


def _wait_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--wait", type=float_arg(0, 3600), default=10.0, metavar="S",
                        help="how long to wait for the service to appear on the graph (default 10 s)")


def add_commands(commands: argparse._SubParsersAction) -> None:
    lifecycle = commands.add_parser("lifecycle", help="a lifecycle node's state, or a transition (as ros2 lifecycle)")
    lifecycle.add_argument("node", metavar="NODE", help="e.g. /dynamixel_driver")
    lifecycle.add_argument("transition", nargs="?", choices=TRANSITIONS, metavar="TRANSITION",
                           help=f"one of {', '.join(TRANSITIONS)}; none: print the state")
    _wait_argument(lifecycle)
    lifecycle.set_defaults(func=_cmd_lifecycle)
    call = commands.add_parser("call", help="call a service, e.g. /hand/reset, /t42/transfer_now (as ros2 "
                                            "service call)")
    call.add_argument("service", metavar="SERVICE")
    call.add_argument("type", nargs="?", metavar="TYPE",
                      help="e.g. std_srvs/srv/SetBool; left out: the type the service shows on the graph")
    call.add_argument("values", nargs="?", metavar="VALUES",
                      help="the request's fields as YAML, e.g. '{data: true}' (default: all defaults)")
    _wait_argument(call)
    call.set_defaults(func=_cmd_call)
    param = commands.add_parser("param", help="get or set a node's parameter, or list them all (as ros2 param "
                                              "get / set / dump)")
    param.add_argument("node", metavar="NODE", help="e.g. /dynamixel_driver")
    param.add_argument("name", nargs="?", metavar="NAME", help="none: every parameter with its value")
    param.add_argument("value", nargs="?", metavar="VALUE",
                       help="a YAML value (2.5, true, '[2.5, 2.5]', text); none: print the parameter")
    _wait_argument(param)
    param.set_defaults(func=_cmd_param)
