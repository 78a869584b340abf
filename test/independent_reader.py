"""An independent reader of a recorded bag: ``python independent_reader.py BAG_DIR`` prints, as JSON, every message
decoded twice, by rosbags with a fresh typestore built only from the bag's own MCAP schemas and by
mcap-ros2-support, without this project's packages, t42_interfaces or rclpy (importing them fails here).

Output: ``{"schemas": {topic: [rosbags' definition format, type]}, "rosbags": {topic: [msg...]},
"mcap_ros2": {topic: [msg...]}}``, each message as plain JSON (fields by name, sequences as lists).
"""

from __future__ import annotations

import importlib.abc
import json
import sys
from pathlib import Path
from typing import Any

FORBIDDEN = ("t42_interfaces", "t42_transfer", "msg_adapters", "rclpy")


class _Refuse(importlib.abc.MetaPathFinder):
    def find_spec(self, name: str, path: Any = None, target: Any = None) -> None:
        if name.split(".")[0] in FORBIDDEN:
            raise ImportError(f"the independent reader must not import {name}")
        return None


sys.meta_path.insert(0, _Refuse())

from mcap.reader import make_reader  # noqa: E402
from mcap_ros2.decoder import DecoderFactory  # noqa: E402
from rosbags.rosbag2 import Reader  # noqa: E402
from rosbags.typesys import Stores, get_types_from_msg, get_typestore  # noqa: E402


def plain(value: Any) -> Any:
    """A decoded message (either reader's) as JSON-able data."""
    if hasattr(value, "tolist"):  # numpy arrays and scalars
        return value.tolist()
    if isinstance(value, (bytes, bytearray)):
        return list(value)
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if isinstance(value, (bool, int, float, str)) or value is None:
        return value
    fields = getattr(value, "__dataclass_fields__", None) or getattr(value, "__slots__", None)
    if fields is None:
        raise TypeError(f"cannot make {type(value).__name__} plain")
    return {name: plain(getattr(value, name)) for name in fields if not name.startswith("_")}


def with_rosbags(bag: Path) -> tuple[dict[str, list[Any]], dict[str, list[str]]]:
    store = get_typestore(Stores.EMPTY)  # nothing known but what the bag says
    out: dict[str, list[Any]] = {}
    schemas: dict[str, list[str]] = {}
    with Reader(bag) as reader:
        for conn in reader.connections:
            schemas[conn.topic] = [conn.msgdef.format.name, conn.msgtype]
            store.register(get_types_from_msg(conn.msgdef.data, conn.msgtype))
            out[conn.topic] = []
        for conn, _, data in reader.messages():
            out[conn.topic].append(plain(store.deserialize_cdr(data, conn.msgtype)))
    return out, schemas


def with_mcap_ros2(bag: Path) -> dict[str, list[Any]]:
    out: dict[str, list[Any]] = {}
    for file in sorted(bag.glob("*.mcap")):
        with file.open("rb") as stream:
            reader = make_reader(stream, decoder_factories=[DecoderFactory()])
            for schema, channel, _, decoded in reader.iter_decoded_messages():
                assert schema is not None and schema.encoding == "ros2msg", (channel.topic, schema)
                out.setdefault(channel.topic, []).append(plain(decoded))
    return out


def main() -> None:
    bag = Path(sys.argv[1])
    rosbags_msgs, schemas = with_rosbags(bag)
    loaded = sorted(m for m in sys.modules if m.split(".")[0] in FORBIDDEN)
    assert not loaded, loaded
    print(json.dumps({"schemas": schemas, "rosbags": rosbags_msgs, "mcap_ros2": with_mcap_ros2(bag)}))


if __name__ == "__main__":
    main()
