"""A node's frozen params dataclass as declared ROS 2 parameters: one configuration mechanism.

Each node keeps its settings in a frozen dataclass whose ``__post_init__`` checks
them (usable without ROS, in tests and the CLI).  :func:`declare_params` declares
one ROS parameter per field, with a descriptor built from the field's
:func:`param` metadata (description, range, read-only), reads the values rclpy
resolved from params files and ``-p`` overrides, and returns the dataclass.

Parameters that are not read-only may change at run time (``ros2 param set``); those a lifecycle node reads
at configure (``configure=True``) only while it is unconfigured, so that a wrong port is fixed by cleanup, a set
and configure, without a restart.
:class:`LiveParams` validates a change by building the would-be dataclass, so a bad
value is refused with the reason ``__post_init__`` gives and the node keeps its old
value; an accepted change reaches the node through a callback.

Types: ``bool``, ``int``, ``float``, ``str``, ``Path`` (a string), tuples of
``float``/``int``/``str`` (arrays); ``X | None`` fields are declared with dynamic
typing so that "unset" is a value.
"""

from __future__ import annotations

import array
import copy
import dataclasses
import math
import types
import typing
from collections.abc import Callable
from pathlib import Path
from typing import Any, Generic, TypeVar

from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    ParameterType,
    SetParametersResult,
)
from rclpy.exceptions import ParameterException, ParameterUninitializedException
from rclpy.lifecycle import LifecycleNode
from rclpy.node import Node
from rclpy.parameter import Parameter

from t42_transfer.ros.node_lifetime import lifecycle_state

P = TypeVar("P")

_META = "t42_param"
UNCONFIGURED_ONLY = "set while unconfigured"


@dataclasses.dataclass(frozen=True)
class ParamInfo:
    description: str
    read_only: bool = False
    """True where a change at run time makes no sense (the node built its hand, bag or model from it)."""
    min: float | None = None
    max: float | None = None
    constraints: str = ""
    """Free text shown by ``ros2 param describe`` for checks a range cannot express."""
    renamed_from: str = ""
    """The parameter's former name: a node given it refuses to start (rclpy would drop it unread)."""
    configure: bool = False
    """Read at a lifecycle node's configure: set only while the node is unconfigured."""


def param(default: Any = dataclasses.MISSING, description: str = "", *, read_only: bool = False,
          min: float | None = None, max: float | None = None, constraints: str = "",
          default_factory: Any = dataclasses.MISSING, renamed_from: str = "", configure: bool = False) -> Any:
    """A dataclass field that is also a documented ROS parameter."""
    if read_only and configure:
        raise TypeError("a parameter is read-only or set while unconfigured, not both")
    info = ParamInfo(description, read_only, min, max, constraints, renamed_from, configure)
    if default_factory is not dataclasses.MISSING:
        return dataclasses.field(default_factory=default_factory, metadata={_META: info})
    return dataclasses.field(default=default, metadata={_META: info})


def torch_threads_param() -> Any:
    """``torch_threads``, the same parameter on every node that runs torch (the transfer server, the planner)."""
    return param(1, "torch's intra-op threads in this process (set at start): the suite's models are small, and a "
                    "second thread waiting for a busy core slows them (measured on 2 cores with both busy: training "
                    "2x, planning 2.3x slower; quiet: training alike, planning 13 % faster)",
                 min=1, max=1024, read_only=True)


_SCALARS = {
    bool: ParameterType.PARAMETER_BOOL,
    int: ParameterType.PARAMETER_INTEGER,
    float: ParameterType.PARAMETER_DOUBLE,
    str: ParameterType.PARAMETER_STRING,
    Path: ParameterType.PARAMETER_STRING,
}
_ARRAYS = {
    bool: ParameterType.PARAMETER_BOOL_ARRAY,
    int: ParameterType.PARAMETER_INTEGER_ARRAY,
    float: ParameterType.PARAMETER_DOUBLE_ARRAY,
    str: ParameterType.PARAMETER_STRING_ARRAY,
}


@dataclasses.dataclass(frozen=True)
class _Field:
    name: str
    hint: Any
    """The hint without ``| None``."""
    optional: bool
    ros_type: int
    info: ParamInfo
    default: Any


def _fields(params_cls: type) -> list[_Field]:
    if not dataclasses.is_dataclass(params_cls):
        raise TypeError(f"{params_cls!r} is not a dataclass")
    hints = typing.get_type_hints(params_cls)
    out = []
    for f in dataclasses.fields(params_cls):
        if not f.init:
            continue
        hint, optional = hints[f.name], False
        if typing.get_origin(hint) in (typing.Union, types.UnionType):
            arms = [a for a in typing.get_args(hint) if a is not type(None)]
            optional = len(arms) < len(typing.get_args(hint))
            # "str | Path" is a path given as a string
            hint = Path if set(arms) <= {str, Path} and Path in arms else arms[0]
            if len(arms) > 1 and hint is not Path:
                raise TypeError(f"{params_cls.__name__}.{f.name}: a parameter has one type, got {hints[f.name]}")
        if typing.get_origin(hint) is tuple:
            elem = typing.get_args(hint)[0]
            ros_type = _ARRAYS[elem]
        elif hint in _SCALARS:
            ros_type = _SCALARS[hint]
        else:
            raise TypeError(f"{params_cls.__name__}.{f.name}: {hint} cannot be a ROS parameter")
        if f.default is not dataclasses.MISSING:
            default = f.default
        elif f.default_factory is not dataclasses.MISSING:
            default = f.default_factory()
        else:
            default = dataclasses.MISSING
        info = f.metadata.get(_META, ParamInfo(""))
        out.append(_Field(f.name, hint, optional, ros_type, info, default))
    return out


