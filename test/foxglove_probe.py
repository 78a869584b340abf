"""An independent Foxglove WebSocket client for the tests: the protocol's reference implementation
(``@foxglove/ws-protocol`` from npm, run with node: foxglove_probe.js) when npm can install it into a temporary
folder, else Python ``websockets`` speaking the protocol (spec: foxglove/ws-protocol docs/spec.md, v1).

:func:`probe` connects, records the server's info and advertised channels, subscribes to ``topics``, keeps the
first ``count`` messages of each, optionally publishes one message repeatedly on a client channel, and returns
a :class:`ProbeResult` (the same from either client).
"""

from __future__ import annotations

import base64
import json
import os
import shutil
import struct
import subprocess
import time
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import Any

WS_PROTOCOL = "@foxglove/ws-protocol@0.8.0"
SUBPROTOCOLS = ["foxglove.websocket.v1", "foxglove.sdk.v1"]
"""The protocol's v1 under ws-protocol's name and under foxglove-sdk's (the server picks the one it speaks)."""
HERE = Path(__file__).resolve().parent


@dataclass
class ProbeResult:
    impl: str
    """``node`` (@foxglove/ws-protocol) or ``python`` (websockets)."""
    server: dict[str, Any] | None
    channels: list[dict[str, Any]]
    messages: dict[str, list[tuple[int, bytes]]]
    """topic -> (log time ns, CDR bytes) of the first messages."""
    times: list[int] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)

    def channel(self, topic: str) -> dict[str, Any]:
        found = [c for c in self.channels if c["topic"] == topic]
        assert found, f"{topic} not advertised; got {sorted(c['topic'] for c in self.channels)}"
        return found[0]


@cache
def ws_protocol_dir() -> Path | None:
    """A folder whose node_modules holds @foxglove/ws-protocol (installed once per machine from the registry), or
    None when node or npm is missing or the registry cannot be reached."""
    node, npm = shutil.which("node"), shutil.which("npm")
    if not node or not npm:
        return None
    folder = Path(os.environ.get("TMPDIR", "/tmp")) / "t42-foxglove-ws-protocol"
    module = folder / "node_modules" / "@foxglove" / "ws-protocol" / "package.json"
    if not module.is_file():
        folder.mkdir(parents=True, exist_ok=True)
        try:
            subprocess.run([npm, "install", "--prefix", str(folder), "--no-audit", "--no-fund", "--fetch-retries=1",
                            "--fetch-timeout=20000", WS_PROTOCOL], check=True, capture_output=True, timeout=120)
        except (subprocess.SubprocessError, OSError):
            return None
    check = subprocess.run([node, "--experimental-websocket", "-e", "require('@foxglove/ws-protocol')"],
                           env=dict(os.environ, NODE_PATH=str(folder / "node_modules")), capture_output=True,
                           timeout=60)
    return folder if module.is_file() and check.returncode == 0 else None


def _request(url: str, topics: list[str], count: int, publish: dict[str, Any] | None, timeout_s: float) -> dict:
    pub = None
    if publish is not None:
        pub = dict(publish, data=base64.b64encode(publish["data"]).decode(), period_ms=publish.get("period_ms", 100),
                   repeat=publish.get("repeat", 5))
    return {"url": url, "topics": topics, "count": count, "publish": pub, "timeout_ms": int(timeout_s * 1000)}


def start_probe(url: str, topics: list[str], count: int = 2, publish: dict[str, Any] | None = None,
                timeout_s: float = 20.0, impl: str | None = None) -> Any:
    """Start a probe; returns a handle for :func:`finish_probe`: node's process, or a Python thread's result."""
    folder = ws_protocol_dir() if impl in (None, "node") else None
    request = _request(url, topics, count, publish, timeout_s)
    if folder is not None:
        env = dict(os.environ, NODE_PATH=str(folder / "node_modules"))
        return subprocess.Popen([shutil.which("node"), "--experimental-websocket", str(HERE / "foxglove_probe.js"),
                                 json.dumps(request)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env,
                                text=True)
    import threading

    box: dict[str, Any] = {}
    thread = threading.Thread(target=lambda: box.update(result=_python_probe(request)), daemon=True)
    thread.start()
    return thread, box


def running(handle: Any) -> bool:
    return handle.poll() is None if isinstance(handle, subprocess.Popen) else handle[0].is_alive()


def finish_probe(handle: Any) -> ProbeResult:
    """Wait for the probe to end; its result."""
    if isinstance(handle, subprocess.Popen):
        out, err = handle.communicate(timeout=60)
        assert handle.returncode == 0 and out.strip(), f"probe failed ({handle.returncode}): {err[-2000:]}"
        raw = json.loads(out.strip().splitlines()[-1])
    else:
        handle[0].join(60)
        raw = handle[1]["result"]
    return ProbeResult(
        impl=raw["impl"], server=raw["server"], channels=raw["channels"],
        messages={t: [(int(m["log_time"]), base64.b64decode(m["data"])) for m in kept]
                  for t, kept in raw["messages"].items()},
        times=[int(t) for t in raw["times"]], errors=raw["errors"])


def _python_probe(request: dict) -> dict:
    """The probe over Python websockets (the fallback), with the node probe's result layout."""
    from websockets.sync.client import connect

    result: dict[str, Any] = {"impl": "python", "server": None, "channels": [], "messages": {}, "times": [],
                              "errors": []}
    topic_of: dict[int, str] = {}
    pub, sent, next_send = request["publish"], 0, 0.0
    deadline = time.monotonic() + request["timeout_ms"] / 1000

    def done() -> bool:
        heard = all(len(result["messages"].get(t, [])) >= request["count"] for t in request["topics"])
        return heard and (pub is None or sent >= pub["repeat"])

    with connect(request["url"], subprotocols=SUBPROTOCOLS, max_size=None) as ws:
        while time.monotonic() < deadline and not done():
            if pub is not None and result["server"] is not None and time.monotonic() >= next_send:
                if sent == 0:
                    ws.send(json.dumps({"op": "advertise", "channels": [
                        {"id": 1, "topic": pub["topic"], "encoding": "cdr", "schemaName": pub["schemaName"]}]}))
                ws.send(b"\x01" + struct.pack("<I", 1) + base64.b64decode(pub["data"]))
                sent, next_send = sent + 1, time.monotonic() + pub["period_ms"] / 1000
            try:
                frame = ws.recv(timeout=0.05)
            except TimeoutError:
                continue
            if isinstance(frame, str):
                msg = json.loads(frame)
                if msg.get("op") == "serverInfo":
                    result["server"] = msg
                elif msg.get("op") == "advertise":
                    for ch in msg["channels"]:
                        result["channels"].append(ch)
                        if ch["topic"] in request["topics"]:
                            sub = len(topic_of) + 1
                            topic_of[sub] = ch["topic"]
                            subscription = {"id": sub, "channelId": ch["id"]}
                            ws.send(json.dumps({"op": "subscribe", "subscriptions": [subscription]}))
            elif frame[0] == 1:  # MessageData: subscription id, log time, payload
                sub, log_time = struct.unpack_from("<IQ", frame, 1)
                kept = result["messages"].setdefault(topic_of.get(sub, "?"), [])
                if len(kept) < request["count"]:
                    kept.append({"log_time": str(log_time), "data": base64.b64encode(frame[13:]).decode()})
            elif frame[0] == 2:  # Time
                result["times"].append(str(struct.unpack_from("<Q", frame, 1)[0]))
    return result
