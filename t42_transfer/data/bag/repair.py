"""Make a bag whose writer died (SIGKILL, power cut) whole again: ``t42 bag repair``.

A recorder killed mid-bag leaves an MCAP without its summary and footer, and no
(or a stale) ``metadata.yaml``.  :func:`~t42_transfer.data.bag.read_bag` already recovers such a
bag's readable prefix, with a warning, every time; repairing it once rewrites the
readable records (every complete chunk, in file order) as a fresh rosbag2 v9 MCAP
through :class:`~.writer.JazzyWriter`, as the recorder and :mod:`.writer` write theirs
(same layout, ``ros_distro: jazzy``), so ``ros2 bag`` and :mod:`t42_transfer.data.bag` read it
cleanly, with ``metadata.yaml`` giving per-topic counts, start time, duration,
types and each topic's offered QoS as recorded in its MCAP channel.  Each
original file, ``metadata.yaml`` included, is kept as ``<name>.orig``.
``custom_data`` keeps what the bag had (the MCAP's own record, written only on a clean
close, else the old ``metadata.yaml``'s: a cut file loses its record, not its yaml) and
gains ``REPAIRED_KEY`` (what was wrong), so :func:`~t42_transfer.data.bag.read_bag` still
treats a cut-off last step as a cut, not an error.  A topic of a type the project's store lacks keeps the file's
own definition; one whose type rosbags cannot write (no definition in the file) is left out and named, never
silently: only reading the input finds damage, and a repair that would carry nothing over leaves the bag alone.

What is wrong is found as ``t42 bag info --verify`` finds it (the same scan of
every record, the same comparison with ``metadata.yaml``), plus files without a
summary; files are read with :func:`~.storage.mcap_records`'s bounds, and a FIFO
or a directory where a file belongs is refused, never opened or replaced.
"""

from __future__ import annotations

import dataclasses
import stat
import tempfile
from pathlib import Path
from typing import Any, BinaryIO

import yaml
from mcap.records import Channel, Message, Metadata, Schema
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2.metadata import parse_qos
from rosbags.typesys import Stores, get_typestore

from msg_adapters import TYPESTORE
from t42_transfer.data.bag.db3 import parsed_definition, stored_definition
from t42_transfer.data.bag.metadata import REPAIRED_KEY, BagMetadata, metadata_yaml, record_metadata
from t42_transfer.data.bag.reader import refusals
from t42_transfer.data.bag.storage import (
    RawBag,
    mcap_records,
    metadata_mismatches,
    path_mode,
    regular_size,
    scan_mcap,
)
from t42_transfer.data.bag.writer import JazzyWriter
from t42_transfer.data.errors import BagError

ORIG_SUFFIX = ".orig"


@dataclasses.dataclass(frozen=True)
class RepairReport:
    """What :func:`repair_bag` found and did."""

    path: Path
    repaired: bool
    """False when the bag was sound and left untouched."""
    problems: tuple[str, ...]
    """Why it needed repair (empty when it did not)."""
    counts: dict[str, int]
    """Messages per topic in the (repaired) bag."""
    originals: tuple[Path, ...] = ()
    """Where the original storage files and metadata.yaml were moved."""
    stopped: str = ""
    """Where reading stopped in a damaged file ("" when every file read to its end)."""
    left_out: tuple[str, ...] = ()
    """What was read but could not be carried over (it is in the originals), and why: a topic of a type rosbags
    cannot write."""
    left_out_messages: int = 0
    """Messages read but not carried over."""

    @property
    def message_count(self) -> int:
        return sum(self.counts.values())


def repair_bag(path: str | Path) -> RepairReport:
    """Rewrite a damaged MCAP bag directory in place (originals kept as ``*.mcap.orig``, ``metadata.yaml.orig``).

    A sound bag (every file read to its summary, ``metadata.yaml`` agreeing with
    the data in files, counts, start and duration) is left as it is; one with
    nothing readable (killed just after it was opened) becomes an empty bag.  A topic
    whose type cannot be written is left out and named in the report (``left_out``).  Raises
    :class:`BagError` for a path that is no MCAP bag directory or holds non-regular
    files where files belong, or when none of the messages read can be carried over (the
    bag is then left as it is: no repair empties a bag), and FileExistsError when
    ``*.orig`` files of an earlier repair are in the way (nothing is ever overwritten).
    """
    bag = Path(path)
    with refusals(bag):
        files = _mcap_files(bag)
        raw = scan_mcap(files, None)
        meta, problems = _problems(bag, raw)
        if not problems:
            return RepairReport(bag, False, (), {topic: t.count for topic, t in raw.topics.items()})
        meta_file = bag / "metadata.yaml"
        originals = [*files, meta_file] if meta_file.exists() or meta_file.is_symlink() else files
        kept = [f.with_name(f.name + ORIG_SUFFIX) for f in originals]
        in_the_way = [str(k) for k in kept if k.exists() or k.is_symlink()]
        if in_the_way:
            raise FileExistsError(f"{bag}: {', '.join(in_the_way)} exist already; move them away to repair again")
        with tempfile.TemporaryDirectory(prefix=f".{bag.name}.", suffix=".repair", dir=bag) as staging:
            rebuilt = Path(staging) / bag.name
            # Nothing readable (a recorder killed right after it opened the file) makes an empty, valid bag.
            rewriter, stopped = _rewrite(files, rebuilt, "; ".join(problems), meta.custom if meta else {})
            left_out, lost = rewriter.left_out(), sum(count for _, count, _ in rewriter.lost.values())
            if lost and not any(rewriter.counts.values()):
                raise BagError(bag, f"none of the messages read can be carried over ({'; '.join(left_out)}); "
                                    "left as it is")
            for original, orig in zip(originals, kept, strict=True):
                original.rename(orig)
            (rebuilt / f"{bag.name}.mcap").rename(files[0])
            _write_metadata(rebuilt / "metadata.yaml", meta_file, files[0].name)
    return RepairReport(bag, True, tuple(problems), rewriter.counts, tuple(kept), stopped, tuple(left_out), lost)


