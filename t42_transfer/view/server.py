"""The one way ``t42 view`` starts a Foxglove WebSocket server (live graph and bags alike)."""

from __future__ import annotations

from typing import Any

import foxglove


def start_server(name: str, host: str, port: int, **options: Any) -> foxglove.WebSocketServer:
    """foxglove's server on ``host:port``; ValueError in one line when it cannot listen there (a port in use, an
    address this machine does not have): the node runner and the CLI then exit 2 with it."""
    try:
        return foxglove.start_server(name=name, host=host, port=port, **options)
    except RuntimeError as err:  # foxglove raises FoxgloveError (a RuntimeError) for a failed bind
        raise ValueError(f"{name}: cannot serve on {host}:{port}: {err}") from None