def _descriptor(field: _Field) -> ParameterDescriptor:
    info = field.info
    desc = ParameterDescriptor(
        name=field.name,
        type=ParameterType.PARAMETER_NOT_SET if field.optional else field.ros_type,
        description=info.description,
        read_only=info.read_only,
        dynamic_typing=field.optional,
        additional_constraints=info.constraints + (" (unset: none)" if field.optional else "")
        + (f" ({UNCONFIGURED_ONLY})" if info.configure else ""),
    )
    if info.min is not None or info.max is not None:
        lo = -math.inf if info.min is None else info.min
        hi = math.inf if info.max is None else info.max
        if field.ros_type == ParameterType.PARAMETER_INTEGER:
            big = 2**63 - 1
            desc.integer_range = [IntegerRange(from_value=int(max(lo, -big)), to_value=int(min(hi, big)), step=0)]
        elif field.ros_type == ParameterType.PARAMETER_DOUBLE:
            desc.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi), step=0.0)]
    return desc


def _to_ros(value: Any) -> Any:
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, tuple):
        return list(value)
    return value


def _from_ros(field: _Field, value: Any) -> Any:
    """The dataclass value of a parameter value; ValueError when its type is not the field's."""
    if value is None:
        if field.optional:
            return None
        raise ValueError(f"parameter {field.name!r} must be set")
    hint = field.hint
    if typing.get_origin(hint) is tuple:
        elem = typing.get_args(hint)[0]
        if isinstance(value, array.array):  # how rclpy hands over a set numeric array (ros2 param set)
            value = value.tolist()
        if not isinstance(value, (list, tuple)):
            raise ValueError(f"parameter {field.name!r} expects a list, got {value!r}")
        return tuple(float(v) if elem is float else v for v in value)
    if hint is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if hint is Path:
        return Path(value) if isinstance(value, str) else value
    if not isinstance(value, hint) or (hint is int and isinstance(value, bool)):
        raise ValueError(f"parameter {field.name!r} expects {hint.__name__}, got {value!r}")
    return value


def describe_params(params_cls: type) -> str:
    """One line per parameter, what ``ros2 param describe`` says of the running node (name, type, default, range,
    read-only, description; an optional one, dynamically typed there, with the type of its set values): offline,
    so a user reads them before starting a node."""
    lines = []
    for field in _fields(params_cls):
        kind = Parameter.Type(field.ros_type).name.lower()
        default = ("required" if field.default is dataclasses.MISSING
                   else f"default {'unset' if field.default is None else _shown(field.default)}")
        info = field.info
        bounds = ((">=", info.min), ("<=", info.max))
        limits = [f"{sign} {_shown(bound)}" for sign, bound in bounds if bound is not None]
        notes = [default, *limits, *(["read-only"] if info.read_only else []),
                 *([UNCONFIGURED_ONLY] if info.configure else [])]
        more = f" ({info.constraints})" if info.constraints else ""
        lines.append(f"  {field.name} ({kind}{', optional' if field.optional else ''}; {', '.join(notes)}): "
                     f"{info.description}{more}")
    return "\n".join(lines)


def _shown(value: Any) -> str:
    """A value for the description: a list in brackets, a large whole bound without an exponent."""
    if isinstance(value, tuple):
        return "[" + ", ".join(_shown(v) for v in value) + "]"
    if isinstance(value, float) and value.is_integer() and 1e5 <= abs(value) < 1e15:
        return str(int(value))
    return repr(value) if isinstance(value, str) else str(value)


