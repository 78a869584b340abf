"""cyclonedds-python IDL classes for ROS 2 message types, generated at run time.

:func:`dds_class` turns the field definitions of a ROS type in the rosbags Jazzy
typestore (:func:`t42_transfer.ros.naming.typestore_for`) into an ``IdlStruct``
whose IDL type name is the one rmw_cyclonedds_cpp uses
(``pkg::msg::dds_::Name_``), recursively for nested types.  Serialised as XCDR1
these classes give the same bytes as rosbags' ``serialize_cdr``.

ROS ``uint8`` (and ``byte``/``char``) fields are declared as IDL ``octet``
(``types.byte``): same bytes on the wire, but a Cyclone 0.10.x peer (Jazzy) crashed
on XTypes type information with int8/uint8 members.  Sequences/arrays of octets
are ``bytes`` on the Python side.

:func:`dds_service_class` is the type of a service request/reply *topic*: what
rmw_cyclonedds_cpp puts on the wire is ``{uint64 guid; int64 seq}`` followed by the
request/response fields, under the request/response type name.  Declaring exactly
that layout (instead of the bare request struct) keeps the XTypes type information
we advertise true to the bytes; rmw_cyclonedds_cpp itself advertises none and
matches by type name only, so the extra members do not disturb ROS peers.

:func:`to_dds` / :func:`from_dds` convert between typestore objects and instances of
the generated classes (tests and diagnostics; the transport itself moves CDR bytes).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from cyclonedds.idl import IdlStruct, make_idl_struct
from cyclonedds.idl import types as t

from t42_transfer.ros.naming import typestore_for

_BASE = {
    "bool": bool,
    "byte": t.byte,
    "char": t.byte,
    "uint8": t.byte,
    "int8": t.int8,
    "int16": t.int16,
    "uint16": t.uint16,
    "int32": t.int32,
    "uint32": t.uint32,
    "int64": t.int64,
    "uint64": t.uint64,
    "float32": t.float32,
    "float64": t.float64,
}
_OCTET = {"byte", "char", "uint8"}
_NUMPY = {
    "bool": np.bool_, "int8": np.int8, "int16": np.int16, "uint16": np.uint16,
    "int32": np.int32, "uint32": np.uint32, "int64": np.int64, "uint64": np.uint64,
    "float32": np.float32, "float64": np.float64, "byte": np.uint8, "char": np.uint8, "uint8": np.uint8,
}

# Nodetype values of rosbags.typesys (BASE=1, NAME=2, ARRAY=3, SEQUENCE=4).
_BASE_NT, _NAME_NT, _ARRAY_NT, _SEQUENCE_NT = 1, 2, 3, 4

_CACHE: dict[str, type[IdlStruct]] = {}
_SERVICE_CACHE: dict[str, type[IdlStruct]] = {}
SERVICE_HEADER_FIELDS = ("request_header_guid", "request_header_seq")
"""Names of the two header members of :func:`dds_service_class` (uint64, int64)."""


def idl_type_name(rostype: str) -> str:
    """``pkg/msg/Name`` -> ``pkg::msg::dds_::Name_`` (also ``pkg/srv/Name_Request``)."""
    pkg, kind, name = rostype.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def _fields(rostype: str) -> list[tuple[str, tuple[Any, Any]]]:
    return typestore_for(rostype).fielddefs[rostype][1]


def _base_type(spec: tuple[str, int]) -> Any:
    name, bound = spec
    if name == "string":
        return t.bounded_str[bound] if bound else str
    if name == "wstring":
        raise NotImplementedError("wstring fields are not supported")
    return _BASE[name]


def _element_type(node: tuple[Any, Any]) -> Any:
    nodetype, detail = int(node[0]), node[1]
    if nodetype == _BASE_NT:
        return _base_type(detail)
    if nodetype == _NAME_NT:
        return dds_class(detail)
    raise ValueError(f"nested arrays are not ROS types: {node!r}")


def _field_type(node: tuple[Any, Any]) -> Any:
    nodetype, detail = int(node[0]), node[1]
    if nodetype in (_BASE_NT, _NAME_NT):
        return _element_type(node)
    inner, size = detail
    element = _element_type(inner)
    if nodetype == _ARRAY_NT:
        return t.array[element, size]
    if nodetype == _SEQUENCE_NT:
        return t.sequence[element, size] if size else t.sequence[element]
    raise ValueError(f"unknown rosbags node type {node!r}")


def dds_class(rostype: str) -> type[IdlStruct]:
    """The (cached) IdlStruct of ROS type ``rostype`` with IDL name ``pkg::msg::dds_::Name_``."""
    cls = _CACHE.get(rostype)
    if cls is None:
        fields = {name: _field_type(node) for name, node in _fields(rostype)}
        cls = make_idl_struct(rostype.split("/")[-1] + "_", idl_type_name(rostype), fields)
        _CACHE[rostype] = cls
    return cls


def dds_service_class(rostype: str) -> type[IdlStruct]:
    """The (cached) wire layout of a service sample: ``{uint64 guid; int64 seq; <fields of rostype>}``.

    ``rostype`` is a request or response type (``std_srvs/srv/Trigger_Request``); the
    IDL name is the one rmw_cyclonedds_cpp registers (``std_srvs::srv::dds_::Trigger_Request_``).
    """
    cls = _SERVICE_CACHE.get(rostype)
    if cls is None:
        if rostype.split("/")[1:2] != ["srv"]:
            raise ValueError(f"{rostype!r} is not a service request/response type")
        body = {name: _field_type(node) for name, node in _fields(rostype)}
        clash = set(body) & set(SERVICE_HEADER_FIELDS)
        if clash:
            raise ValueError(f"{rostype} has fields named like the request header: {sorted(clash)}")
        guid, seq = SERVICE_HEADER_FIELDS
        fields = {guid: t.uint64, seq: t.int64, **body}
        cls = make_idl_struct(rostype.split("/")[-1] + "_", idl_type_name(rostype), fields)
        _SERVICE_CACHE[rostype] = cls
    return cls


def _is_octet(node: tuple[Any, Any]) -> bool:
    return int(node[0]) == _BASE_NT and node[1][0] in _OCTET


def _to_dds_value(node: tuple[Any, Any], value: Any) -> Any:
    nodetype, detail = int(node[0]), node[1]
    if nodetype == _BASE_NT:
        if detail[0] in _OCTET:
            return int(value)
        if detail[0] == "bool":
            return bool(value)
        if detail[0] in ("float32", "float64"):
            return float(value)
        if detail[0] == "string":
            return str(value)
        return int(value)
    if nodetype == _NAME_NT:
        return to_dds(detail, value)
    inner = detail[0]
    if _is_octet(inner):
        return bytes(np.asarray(value, dtype=np.uint8).tobytes())
    return [_to_dds_value(inner, v) for v in value]


def to_dds(rostype: str, msg: Any) -> IdlStruct:
    """An instance of :func:`dds_class` ``(rostype)`` with the values of typestore object ``msg``."""
    cls = dds_class(rostype)
    return cls(**{name: _to_dds_value(node, getattr(msg, name)) for name, node in _fields(rostype)})


def _from_dds_value(node: tuple[Any, Any], value: Any) -> Any:
    nodetype, detail = int(node[0]), node[1]
    if nodetype == _BASE_NT:
        return value
    if nodetype == _NAME_NT:
        return from_dds(detail, value)
    inner = detail[0]
    if int(inner[0]) == _BASE_NT and inner[1][0] in _NUMPY:
        if _is_octet(inner):
            return np.frombuffer(bytes(value), dtype=np.uint8).copy()
        return np.asarray(value, dtype=_NUMPY[inner[1][0]])
    return [_from_dds_value(inner, v) for v in value]


def from_dds(rostype: str, obj: Any) -> Any:
    """The typestore object of ``rostype`` with the values of a :func:`dds_class` instance."""
    cls = typestore_for(rostype).types[rostype]
    return cls(**{name: _from_dds_value(node, getattr(obj, name)) for name, node in _fields(rostype)})
