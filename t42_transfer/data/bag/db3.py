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
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

from rosbags.highlevel import AnyReader
from rosbags.interfaces import Connection, ConnectionExtRosbag2, MessageDefinition, MessageDefinitionFormat
from rosbags.rosbag2 import Reader, ReaderError
from rosbags.rosbag2.metadata import ReaderMetadata, parse_qos
from rosbags.rosbag2.reader import DirectoryReader
from rosbags.rosbag2.storage_sqlite3 import Sqlite3Reader

import msg_adapters as ma
from t42_transfer.data.bag.idl import rosbags_idl

_FORMATS = {"ros2msg": MessageDefinitionFormat.MSG, "ros2idl": MessageDefinitionFormat.IDL}
_NO_DEFINITION = MessageDefinition(MessageDefinitionFormat.NONE, "")
_NO_TIMES = (0, 2**63 - 1, 0)
"""rosbags' duration, start and end of a storage without messages."""


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
                known = _FORMATS.get(encoding)
                definitions.setdefault(msgtype, _NO_DEFINITION if known is None else MessageDefinition(known, text))
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
        """Open the storage; its IDL definitions in the form rosbags parses (``AnyReader`` parses them next)."""
        super().open()
        self.storage.connections = [_readable(conn) for conn in self.storage.connections]


def _readable(conn: Connection) -> Connection:
    """``conn`` with an IDL definition as rosbags parses it (the messages are matched by id, topic and type, never
    by definition)."""
    if conn.msgdef.format != MessageDefinitionFormat.IDL:
        return conn
    return conn._replace(msgdef=MessageDefinition(MessageDefinitionFormat.IDL,
                                                  rosbags_idl(conn.msgdef.data, conn.msgtype)))


class BagReader(AnyReader):
    """rosbags' ``AnyReader`` of rosbag2 ``paths`` (a bag directory, or its storage files), sqlite3 files read by
    :class:`_Db3`; types the bag does not define come from the project's typestore."""

    def __init__(self, paths: Sequence[Path]) -> None:
        super().__init__(paths, default_typestore=ma.TYPESTORE)
        self.readers = [_Reader(path) for path in paths]
