"""The one rosbags reader every bag is opened with, its sqlite3 storage taking a topic stored without a definition,
and a topic of an IDL-defined type read from its definition as rosbag2 stores it.

``ros2 bag record`` stores a topic whose ``.msg`` it cannot find with an empty message definition (encoding
``""``); rosbags 0.11's sqlite3 storage has no entry for that encoding and refuses the whole bag (``KeyError: ''``),
while its MCAP storage takes such a schema as definition-less.  :class:`BagReader` is rosbags' ``AnyReader`` whose
sqlite3 files are opened by :class:`_Db3`: it lists a file's connections from its ``topics`` and
``message_definitions`` tables itself, a definition of no known encoding given as none (that topic is not
decodable from the bag, and the hand never needs it), and leaves opening, messages and closing to rosbags.

rosbag2 stores an IDL definition with ``#include`` lines (and a vendor's include guards), which rosbags' IDL parser
refuses, and ``AnyReader`` the whole bag with it ("Could not parse"): every storage's IDL definitions are given to
rosbags as :func:`~.idl.rosbags_idl` gives them, those lines comments, so such a topic decodes from the bag.

``AnyReader`` parses every definition it is given (of a type the project's typestore knows too), and refuses the
whole bag over one it cannot parse (a definition cut off, or otherwise malformed, in a ``ros2 bag record -a`` of
topics the hand never needs), or whose types do not give the type hash stored with it (a type it uses missing, or
another hash).  :func:`readable_definition` parses each first, as ``AnyReader`` will, and gives one
that it would refuse as none: that topic is not decodable from the bag, like one stored without a definition.
:attr:`BagReader.undecodable` says which and why, for its users to warn of (the reader says nothing itself).
"""

from __future__ import annotations

import functools
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from rosbags.highlevel import AnyReader
from rosbags.interfaces import Connection, ConnectionExtRosbag2, MessageDefinition, MessageDefinitionFormat
from rosbags.rosbag2 import Reader, ReaderError
from rosbags.rosbag2.metadata import ReaderMetadata, parse_qos
from rosbags.rosbag2.reader import DirectoryReader
from rosbags.rosbag2.storage_sqlite3 import Sqlite3Reader
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

import msg_adapters as ma
from t42_transfer.data.bag.idl import idl_types, rosbags_idl

_FORMATS = {"ros2msg": MessageDefinitionFormat.MSG, "ros2idl": MessageDefinitionFormat.IDL}
_NO_DEFINITION = MessageDefinition(MessageDefinitionFormat.NONE, "")
_NO_TIMES = (0, 2**63 - 1, 0)
"""rosbags' duration, start and end of a storage without messages."""
_SHOWN = 40
"""At most this much of the text where parsing stopped is quoted in why a definition cannot be parsed."""


