"""A bag's storage files read into a :class:`RawBag`: MCAP scanned record by record, sqlite3 through
:class:`~.db3.BagReader` (rosbags, taking a topic stored without a definition).

Bags are untrusted input.  Every MCAP read is bounded by the file's size and every chunk by its stated
size, so a damaged MCAP (cut off mid-write, writer killed) gives its readable prefix; non-regular files
are refused before anything opens them.  Which messages make episodes is :mod:`.episodes`'s business.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import sqlite3
import stat
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

import lz4.frame
import zstandard
from mcap.records import Channel, Chunk, McapRecord, Message, Metadata, Schema, Statistics
from mcap.stream_reader import StreamReader, breakup_chunk
from rosbags.interfaces import MessageDefinition, MessageDefinitionFormat
from rosbags.rosbag2 import StoragePlugin

import msg_adapters as ma
from t42_transfer.data.bag.db3 import (
    BagReader,
    readable_definition,
    stored_definition,
    undecodable_line,
    unhashable_definitions,
)
from t42_transfer.data.bag.hand_topics import HAND_ROLES, written_names
from t42_transfer.data.bag.metadata import (
    REPAIRED_KEY,
    BagMetadata,
    metadata_yaml,
    record_metadata,
    serialized_metadata,
)
from t42_transfer.data.errors import BagError
from t42_transfer.files import file_kind, not_regular_reason

STORAGES = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}
SUFFIXES = {".mcap": "mcap", ".db3": "sqlite3"}
HAND_TYPES = {*ma.HAND_TOPICS.values(), ma.STRING}
"""The types of the hand's steps and status: an MCAP without metadata.yaml keeps every topic of these types until
its own metadata record says which of them a recorder wrote its remapped hand topics to.  (The messages loaded are
those of the hand topics, by name or by that record.)"""
_MAX_CHUNK_BYTES = 1 << 28
"""An MCAP chunk may unpack to at most this (rosbag2 writes chunks of about 1 MiB); more is refused, not allocated."""

_NO_DEFINITION = MessageDefinition(MessageDefinitionFormat.NONE, "")


def path_mode(bag: Path) -> int:
    """``st_mode`` of the bag path; BagError when there is nothing."""
    try:
        return bag.stat().st_mode
    except FileNotFoundError:
        raise BagError(bag, "does not exist") from None


def regular_size(bag: Path, file: Path) -> int:
    """Size of ``file`` in ``bag``; BagError unless it is a regular file (checked before opening: a FIFO blocks)."""
    info = file.stat()
    if not stat.S_ISREG(info.st_mode):
        raise BagError(bag, f"{file.name} {not_regular_reason(info.st_mode)}")
    return info.st_size


@dataclasses.dataclass
class _Topic:
    msgtype: str
    count: int
    digest: str = ""


@dataclasses.dataclass
class RawBag:
    """What storage gave: every topic with its messages counted, and the CDR payloads of hand-like topics."""

    storage: str
    topics: dict[str, _Topic]
    messages: dict[str, list[tuple[int, bytes]]]
    """By bag topic, in log-time order: every topic named like a hand topic (the namespace is chosen later)."""
    custom: dict[str, str]
    ros_distro: str | None
    start_ns: int
    end_ns: int
    """First and last log time (0 and 0 without messages)."""
    stopped: str = ""
    """Where reading stopped in a damaged file ("" when every file was read to its end)."""
    unsummarized: tuple[str, ...] = ()
    """MCAP files read to their end that have no summary statistics."""
    meta: BagMetadata | None = None
    problem: str = ""
    """Why a bag directory's metadata.yaml was not used ("" when it was)."""
    undecodable: dict[str, str] = dataclasses.field(default_factory=dict)
    """Why each topic whose stored definition does not parse is not decodable from the bag (a line each, for a
    warning; its messages are read and counted as any topic's)."""

    @property
    def cut(self) -> bool:
        """Only a readable prefix is here (damaged, or repaired from damage): a cut-off last step is no error."""
        return bool(self.stopped) or REPAIRED_KEY in self.custom