def _mcap_files(bag: Path) -> list[Path]:
    if not stat.S_ISDIR(path_mode(bag)):
        raise BagError(bag, "is not a bag directory (repair works on the directory holding the .mcap)")
    files = sorted(bag.glob("*.mcap"))
    if not files:
        raise BagError(bag, "is not an MCAP bag: the directory holds no .mcap file")
    for file in files:
        regular_size(bag, file)
        with file.open("rb") as stream:
            if stream.read(8) != b"\x89MCAP0\r\n":
                raise BagError(bag, f"{file.name} is not an MCAP file (bad magic bytes)")
    meta_file = bag / "metadata.yaml"
    if meta_file.exists() or meta_file.is_symlink():
        regular_size(bag, meta_file)  # a FIFO or a directory in its place is refused, never replaced
    return files


def _problems(bag: Path, raw: RawBag) -> tuple[BagMetadata | None, list[str]]:
    """The bag's metadata.yaml (None where missing or unusable) and what is wrong with the bag; no problems when
    its files read to their summaries and metadata.yaml agrees."""
    problems = [raw.stopped] if raw.stopped else []
    problems += [f"{name} has no summary" for name in raw.unsummarized]
    try:
        meta, problem = metadata_yaml(bag)
    except BagError as err:  # wrong types, a compressed bag: the rewritten metadata.yaml replaces it
        meta, problem = None, f"metadata.yaml is unusable ({err.problem})"
    if meta is None:
        return None, [*problems, problem]
    return meta, [*problems, *metadata_mismatches(bag, meta, raw)]


def _typing(channel: Channel, schema: Schema | None) -> dict[str, Any] | str:
    """``add_connection``'s type arguments for ``channel``, or why its type cannot be carried over.

    A type of the project's (Jazzy's) store is written as Jazzy defines it.  Any other keeps the file's own
    definition, with that definition's RIHS01 hash as rosbags computes it: Humble's MCAP plugin writes no
    ``topic_type_hash`` and Jazzy's an empty one for some publishers, rosbags' writer needs one, and its reader
    refuses a bag whose hash and definition disagree.  A type with neither (rosbag2 records a type whose ``.msg``
    it could not find with an empty schema) cannot be written by rosbags.
    """
    if schema is None:
        return "its channel names no schema, so no message type"
    if schema.name in TYPESTORE.types:
        return {"typestore": TYPESTORE}
    if schema.encoding not in ("ros2msg", "ros2idl") or not schema.data.strip():
        return (f"the file holds no definition of {schema.name} (schema encoding {schema.encoding!r}) and ROS 2 "
                "Jazzy's types do not include it")
    try:  # an IDL one written with rosbag2's header, its #include lines and include guards kept as comments
        msgdef, types = parsed_definition(stored_definition(schema.encoding, schema.data.decode()), schema.name)
        text = msgdef.data
        store = get_typestore(Stores.EMPTY)
        store.register({**TYPESTORE.fielddefs, **types})  # the file's definitions first, Jazzy's for the rest
        rihs01 = store.hash_rihs01(schema.name)
    except Exception as err:  # rosbags raises many types for a definition it cannot parse or resolve
        return f"its definition of {schema.name} cannot be used ({type(err).__name__}: {err})"
    return {"msgdef": text, "rihs01": rihs01}


