"""Choosing the Transport a node process runs on: rclpy where ROS 2 is installed, else Cyclone DDS.

The backend comes from the ``backend`` argument, else ``T42_TRANSPORT``
(``auto``, ``rclpy`` or ``cyclone``; unset means ``auto``).  ``auto`` picks rclpy
when ``import rclpy`` works (a sourced ROS 2 install), otherwise Cyclone DDS,
which speaks to ROS 2 nodes running ``rmw_cyclonedds_cpp`` without one.
"""

from __future__ import annotations

import os

from t42_transfer.ros.transport import Transport

BACKENDS = ("auto", "rclpy", "cyclone")
ENV_VAR = "T42_TRANSPORT"


def rclpy_available() -> bool:
    """Whether ``import rclpy`` works here (a half-sourced install that fails to load counts as no)."""
    try:
        import rclpy  # noqa: F401
    except ImportError:
        return False
    return True


def resolve_backend(backend: str | None = None) -> str:
    """``rclpy`` or ``cyclone``: the concrete backend ``backend`` (else ``$T42_TRANSPORT``, else auto) means."""
    choice = (backend if backend is not None else os.environ.get(ENV_VAR, "") or "auto").strip().lower()
    if choice not in BACKENDS:
        source = "backend" if backend is not None else ENV_VAR
        raise ValueError(f"{source}={choice!r}: expected one of {', '.join(BACKENDS)}")
    if choice == "auto":
        return "rclpy" if rclpy_available() else "cyclone"
    if choice == "rclpy" and not rclpy_available():
        raise ValueError("the rclpy backend was requested but rclpy is not importable "
                         f"(source a ROS 2 Jazzy install, or set {ENV_VAR}=cyclone)")
    return choice


def make_transport(node_name: str, backend: str | None = None, domain_id: int | None = None) -> Transport:
    """A transport for node ``node_name`` on the chosen backend (``domain_id`` default: ``ROS_DOMAIN_ID``)."""
    if resolve_backend(backend) == "rclpy":
        from t42_transfer.ros.rclpy_backend import RclpyTransport

        return RclpyTransport(node_name, domain_id=domain_id)
    from t42_transfer.ros.cyclone import CycloneTransport

    return CycloneTransport(node_name, domain_id=domain_id)