def bag_files(bag: Path) -> tuple[str, list[Path], BagMetadata | None, str]:
    """Storage plugin and files of a bag path, its metadata.yaml and why that is None ("" when it is not).

    The one check before anything opens a bag, here or through rosbags (``t42 bag play``, ``t42 view --bag``):
    BagError for a path that is no rosbag2 bag, or a FIFO, directory or device where a file belongs (opening a
    FIFO blocks forever).
    """
    mode = path_mode(bag)
    if stat.S_ISDIR(mode):
        meta, problem = metadata_yaml(bag)
        return (*_storage_files(bag, meta), meta, problem)
    if not stat.S_ISREG(mode):
        raise BagError(bag, f"is {file_kind(mode)}, not a bag directory or storage file")
    if bag.suffix in SUFFIXES:
        return SUFFIXES[bag.suffix], [bag], None, ""
    raise BagError(bag, "is not a rosbag2 bag (expected a bag directory, an .mcap or a .db3 file)")


def is_bag(path: Path) -> bool:
    """Whether ``path`` is a bag directory: a ``metadata.yaml`` or a storage file of its own (a folder of bags
    is not)."""
    return path.is_dir() and ((path / "metadata.yaml").exists() or any(any(path.glob(f"*{s}")) for s in SUFFIXES))


def list_bags(bag_dir: Path) -> list[Path]:
    """Finished bags in ``bag_dir``, by name: non-hidden directories with a ``metadata.yaml``.

    A recorder writes ``metadata.yaml`` when it closes a bag, so the bag being
    recorded is not taken; hidden directories are ``write_bag``'s staging.
    """
    if not bag_dir.is_dir():
        raise ValueError(f"{bag_dir} is not a directory")
    return sorted(p for p in bag_dir.iterdir() if p.is_dir() and not p.name.startswith(".")
                  and (p / "metadata.yaml").is_file())


def load_raw(bag: Path) -> RawBag:
    """The bag's storage files (MCAP scanned record by record, sqlite3 through rosbags) and its metadata.yaml."""
    storage, files, meta, problem = bag_files(bag)
    raw = scan_mcap(files, meta) if storage == "mcap" else _read_sqlite3(bag, files, meta)
    raw.meta, raw.problem = meta, problem
    return raw


def _storage_files(bag: Path, meta: BagMetadata | None) -> tuple[str, list[Path]]:
    """Storage plugin and files of a bag directory: those metadata.yaml lists, else those it holds; all regular."""
    if meta is None:
        for suffix in SUFFIXES:
            files = sorted(bag.glob(f"*{suffix}"))
            if files:
                storage = SUFFIXES[suffix]
                break
        else:
            raise BagError(bag, "is not a rosbag2 bag: no metadata.yaml and no .mcap or .db3 file")
    else:
        if meta.storage not in STORAGES:
            raise BagError(bag, f"has storage {meta.storage!r}; readable storages are {sorted(STORAGES)}")
        if not meta.files:
            raise BagError(bag, "metadata.yaml lists no storage file (relative_file_paths is empty)")
        storage, files = meta.storage, []
        for name in meta.files:
            if name in ("", "..") or "\x00" in name:
                raise BagError(bag, f"metadata.yaml lists {name!r} in relative_file_paths, which names no file")
            if not (bag / name).exists() and not (bag / name).is_symlink():
                raise BagError(bag, f"metadata.yaml lists {name}, which is missing")
            files.append(bag / name)
    for file in files:
        regular_size(bag, file)
    return storage, files


def _add_topic(topics: dict[str, _Topic], topic: str, msgtype: str, count: int, digest: str) -> None:
    """Merge one connection into the topic table; a topic with several types keeps them all for the error."""
    known = topics.setdefault(topic, _Topic(msgtype, 0, digest))
    if msgtype not in known.msgtype.split(" and "):
        known.msgtype = f"{known.msgtype} and {msgtype}"
    known.count += count


def _read_sqlite3(bag: Path, files: list[Path], meta: BagMetadata | None) -> RawBag:
    """A sqlite3 bag through :class:`~.db3.BagReader`, as it is played (its counts and times are SQL over the stored
    messages)."""
    digests = meta.digests if meta else {}
    custom, distro = (meta.custom, meta.ros_distro) if meta else _db3_metadata(files[0])
    try:
        with BagReader(files) as reader:
            topics: dict[str, _Topic] = {}
            for conn in reader.connections:
                _add_topic(topics, conn.topic, conn.msgtype, conn.msgcount, conn.digest or digests.get(conn.topic, ""))
            written = written_names(custom)
            wanted = [c for c in reader.connections if c.topic.endswith(HAND_ROLES) or c.topic in written]
            messages: dict[str, list[tuple[int, bytes]]] = {c.topic: [] for c in wanted}
            if wanted:  # an empty list would mean "every connection"
                for conn, log_ns, data in reader.messages(connections=wanted):
                    messages[conn.topic].append((log_ns, bytes(data)))
            start, end = (0, 0) if reader.message_count == 0 else (reader.start_time, reader.end_time - 1)
            undecodable = reader.undecodable
    except Exception as err:  # rosbags and sqlite3 raise many types on damaged files
        raise BagError(bag, f"rosbags cannot read it ({type(err).__name__}: {err})") from None
    return RawBag("sqlite3", topics, messages, custom, distro, start, end, undecodable=undecodable)


