"""ROS 2 parameters for a node's frozen params dataclass, without a ROS install.

One configuration mechanism, the one ROS uses: params-file YAML
(``<node_name>: {ros__parameters: {...}}``, with ``/**`` as the every-node
wildcard) plus command-line overrides in ROS syntax::

    --ros-args --params-file F.yaml -p name:=value -r __node:=new_name

so the same files and arguments work under ``ros2 run``/``ros2 launch`` (rclpy)
and ``t42 node``/``t42 up`` (Cyclone DDS).  Values are YAML (``-p`` values are
parsed as YAML scalars or lists, as rcl does).  Precedence, lowest first: the
dataclass defaults, each params file in order (within a file ``/**`` before the
node's own section), then ``-p`` overrides in order.

Values are checked against the dataclass's type hints: an unknown name, a missing
required parameter or a value of the wrong type is a :class:`ValueError` that names
the node and the parameter.  Coercions are the lossless ones a YAML file needs:
list -> tuple, str -> Path, int -> float.  A mapping-typed field takes a YAML
mapping (ROS itself would flatten it into dotted names; only this loader reads it).
"""

from __future__ import annotations

import dataclasses
import types
import typing
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from t42_transfer.ros.naming import validate_node_name

WILDCARDS = ("/**", "**")
"""Params-file keys that apply to every node."""


@dataclass(frozen=True)
class RosArgs:
    """What ``--ros-args`` blocks of a command line ask for."""

    params_files: tuple[Path, ...] = ()
    overrides: tuple[tuple[str, Any], ...] = ()
    """``-p name:=value`` pairs, values parsed as YAML, in command-line order."""
    node_name: str | None = None
    """``-r __node:=name``."""


def _split_assignment(text: str, option: str) -> tuple[str, str]:
    name, sep, value = text.partition(":=")
    if not sep or not name:
        raise ValueError(f"--ros-args {option} expects name:=value, got {text!r}")
    return name, value


def parse_ros_args(argv: Sequence[str]) -> tuple[list[str], RosArgs]:
    """Split ``argv`` into the arguments outside ``--ros-args ... [--]`` blocks and the parsed ROS arguments.

    Understood: ``--params-file F``, ``-p/--param name:=value``, ``-r/--remap __node:=name``
    (also ``__name:=``).  Anything else inside a block is a ValueError (this is not rcl:
    topic remapping, namespaces and log options are not supported).
    """
    rest: list[str] = []
    files: list[Path] = []
    overrides: list[tuple[str, Any]] = []
    node_name: str | None = None
    args = list(argv)
    i, in_block = 0, False
    while i < len(args):
        arg = args[i]
        i += 1
        if arg == "--ros-args":
            in_block = True
            continue
        if not in_block:
            rest.append(arg)
            continue
        if arg == "--":
            in_block = False
            continue
        if arg in ("--params-file", "-p", "--param", "-r", "--remap"):
            if i >= len(args):
                raise ValueError(f"--ros-args {arg} expects a value")
            value = args[i]
            i += 1
            if arg == "--params-file":
                files.append(Path(value))
            elif arg in ("-p", "--param"):
                name, text = _split_assignment(value, arg)
                overrides.append((name, yaml.safe_load(text) if text else None))
            else:
                name, text = _split_assignment(value, arg)
                if name not in ("__node", "__name"):
                    raise ValueError(f"--ros-args {arg} {value}: only __node:=<name> remapping is supported")
                node_name = validate_node_name(text)
            continue
        raise ValueError(f"unsupported ROS argument {arg!r} (supported: --params-file, -p, -r __node:=)")
    return rest, RosArgs(tuple(files), tuple(overrides), node_name)


def read_params_file(path: str | Path, node_name: str) -> dict[str, Any]:
    """The parameters a params file gives ``node_name``: its ``/**`` section, then its own (later wins)."""
    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text())
    except OSError as err:
        raise ValueError(f"params file {path}: {err.strerror or err}") from None
    except yaml.YAMLError as err:
        raise ValueError(f"params file {path}: not valid YAML ({err})") from None
    if doc is None:
        return {}
    if not isinstance(doc, dict):
        raise ValueError(f"params file {path}: expected a mapping of node names, got {type(doc).__name__}")
    values: dict[str, Any] = {}
    for key in (*WILDCARDS, node_name, "/" + node_name):
        if key not in doc:
            continue
        section = doc[key]
        params = section.get("ros__parameters") if isinstance(section, dict) else None
        if not isinstance(params, dict):
            raise ValueError(f"params file {path}: section {key!r} must be a mapping with 'ros__parameters'")
        values.update(params)
    return values


def node_sections(path: str | Path) -> list[str]:
    """Names of the nodes a params file has its own section for (wildcards excluded), in file order."""
    doc = yaml.safe_load(Path(path).read_text()) or {}
    if not isinstance(doc, dict):
        raise ValueError(f"params file {path}: expected a mapping of node names")
    return [str(key).lstrip("/") for key in doc if key not in WILDCARDS]


def _type_name(hint: Any) -> str:
    return getattr(hint, "__name__", None) or str(hint).replace("typing.", "")