def declare_params(node: Node, params_cls: type[P]) -> P:
    """Declare ``params_cls``'s fields as ``node``'s parameters; the dataclass of their values.

    ValueError (one line naming the node and the parameter) for a missing required
    parameter, a value of the wrong type, one ``__post_init__`` refuses, or a parameter's former name.
    """
    where = node.get_fully_qualified_name()
    values: dict[str, Any] = {}
    for field in _fields(params_cls):
        if field.info.renamed_from and field.info.renamed_from in parameter_overrides(node):
            raise ValueError(f"{where}: parameter {field.info.renamed_from!r} is now {field.name!r}: "
                             f"{field.info.description}")
        try:
            if field.default is dataclasses.MISSING or field.default == ():
                # No default, or an empty one whose type rclpy cannot infer from [] (it would say BYTE_ARRAY):
                # declare by type; an empty default is then set with its type spelled out.
                # A read-only one is declared writable until it holds its value (set_parameters refuses a
                # read-only parameter, and one left unset empties every get_parameters answer that names it).
                ros_type, descriptor = Parameter.Type(field.ros_type), _descriptor(field)
                writable = copy.copy(descriptor)
                writable.read_only = False
                value = node.declare_parameter(field.name, ros_type, writable).value
                if value is None and field.default == ():
                    (result,) = node.set_parameters([Parameter(field.name, ros_type, [])])
                    if not result.successful:
                        raise ValueError(result.reason)
                    value = []
                if value is not None and descriptor.read_only:
                    node.set_descriptor(field.name, descriptor)
            else:
                value = node.declare_parameter(field.name, _to_ros(field.default), _descriptor(field)).value
        except ParameterUninitializedException:
            raise ValueError(f"{where}: missing required parameter {field.name!r} "
                             f"(set it in a params file or with -p {field.name}:=...)") from None
        except ParameterException as err:  # wrong type or out of range
            raise ValueError(f"{where}: parameter {field.name!r}: {err}") from None
        except (TypeError, ValueError) as err:
            raise ValueError(f"{where}: parameter {field.name!r}: {err}") from None
        if value is None and field.default is dataclasses.MISSING:
            raise ValueError(f"{where}: missing required parameter {field.name!r} "
                             f"(set it in a params file or with -p {field.name}:=...)")
        try:
            values[field.name] = _from_ros(field, value)
        except ValueError as err:
            raise ValueError(f"{where}: {err}") from None
    try:
        return params_cls(**values)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{where}: {err}") from None


def undeclared_overrides(node: Node) -> list[str]:
    """Parameters the command line or a params file gave ``node`` that it has not declared, sorted.

    rclpy drops them without a word, so ``-p rate_factr:=2.0`` (a typo) runs on the default: the runner warns.
    rclpy keeps the overrides in a private attribute only; without it the list is empty."""
    return sorted(name for name in parameter_overrides(node) if not node.has_parameter(name))


def parameter_overrides(node: Node) -> dict[str, Any]:
    """The parameter values the command line and params files gave ``node`` (rclpy keeps them private)."""
    return getattr(node, "_parameter_overrides", None) or {}


class LiveParams(Generic[P]):
    """A node's params dataclass kept in step with ``ros2 param set``: bad values refused with the reason.

    ``on_change(old, new)`` runs after a change was accepted (in the executor's thread).  ``veto(old, new)``
    refuses a change that is fine as settings but not as a change at run time (the reason, or None).  A
    ``configure`` parameter changes only while the (lifecycle) node is unconfigured.
    """

    def __init__(self, node: Node, params_cls: type[P], on_change: Callable[[P, P], None] | None = None,
                 veto: Callable[[P, P], str | None] | None = None) -> None:
        self._fields = {f.name: f for f in _fields(params_cls)}
        if not isinstance(node, LifecycleNode) and any(f.info.configure for f in self._fields.values()):
            raise TypeError(f"{params_cls.__name__}: parameters set while unconfigured need a lifecycle node")
        self._node = node
        self.value: P = declare_params(node, params_cls)
        self._pending: P | None = None
        self._on_change, self._veto = on_change, veto
        node.add_on_set_parameters_callback(self._validate)
        node.add_post_set_parameters_callback(self._apply)

    def _validate(self, parameters: list[Parameter]) -> SetParametersResult:
        changes = {}
        for p in parameters:
            field = self._fields.get(p.name)
            if field is None:  # rclpy's own (use_sim_time, ...)
                continue
            if p.type_ == Parameter.Type.NOT_SET:  # rclpy would undeclare it: gone until the node restarts
                return SetParametersResult(successful=False, reason=f"{p.name} cannot be unset at run time (it "
                                           "would be undeclared); set a value, or restart the node without one")
            try:
                changes[p.name] = _from_ros(field, p.value)
            except ValueError as err:
                return SetParametersResult(successful=False, reason=str(err))
            state = lifecycle_state(self._node) if field.info.configure else "unconfigured"
            if state != "unconfigured" and changes[p.name] != getattr(self.value, p.name):
                return SetParametersResult(successful=False, reason=f"{p.name} is read at configure: set it while "
                                           f"the node is unconfigured (it is {state}: cleanup first)")
        if not changes:
            return SetParametersResult(successful=True)
        try:
            pending = dataclasses.replace(self.value, **changes)
        except (TypeError, ValueError) as err:
            return SetParametersResult(successful=False, reason=str(err))
        refused = self._veto(self.value, pending) if self._veto is not None else None
        if refused:
            return SetParametersResult(successful=False, reason=refused)
        self._pending = pending
        return SetParametersResult(successful=True)

    def _apply(self, parameters: list[Parameter]) -> None:
        if self._pending is None:
            return
        old, self.value, self._pending = self.value, self._pending, None
        if self._on_change is not None and self.value != old:  # a value set again changes nothing
            self._on_change(old, self.value)
