"""ROS 2 names -> DDS names and type hashes, as rmw_cyclonedds_cpp (Jazzy) maps them.

Pure functions.  Topics travel as ``rt`` + ROS name, services as ``rq`` + name +
``Request`` and ``rr`` + name + ``Reply``; types as ``pkg::msg::dds_::Name_`` and
``pkg::srv::dds_::Name_Request_`` / ``Name_Response_``.  Endpoint USER_DATA carries
``typehash=RIHS01_<64 hex>;``.

Service types are not in rosbags' Jazzy typestore, so :data:`SRV_TYPESTORE` is a
separate Jazzy typestore with the project's service types registered from IDL.  IDL
(not ``.msg`` text) gives the names rosidl generates (``std_srvs/srv/Trigger_Request``)
and hence the right RIHS01 hashes; an empty request gets rosidl's placeholder
``uint8 structure_needs_at_least_one_member``.  :func:`type_hash` of a request or
response is that message's hash; the whole-service hash (request, response and event
message together) is not computed here.
"""

from __future__ import annotations

import re
from typing import Any

from rosbags.typesys import Stores, get_types_from_idl, get_typestore

from msg_adapters import TYPESTORE

SERVICE_IDL = """
module std_srvs {
  module srv {
    struct Trigger_Request {
      uint8 structure_needs_at_least_one_member;
    };
    struct Trigger_Response {
      boolean success;
      string message;
    };
  };
};
"""
"""IDL of the service types the project uses, as rosidl generates it."""

SRV_TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
SRV_TYPESTORE.register(get_types_from_idl(SERVICE_IDL))

_TOKEN = r"[A-Za-z_][A-Za-z0-9_]*"
_ROS_NAME = re.compile(rf"(/{_TOKEN})+")
_NODE_NAME = re.compile(_TOKEN)
_TYPE_NAME = re.compile(rf"({_TOKEN})/(msg|srv)/([A-Za-z][A-Za-z0-9_]*)")


def validate_name(name: str, what: str = "topic") -> str:
    """Return ``name`` if it is a fully qualified ROS topic/service name, else ValueError."""
    if not isinstance(name, str):
        raise ValueError(f"ROS {what} name must be a str, got {type(name).__name__}")
    if not name.startswith("/"):
        raise ValueError(f"ROS {what} name {name!r} must be absolute (start with '/')")
    if name.endswith("/"):
        raise ValueError(f"ROS {what} name {name!r} must not end with '/'")
    if not _ROS_NAME.fullmatch(name):
        raise ValueError(
            f"ROS {what} name {name!r} is invalid: tokens separated by single '/' of "
            "[A-Za-z0-9_], not starting with a digit"
        )
    if "__" in name:
        raise ValueError(f"ROS {what} name {name!r} must not contain repeated underscores")
    return name


def validate_node_name(name: str) -> str:
    """Return ``name`` if it is a valid ROS node name (no namespace), else ValueError."""
    if not isinstance(name, str) or not _NODE_NAME.fullmatch(name) or "__" in name:
        raise ValueError(f"ROS node name {name!r} is invalid: [A-Za-z_][A-Za-z0-9_]*, no '__'")
    return name


def _split_type(typename: str, kind: str) -> tuple[str, str]:
    match = _TYPE_NAME.fullmatch(typename) if isinstance(typename, str) else None
    if match is None or match.group(2) != kind:
        raise ValueError(f"{typename!r} is not a ROS {kind} type name like 'pkg/{kind}/Name'")
    return match.group(1), match.group(3)


def dds_topic(ros_topic: str) -> str:
    """``/hand/object_pose`` -> ``rt/hand/object_pose``."""
    return "rt" + validate_name(ros_topic)


def dds_request_topic(service: str) -> str:
    """``/reset`` -> ``rq/resetRequest``."""
    return "rq" + validate_name(service, "service") + "Request"


def dds_reply_topic(service: str) -> str:
    """``/reset`` -> ``rr/resetReply``."""
    return "rr" + validate_name(service, "service") + "Reply"


def dds_type_name(msgtype: str) -> str:
    """``geometry_msgs/msg/PoseStamped`` -> ``geometry_msgs::msg::dds_::PoseStamped_``."""
    pkg, name = _split_type(msgtype, "msg")
    return f"{pkg}::msg::dds_::{name}_"


def dds_request_type_name(srvtype: str) -> str:
    """``std_srvs/srv/Trigger`` -> ``std_srvs::srv::dds_::Trigger_Request_``."""
    pkg, name = _split_type(srvtype, "srv")
    return f"{pkg}::srv::dds_::{name}_Request_"


def dds_response_type_name(srvtype: str) -> str:
    """``std_srvs/srv/Trigger`` -> ``std_srvs::srv::dds_::Trigger_Response_``."""
    pkg, name = _split_type(srvtype, "srv")
    return f"{pkg}::srv::dds_::{name}_Response_"


def request_type(srvtype: str) -> str:
    """``std_srvs/srv/Trigger`` -> ``std_srvs/srv/Trigger_Request`` (the typestore name)."""
    _split_type(srvtype, "srv")
    return srvtype + "_Request"


def response_type(srvtype: str) -> str:
    """``std_srvs/srv/Trigger`` -> ``std_srvs/srv/Trigger_Response`` (the typestore name)."""
    _split_type(srvtype, "srv")
    return srvtype + "_Response"


def typestore_for(typename: str) -> Any:
    """The typestore defining ``typename``: msg_adapters' Jazzy store, or :data:`SRV_TYPESTORE`."""
    if typename in TYPESTORE.types:
        return TYPESTORE
    if typename in SRV_TYPESTORE.types:
        return SRV_TYPESTORE
    raise KeyError(f"unknown ROS type {typename!r}: not in the Jazzy typestore nor SERVICE_IDL")


def type_hash(typename: str) -> str:
    """``RIHS01_<64 hex>`` of a message (or service request/response) type."""
    return typestore_for(typename).hash_rihs01(typename)


def user_data_typehash(typename: str) -> str:
    """``typehash=RIHS01_...;``, the endpoint USER_DATA entry."""
    return f"typehash={type_hash(typename)};"