class _Db3(Sqlite3Reader):
    """rosbags' sqlite3 storage; its connections read here, so an empty definition is no definition, not an error."""

    def _open(self) -> None:
        """Connections and times of the open database (rosbags' ``open`` calls this once it is connected)."""
        db = self.dbconn
        assert db is not None, "_open() of a storage that is not connected"
        tables = {row[0] for row in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        if not {"topics", "messages"} <= tables:
            raise ReaderError(f"{self.path} is no rosbag2 database: it lacks the topics or messages table")
        columns = {row[1] for row in db.execute("PRAGMA table_info(topics)")}
        # the columns older schemas lack: QoS came in Foxy's schema 2, type hashes in Iron's schema 4
        qos = "offered_qos_profiles" if "offered_qos_profiles" in columns else "''"
        digest = "type_description_hash" if "type_description_hash" in columns else "''"
        definitions = {}
        if "message_definitions" in tables:
            for msgtype, encoding, text in db.execute(
                    "SELECT topic_type, encoding, encoded_message_definition FROM message_definitions ORDER BY id"):
                definitions.setdefault(msgtype, stored_definition(encoding, text))
        self.connections = [
            Connection(cid, topic, msgtype, definitions.get(msgtype, _NO_DEFINITION), rihs01 or "", count,
                       ConnectionExtRosbag2(serialization, parse_qos(offered) if offered else []), self)
            for cid, topic, msgtype, count, serialization, offered, rihs01 in db.execute(
                f"SELECT topics.id, name, type, count(messages.id), serialization_format, {qos}, {digest} "
                "FROM topics LEFT JOIN messages ON topics.id = messages.topic_id GROUP BY topics.id ORDER BY topics.id")
        ]
        first, last, count = next(iter(db.execute("SELECT MIN(timestamp), MAX(timestamp), COUNT(*) FROM messages")))
        duration, start, end = _NO_TIMES if first is None else (last + 1 - first, first, last + 1)
        self.metadata = ReaderMetadata(duration, start, end, count, None, None, None, None)


class _Directory(DirectoryReader):
    STORAGE_PLUGINS: Mapping = {**DirectoryReader.STORAGE_PLUGINS, "sqlite3": _Db3}


class _Reader(Reader):
    STORAGE_PLUGINS: Mapping = {**Reader.STORAGE_PLUGINS, "dir": _Directory, ".db3": _Db3}

    def open(self) -> None:
        """Open the storage; its definitions as :func:`readable_definition` gives them (``AnyReader`` parses them
        next), and :attr:`undecodable` the topics whose definition does not parse."""
        self.undecodable: dict[str, str] = {}
        """Why each topic whose stored definition does not parse is not decodable from the bag, a line each."""
        super().open()
        connections = []
        for conn in self.storage.connections:  # (messages are matched by id, topic and type, never by definition)
            msgdef, why = readable_definition(conn.msgdef, conn.msgtype)
            if why:
                self.undecodable.setdefault(conn.topic, undecodable_line(conn.topic, conn.msgtype, why))
            connections.append(conn._replace(msgdef=msgdef))
        for i, why in unhashable_definitions([(c.msgdef, c.msgtype, c.digest) for c in connections]).items():
            conn = connections[i]
            self.undecodable.setdefault(conn.topic, undecodable_line(conn.topic, conn.msgtype, why))
            connections[i] = conn._replace(msgdef=_NO_DEFINITION)
        self.storage.connections = connections


@functools.lru_cache(maxsize=256)  # the same definitions come in bag after bag, and each time a bag is opened
def readable_definition(msgdef: MessageDefinition, msgtype: str) -> tuple[MessageDefinition, str]:
    """``msgdef``, a stored definition of ``msgtype``, as rosbags' ``AnyReader`` is given it (an IDL one as
    :func:`~.idl.rosbags_idl` gives it) and ""; or no definition and why ``msgdef`` cannot be parsed, one line.

    Parsed as ``AnyReader`` parses it: a ``.msg`` one by rosbags' ``get_types_from_msg``, an IDL one by
    :func:`~.idl.idl_types`.  The stored hashes are checked for all of a bag's definitions together
    (:func:`unhashable_definitions`), as ``AnyReader`` checks them."""
    if msgdef.format == MessageDefinitionFormat.NONE:
        return msgdef, ""
    try:
        msgdef, _ = parsed_definition(msgdef, msgtype)
    except Exception as err:  # rosbags raises many types for what it cannot parse
        return _NO_DEFINITION, f"its stored definition cannot be parsed ({_short(err)})"
    return msgdef, ""


def parsed_definition(msgdef: MessageDefinition, msgtype: str) -> tuple[MessageDefinition, dict[str, Any]]:
    """``msgdef`` (a ``.msg`` or IDL definition of ``msgtype``) as rosbags is given it, an IDL one as
    :func:`~.idl.rosbags_idl` gives it, and the types it defines, parsed as ``AnyReader`` parses them; rosbags raises
    what it cannot parse.  For reading a bag (:func:`readable_definition`) and for repairing one."""
    if msgdef.format == MessageDefinitionFormat.IDL:
        msgdef = MessageDefinition(MessageDefinitionFormat.IDL, rosbags_idl(msgdef.data, msgtype))
        return msgdef, idl_types(msgdef.data)
    return msgdef, get_types_from_msg(msgdef.data, msgtype)


CLASHING = ("its stored definition gives a type it uses otherwise than another topic's definition does, and the two "
            "do not hash together")
"""Why a topic is not decodable when its definition hashes right alone but not with the bag's others."""


def unhashable_definitions(stored: Sequence[tuple[MessageDefinition, str, str]]) -> dict[int, str]:
    """Which of a bag's ``(definition, type, stored hash)`` (readable definitions, as :func:`readable_definition` gives
    them) ``AnyReader`` would refuse the bag over, and why: it registers every definition in one store, where a type
    two definitions give differently (two installs of a package) takes the later one, then checks each stored hash
    (RIHS01), refusing the bag over a type no definition gives or another hash.  Those found are left out and the rest
    checked again, as reading the bag without them would."""
    return dict(_unhashable(tuple(stored)))


@functools.lru_cache(maxsize=64)  # bags of one recorder hold the same definitions: the check is 20 ms a bag
def _unhashable(stored: tuple[tuple[MessageDefinition, str, str], ...]) -> tuple[tuple[int, str], ...]:
    dropped: dict[int, str] = {}
    while True:
        kept = [i for i, (msgdef, _, _) in enumerate(stored)
                if i not in dropped and msgdef.format != MessageDefinitionFormat.NONE]
        store = _store(stored[i][:2] for i in kept)
        if store is None:  # rosbags says why when it opens the bag
            return tuple(sorted(dropped.items()))
        found = {i: why for i in kept if stored[i][2] and (why := _hash_problem(store, *stored[i]))}
        if not found:
            return tuple(sorted(dropped.items()))
        dropped.update(found)


def _store(definitions: Iterable[tuple[MessageDefinition, str]]) -> Any:
    """A typestore of ``definitions`` registered as ``AnyReader`` registers them (a later one of a type replaces an
    earlier), or None when rosbags refuses them together."""
    types: dict[str, Any] = {}
    for msgdef, msgtype in definitions:
        types.update(parsed_definition(msgdef, msgtype)[1])
    store = get_typestore(Stores.EMPTY)
    try:
        store.register(types)
    except Exception:
        return None
    return store


def _hash_problem(store: Any, msgdef: MessageDefinition, msgtype: str, digest: str) -> str:
    """Why ``msgtype`` does not hash to ``digest`` in ``store``, the bag's definitions together; "" when it does."""
    try:
        if store.hash_rihs01(msgtype) == digest:
            return ""
    except Exception as err:  # KeyError: a type it uses that no definition gives
        return f"its stored definition uses a type no definition in the bag gives ({_short(err)})"
    alone = _store([(msgdef, msgtype)])
    try:
        have = "" if alone is None else alone.hash_rihs01(msgtype)
    except Exception:  # a type it uses that only another definition gives
        have = ""
    if have == digest:
        return CLASHING
    return f"its stored definition hashes to {have[:15] or 'another hash'}..., not to its stored {digest[:15]}..."


def stored_definition(encoding: str, text: str | bytes) -> MessageDefinition:
    """The definition stored with ``encoding`` (rosbag2's ``ros2msg`` or ``ros2idl``; any other is none)."""
    known = _FORMATS.get(encoding)
    if known is None:
        return _NO_DEFINITION
    return MessageDefinition(known, text.decode(errors="replace") if isinstance(text, bytes) else text)


def undecodable_line(topic: str, msgtype: str, why: str) -> str:
    """What a warning says of ``topic`` (of ``msgtype``), not decodable from the bag for ``why``."""
    return f"{topic} ({msgtype}) is not decodable from the bag: {why}"


def _short(err: Exception) -> str:
    """``err``'s type and message, one short line.  rosbags' parse error quotes the whole definition, then the
    offset and the text from there: it is said as where parsing stopped."""
    lines = str(err).splitlines() or [""]
    text = "".join(c if c.isprintable() else "?" for c in lines[0].rstrip(":"))[:100]
    if len(lines) > 3 and lines[2].strip().isdigit() and lines[3].strip():
        text += f" at {lines[3].strip()[:_SHOWN]!r}"
    return f"{type(err).__name__}: {text}"


class BagReader(AnyReader):
    """rosbags' ``AnyReader`` of rosbag2 ``paths`` (a bag directory, or its storage files), sqlite3 files read by
    :class:`_Db3`; types the bag does not define come from the project's typestore."""

    def __init__(self, paths: Sequence[Path]) -> None:
        super().__init__(paths, default_typestore=ma.TYPESTORE)
        self.readers = [_Reader(path) for path in paths]

    @property
    def undecodable(self) -> dict[str, str]:
        """Of the open bag, why each topic whose stored definition does not parse is not decodable from it (a line
        each, for a warning); those topics read as if stored without a definition."""
        lines: dict[str, str] = {}
        for reader in self.readers:
            for topic, line in getattr(reader, "undecodable", {}).items():
                lines.setdefault(topic, line)
        return lines