def _coerce(value: Any, hint: Any, where: str) -> Any:
    """``value`` as ``hint`` (see the module docstring for the coercions); ValueError if it cannot be."""
    origin = typing.get_origin(hint)
    if hint is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        arms = typing.get_args(hint)
        if value is None:
            if type(None) in arms:
                return None
        else:
            for arm in arms:  # an exact match first, so 'str | Path' keeps a str
                if isinstance(arm, type) and arm is not type(None) and isinstance(value, arm) \
                        and not (arm is int and isinstance(value, bool)):
                    return value
            for arm in arms:
                if arm is type(None):
                    continue
                try:
                    return _coerce(value, arm, where)
                except ValueError:
                    pass
        raise ValueError(f"{where} expects {_type_name(hint)}, got {value!r}")
    if origin is tuple:
        args = typing.get_args(hint)
        if not isinstance(value, (list, tuple)):
            raise ValueError(f"{where} expects a list, got {value!r}")
        if not args:
            return tuple(value)
        if len(args) == 2 and args[1] is Ellipsis:
            args = (args[0],) * len(value)
        if len(args) != len(value):
            raise ValueError(f"{where} expects {len(args)} values, got {len(value)}")
        return tuple(_coerce(v, a, f"{where}[{i}]") for i, (v, a) in enumerate(zip(value, args)))
    if origin in (dict, Mapping, typing.Mapping) or hint in (dict, Mapping):
        if not isinstance(value, dict):
            raise ValueError(f"{where} expects a mapping, got {value!r}")
        key_hint, value_hint = typing.get_args(hint) or (Any, Any)
        return {_coerce(k, key_hint, where): _coerce(v, value_hint, f"{where}[{k!r}]") for k, v in value.items()}
    if hint is float and isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if hint is Path and isinstance(value, (str, Path)):
        return Path(value)
    if isinstance(hint, type) and isinstance(value, hint) and not (hint is int and isinstance(value, bool)):
        return value
    raise ValueError(f"{where} expects {_type_name(hint)}, got {value!r} ({type(value).__name__})")


@dataclasses.dataclass(frozen=True)
class NodeOptions:
    """Parameters every ROS node has, whatever its own params class (``-p use_sim_time:=true``)."""

    use_sim_time: bool = False
    """ROS time from ``/clock`` (a simulator's) instead of the system clock."""


COMMON = frozenset(f.name for f in dataclasses.fields(NodeOptions))


def _gather(node_name: str, params_files: Sequence[str | Path],
            overrides: Sequence[tuple[str, Any]] | Mapping[str, Any]) -> tuple[dict[str, Any], dict[str, str]]:
    values: dict[str, Any] = {}
    sources: dict[str, str] = {}
    for path in params_files:
        for name, value in read_params_file(path, node_name).items():
            values[name], sources[name] = value, f"params file {path}"
    items = overrides.items() if isinstance(overrides, Mapping) else overrides
    for name, value in items:
        values[name], sources[name] = value, "-p"
    return values, sources


def _build(params_cls: type, node_name: str, values: dict[str, Any], sources: dict[str, str]) -> Any:
    if not dataclasses.is_dataclass(params_cls):
        raise TypeError(f"{params_cls!r} is not a dataclass")
    fields = {f.name: f for f in dataclasses.fields(params_cls) if f.init}
    hints = typing.get_type_hints(params_cls)
    unknown = sorted(set(values) - set(fields))
    if unknown:
        raise ValueError(
            f"{node_name}: unknown parameter(s) {', '.join(unknown)} "
            f"(from {', '.join(sorted({sources[n] for n in unknown}))}); valid: {', '.join(fields)}"
        )
    missing = [n for n, f in fields.items() if n not in values
               and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING]
    if missing:
        raise ValueError(f"{node_name}: missing required parameter(s) {', '.join(missing)} "
                         f"(set them in a params file or with -p name:=value)")
    kwargs = {n: _coerce(v, hints[n], f"{node_name}: parameter {n!r}") for n, v in values.items()}
    try:
        return params_cls(**kwargs)
    except (TypeError, ValueError, KeyError) as err:
        raise ValueError(f"{node_name}: {err}") from None


def load_params(
    params_cls: type,
    node_name: str,
    params_files: Sequence[str | Path] = (),
    overrides: Sequence[tuple[str, Any]] | Mapping[str, Any] = (),
) -> Any:
    """An instance of the frozen dataclass ``params_cls`` for ``node_name`` from params files and overrides.

    The :class:`NodeOptions` every node has (``use_sim_time``) are left to :func:`node_options`.
    """
    values, sources = _gather(node_name, params_files, overrides)
    own = {n: v for n, v in values.items() if n not in COMMON}
    return _build(params_cls, node_name, own, sources)


def node_options(
    node_name: str,
    params_files: Sequence[str | Path] = (),
    overrides: Sequence[tuple[str, Any]] | Mapping[str, Any] = (),
) -> NodeOptions:
    """The :class:`NodeOptions` of ``node_name`` from the same params files and overrides."""
    values, sources = _gather(node_name, params_files, overrides)
    return _build(NodeOptions, node_name, {n: v for n, v in values.items() if n in COMMON}, sources)