class _Rewriter:
    """Streams salvaged records into a rosbags writer, one connection per (topic, type, offered QoS).

    Only reading the input finds damage: what writing raises (our code, rosbags') propagates, so a failure here
    never passes for a cut file and never empties a bag.  A topic whose type cannot be written is left out,
    counted, and said so.
    """

    def __init__(self, writer: JazzyWriter) -> None:
        self.writer = writer
        self.connections: dict[tuple[str, str, tuple[Any, ...]], Any] = {}
        self.counts: dict[str, int] = {}
        self.lost: dict[str, list[Any]] = {}
        """Topics left out: [type, messages read, why]."""
        self.notes: list[str] = []
        """What else was not carried over (a channel's unreadable offered QoS)."""
        self.custom: dict[str, str] | None = None
        """custom_data of the files' rosbag2 metadata record (None: none was read)."""

    def file(self, stream: BinaryIO, size: int, name: str) -> str:
        """Carry one file's readable records over; where reading stopped ("" when it was read to its end)."""
        schemas: dict[int, Schema] = {}
        channels: dict[int, tuple[str, Any]] = {}  # by channel id: its topic and connection (None: left out)
        records = mcap_records(stream, size)
        while True:
            try:
                record = next(records, None)
                if isinstance(record, Message) and record.channel_id not in channels:  # as the reader stops there
                    raise ValueError(f"a message on channel {record.channel_id}, which no channel record declared")
            except Exception as err:  # whatever the damage, the records before it stand
                return f"{name} is unreadable from offset {stream.tell()} ({type(err).__name__}: {err})"
            if record is None:
                return ""
            if isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                channels[record.id] = (record.topic, self._connection(record, schemas.get(record.schema_id)))
            elif isinstance(record, Message):
                topic, connection = channels[record.channel_id]
                if connection is None:
                    self.lost[topic][1] += 1
                else:
                    self.writer.write(connection, record.log_time, record.data)
                    self.counts[topic] += 1
            elif isinstance(record, Metadata) and record.name == "rosbag2" and self.custom is None:
                self._custom_data(record)

    def _connection(self, channel: Channel, schema: Schema | None) -> Any:
        """The writer's connection for ``channel``; None when its type cannot be written (noted in ``lost``)."""
        msgtype = schema.name if schema is not None else "no type"
        qos_text = channel.metadata.get("offered_qos_profiles", "")
        try:
            qos = parse_qos(qos_text) if qos_text else []
        except Exception as err:  # a damaged QoS text: the messages stand, offered the default QoS
            qos, note = [], f"{channel.topic}: its offered QoS, unreadable ({type(err).__name__}: {err})"
            self.notes += [] if note in self.notes else [note]
        key = (channel.topic, msgtype, tuple(qos))
        if key not in self.connections:
            typed = _typing(channel, schema)
            if isinstance(typed, str):
                self.lost.setdefault(channel.topic, [msgtype, 0, typed])
                self.connections[key] = None
            else:
                self.connections[key] = self.writer.add_connection(
                    channel.topic, msgtype, serialization_format=channel.message_encoding,
                    offered_qos_profiles=qos, **typed,
                )
                self.counts.setdefault(channel.topic, 0)
        return self.connections[key]

    def left_out(self) -> list[str]:
        """What the new bag lacks of what was read, and why."""
        return [*(f"{topic} ({msgtype}, {count} messages): {why}"
                  for topic, (msgtype, count, why) in sorted(self.lost.items())), *self.notes]

    def _custom_data(self, record: Metadata) -> None:
        """custom_data of rosbag2's own metadata record (written only on a clean close)."""
        self.custom = record_metadata(record)[0]
        self.keep_custom(self.custom)

    def keep_custom(self, custom: dict[str, str]) -> None:
        """Carry the bag's custom_data into the new one."""
        for key, value in custom.items():
            if key != REPAIRED_KEY:  # this repair's own entry stands
                self.writer.set_custom_data(key, value)


def _rewrite(files: list[Path], rebuilt: Path, problems: str, old_custom: dict[str, str]) -> tuple[_Rewriter, str]:
    """Salvage every readable record of ``files`` into a new bag at ``rebuilt``: (what was carried, where reading
    stopped).

    ``old_custom`` (the old metadata.yaml's custom_data) stands in where no file's metadata record was read.
    """
    stopped = []
    with JazzyWriter(rebuilt, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        rewriter = _Rewriter(writer)
        for file in files:
            with file.open("rb") as stream:
                stopped.append(rewriter.file(stream, file.stat().st_size, file.name))
        if rewriter.custom is None:
            rewriter.keep_custom(old_custom)
        left_out = rewriter.left_out()
        writer.set_custom_data(REPAIRED_KEY, "; ".join([problems, *(f"left out {line}" for line in left_out)]))
    return rewriter, "; ".join(s for s in stopped if s)


def _write_metadata(written: Path, target: Path, file_name: str) -> None:
    """rosbags' metadata.yaml for the rebuilt file, renamed to the original file name."""
    meta = yaml.safe_load(written.read_text())
    info = meta["rosbag2_bagfile_information"]
    info["relative_file_paths"] = [file_name]
    for entry in info.get("files") or []:
        entry["path"] = file_name
    tmp = target.with_name(target.name + ".tmp")
    tmp.write_text(yaml.safe_dump(meta, sort_keys=False))
    tmp.replace(target)