def _db3_metadata(file: Path) -> tuple[dict[str, str], str | None]:
    """custom_data and ros_distro of the metadata copy in a db3's ``metadata`` table (rosbag2 and rosbags write one
    on close, schema 4 on): what a bag without its metadata.yaml still says of itself; none when there is none.

    Opened immutable, as the messages are read: a writer's lock on the file neither stalls nor hides it."""
    uri = f"{file.resolve().as_uri()}?mode=ro&immutable=1"
    try:
        with contextlib.closing(sqlite3.connect(uri, uri=True, timeout=0)) as db:
            if not db.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'metadata'").fetchone():
                return {}, None  # a schema before 4 keeps no copy
            row = db.execute("SELECT metadata FROM metadata ORDER BY rowid DESC LIMIT 1").fetchone()
    except sqlite3.Error as err:
        warnings.warn(f"{file}: the copy of metadata.yaml in its metadata table cannot be read ({err}); its custom "
                      "data (hand, end reasons, remapped hand topics) is lost", stacklevel=2)
        return {}, None
    return serialized_metadata(row[0], file.name) if row and isinstance(row[0], str) else ({}, None)


class _ExactReads:
    """A file view whose reads return all bytes asked for or raise, so a cut-off record is never half-parsed."""

    def __init__(self, stream: BinaryIO, size: int) -> None:
        self._stream, self._size = stream, size

    def read(self, n: int) -> bytes:
        at = self._stream.tell()
        if at + n > self._size:
            raise EOFError(f"a record needs {n} bytes at offset {at}, but the file ends at {self._size}")
        return self._stream.read(n)


def mcap_records(stream: BinaryIO, size: int) -> Iterator[McapRecord]:
    """The records of an MCAP file of ``size`` bytes in file order, chunks opened; raises where it is unreadable.

    No read goes past the file's size and no chunk unpacks beyond its stated size
    (at most :data:`_MAX_CHUNK_BYTES`), so a damaged length cannot allocate more than the file justifies.
    """
    for record in StreamReader(_ExactReads(stream, size), emit_chunks=True, record_size_limit=size).records:
        if isinstance(record, Chunk):
            yield from breakup_chunk(_unpacked(record))
        else:
            yield record


def _unpacked(chunk: Chunk) -> Chunk:
    size = chunk.uncompressed_size
    if chunk.compression in ("zstd", "lz4") and size > _MAX_CHUNK_BYTES:
        raise ValueError(f"a chunk claims {size} bytes unpacked, more than the {_MAX_CHUNK_BYTES} allowed")
    if chunk.compression == "zstd":
        data = zstandard.ZstdDecompressor().stream_reader(io.BytesIO(chunk.data)).read(size + 1)
    elif chunk.compression == "lz4":
        data = lz4.frame.LZ4FrameDecompressor().decompress(chunk.data, max_length=size + 1)
    elif chunk.compression == "":
        data = chunk.data
    else:
        raise ValueError(f"a chunk has unknown compression {chunk.compression!r}")
    if len(data) != size:
        raise ValueError(f"a chunk unpacks to {len(data)} bytes, not the {size} it states")
    return dataclasses.replace(chunk, compression="", data=data)


