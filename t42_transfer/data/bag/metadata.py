"""A bag's ``metadata.yaml`` and ``custom_data``: parsed with every field's type checked, never by rosbags.

rosbags would unpack a compressed bag into a temporary folder to read it, so the bag information is
parsed here and a compressed bag is refused.  The ``t42_transfer.*`` keys of ``custom_data`` restore what
stamps cannot say: the hand, each episode's end reason, and whether a bag is a repaired prefix.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path, PurePath
from typing import Any

import yaml
from mcap.records import Metadata

from t42_transfer.data.errors import BagError
from t42_transfer.files import NotRegularFile, regular_file

HAND_KEY = "t42_transfer.hand"
EPISODES_KEY = "t42_transfer.episodes"
REPAIRED_KEY = "t42_transfer.repaired"
"""Set by :mod:`t42_transfer.data.bag.repair`: the bag is a killed writer's salvaged prefix
(a cut last step is no error)."""
UNIT_KEY = "t42_transfer.action_unit_rad"
"""The action unit the episodes written were in (:func:`~t42_transfer.data.bag.writer.write_bag`): a bag holds the
actuators' steps, and is read back in that unit unless another is asked for.  A recorder's bag has none."""


def declared_unit(custom: dict[str, str]) -> float | None:
    """The action unit ``custom`` data declares (:data:`UNIT_KEY`), or None when it declares none or no number."""
    try:
        return float(custom[UNIT_KEY])
    except (KeyError, ValueError):
        return None


@dataclasses.dataclass(frozen=True)
class BagMetadata:
    """What a bag's metadata.yaml says, each field's type checked (an absent field is None)."""

    storage: str | None
    files: tuple[str, ...]
    """Names of ``relative_file_paths`` (their directories are ignored: no path leads out of the bag)."""
    custom: dict[str, str]
    ros_distro: str | None
    counts: dict[str, int | None]
    """Message count by topic."""
    digests: dict[str, str]
    """Type hash by topic, where given."""
    message_count: int | None
    start_ns: int | None
    duration_ns: int | None


_MAX_METADATA_BYTES = 1 << 24
"""A bag's metadata.yaml is kilobytes; a bigger one is refused before it is parsed."""


def metadata_yaml(bag: Path) -> tuple[BagMetadata | None, str]:
    """The bag directory's metadata.yaml, or None and why not (missing, or no YAML: a writer cut off closing).

    BagError when it is no regular file, too big, or not rosbag2 bag information
    (a field of the wrong type, a compressed bag).
    """
    file = bag / "metadata.yaml"
    if not file.exists() and not file.is_symlink():
        return None, "metadata.yaml is missing"
    try:
        size = regular_file(file).st_size
    except NotRegularFile as err:
        raise BagError(bag, f"{file.name} {err.reason}") from None
    if size > _MAX_METADATA_BYTES:
        raise BagError(bag, f"metadata.yaml is {size} bytes, more than the {_MAX_METADATA_BYTES} read of one")
    try:
        doc = yaml.safe_load(file.read_bytes().decode())
    except (ValueError, yaml.YAMLError, RecursionError) as err:  # not UTF-8, not YAML, nested beyond the stack
        first = next(iter(str(err).splitlines()), "")
        return None, f"metadata.yaml is unreadable ({type(err).__name__}: {first})"
    return parse_metadata(bag, doc), ""


_EXPECTED = {str: "text", int: "an integer", list: "a list", dict: "a mapping"}


def _field(bag: Path, mapping: dict[Any, Any], key: str, kind: type, where: str = "") -> Any:
    """``mapping[key]`` if it is a ``kind`` (a bool is no integer) or absent (None); BagError otherwise."""
    value = mapping.get(key)
    if value is None or (isinstance(value, kind) and not (kind is int and isinstance(value, bool))):
        return value
    raise BagError(bag, f"metadata.yaml: {where}{key} must be {_EXPECTED[kind]}, not {type(value).__name__}")


def parse_metadata(bag: Path, doc: Any) -> BagMetadata:
    info = doc.get("rosbag2_bagfile_information") if isinstance(doc, dict) else None
    if not isinstance(info, dict):
        raise BagError(bag, "metadata.yaml holds no rosbag2_bagfile_information mapping")
    mode = _field(bag, info, "compression_mode", str) or ""
    if mode.lower() not in ("", "none"):
        compression = _field(bag, info, "compression_format", str)
        raise BagError(bag, f"is compressed (compression_mode {mode}, compression_format {compression}); only "
                            "uncompressed bags are read (ros2 bag convert decompresses one)")
    paths = _field(bag, info, "relative_file_paths", list) or []
    if not all(isinstance(p, str) for p in paths):
        raise BagError(bag, "metadata.yaml: relative_file_paths must list file names")
    custom = {}
    for key, value in (_field(bag, info, "custom_data", dict) or {}).items():
        if isinstance(value, (list, dict, set)):
            raise BagError(bag, f"metadata.yaml: custom_data {key} must be text, not {type(value).__name__}")
        custom[str(key)] = "" if value is None else str(value)
    counts: dict[str, int | None] = {}
    digests = {}
    for i, entry in enumerate(_field(bag, info, "topics_with_message_count", list) or []):
        where = f"topics_with_message_count[{i}]"
        if not isinstance(entry, dict):
            raise BagError(bag, f"metadata.yaml: {where} must be a mapping, not {type(entry).__name__}")
        topic = _field(bag, entry, "topic_metadata", dict, f"{where}.") or {}
        name = _field(bag, topic, "name", str, f"{where}.topic_metadata.")
        if name is None:
            raise BagError(bag, f"metadata.yaml: {where} names no topic")
        counts[name] = _field(bag, entry, "message_count", int, f"{where}.")
        digest = _field(bag, topic, "type_description_hash", str, f"{where}.topic_metadata.")
        if digest:
            digests[name] = digest
    return BagMetadata(
        storage=_field(bag, info, "storage_identifier", str),
        files=tuple(PurePath(p).name for p in paths),
        custom=custom,
        ros_distro=_field(bag, info, "ros_distro", str),
        counts=counts,
        digests=digests,
        message_count=_field(bag, info, "message_count", int),
        start_ns=_field(bag, _field(bag, info, "starting_time", dict) or {}, "nanoseconds_since_epoch", int,
                        "starting_time."),
        duration_ns=_field(bag, _field(bag, info, "duration", dict) or {}, "nanoseconds", int, "duration."),
    )


def record_metadata(record: Metadata) -> tuple[dict[str, str], str | None]:
    """custom_data and ros_distro of rosbag2's metadata record in an MCAP: a convenience copy, a bad one is none."""
    return serialized_metadata(record.metadata.get("serialized_metadata", ""), record.name)


def serialized_metadata(text: str, name: str) -> tuple[dict[str, str], str | None]:
    """custom_data and ros_distro of the copy of metadata.yaml a storage file keeps (an MCAP's metadata record, a
    db3's ``metadata`` table), written on close: a convenience copy, a bad one is none."""
    try:
        doc = yaml.safe_load(text)
        info = doc.get("rosbag2_bagfile_information", doc) if isinstance(doc, dict) else None
        meta = parse_metadata(Path(name), {"rosbag2_bagfile_information": info})
    except (BagError, ValueError, yaml.YAMLError, RecursionError):
        return {}, None
    return meta.custom, meta.ros_distro