def scan_mcap(files: list[Path], meta: BagMetadata | None) -> RawBag:
    """Every record of the MCAP ``files`` in file order, up to the first unreadable one.

    Counts and log times are those of the messages read, whatever a summary says.
    Without ``meta``, custom_data comes from rosbag2's own metadata record in the MCAP.
    Each channel's schema is parsed as a sqlite3 bag's definitions are (:class:`~.db3.BagReader`), so a topic not
    decodable from either is named alike.
    """
    topics: dict[str, _Topic] = {}
    undecodable: dict[str, str] = {}
    definitions: list[tuple[str, tuple[MessageDefinition, str, str]]] = []
    """Each channel's topic and (readable definition, type, stored hash), for the check of them all together."""
    messages: dict[str, list[tuple[int, bytes]]] = {}
    digests = meta.digests if meta else {}
    # Without metadata.yaml the names a recorder wrote down come last, in the MCAP's own metadata record:
    # messages of every topic of a hand type are kept until then.
    written, typed = written_names(meta.custom) if meta else set(), set()
    record_meta: tuple[dict[str, str], str | None] | None = None
    log_times: list[int] = []
    stopped, unsummarized = "", []
    for file in files:
        schemas: dict[int, Schema] = {}
        channels: dict[int, str] = {}
        summarized = False
        with file.open("rb") as stream:
            try:
                for record in mcap_records(stream, file.stat().st_size):
                    if isinstance(record, Schema):
                        schemas[record.id] = record
                    elif isinstance(record, Channel):
                        channels[record.id] = record.topic
                        digest = record.metadata.get("topic_type_hash", digests.get(record.topic, ""))
                        schema = schemas.get(record.schema_id)
                        msgtype = "(no schema)" if schema is None else schema.name
                        _add_topic(topics, record.topic, msgtype, 0, digest)
                        msgdef, why = (_NO_DEFINITION, "") if schema is None else readable_definition(
                            stored_definition(schema.encoding, schema.data), msgtype)
                        definitions.append((record.topic, (msgdef, msgtype, digest)))
                        if why:
                            undecodable.setdefault(record.topic, undecodable_line(record.topic, msgtype, why))
                        if msgtype in HAND_TYPES:
                            typed.add(record.topic)
                    elif isinstance(record, Message):
                        topic = channels[record.channel_id]
                        topics[topic].count += 1
                        log_times.append(record.log_time)
                        if topic.endswith(HAND_ROLES) or topic in written or (meta is None and topic in typed):
                            messages.setdefault(topic, []).append((record.log_time, record.data))
                    elif isinstance(record, Metadata) and record.name == "rosbag2" and record_meta is None:
                        record_meta = record_metadata(record)
                    elif isinstance(record, Statistics):
                        summarized = True
            except Exception as err:  # whatever the damage, what was read before it stands
                stopped = f"{file.name} is unreadable from offset {stream.tell()} ({type(err).__name__}: {err})"
                break
        if not summarized:
            unsummarized.append(file.name)
    for received in messages.values():
        received.sort(key=lambda m: m[0])
    for i, why in unhashable_definitions([stored for _, stored in definitions]).items():
        topic, (_, msgtype, _) = definitions[i]
        undecodable.setdefault(topic, undecodable_line(topic, msgtype, why))
    custom, distro = (meta.custom, meta.ros_distro) if meta else record_meta or ({}, None)
    start, end = (min(log_times), max(log_times)) if log_times else (0, 0)
    return RawBag("mcap", topics, messages, custom, distro, start, end, stopped, tuple(unsummarized),
                  undecodable=undecodable)


def metadata_mismatches(bag: Path, meta: BagMetadata, raw: RawBag) -> list[str]:
    """Where ``meta`` (the bag's metadata.yaml) disagrees with the data read from the bag directory's files."""
    found = []
    suffix = next(x for x, s in SUFFIXES.items() if s == raw.storage)
    held = sorted(p.name for p in bag.glob(f"*{suffix}"))
    if sorted(meta.files) != held:
        found.append(f"metadata.yaml lists files {sorted(meta.files)}, the bag holds {held}")
    for name in sorted(set(meta.counts) | set(raw.topics)):
        count = raw.topics[name].count if name in raw.topics else 0
        if name not in meta.counts:
            if count:
                found.append(f"{name}: {count} messages in the data, not listed in metadata.yaml")
        elif meta.counts[name] != count:
            found.append(f"metadata.yaml counts {meta.counts[name]} messages on {name}, the data holds {count}")
    total = sum(t.count for t in raw.topics.values())
    if meta.message_count != total:
        found.append(f"metadata.yaml counts {meta.message_count} messages, the data holds {total}")
    if total and meta.start_ns != raw.start_ns:
        found.append(f"metadata.yaml says the bag starts at {meta.start_ns} ns, its first message is logged at "
                     f"{raw.start_ns} ns")
    if total and meta.duration_ns != raw.end_ns - raw.start_ns:
        found.append(f"metadata.yaml says the bag lasts {meta.duration_ns} ns, its messages span "
                     f"{raw.end_ns - raw.start_ns} ns")
    return found
