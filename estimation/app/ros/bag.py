"""Writing a ROS 2 bag as one MCAP file under coopmap's output rules (docs/results.md), and
reading any ROS bag with one-line errors.

The bag is written by rosbags' rosbag2 writer (MCAP storage) into a hidden folder beside the
target, marked as coopmap's (kind ``mcap``), and its ``.mcap`` file then takes the target's
place in one rename: a failed export leaves the old file as it was. The rosbag2 metadata inside
the file carries ``custom_data: {coopmap: <version>}``; an existing target without it — a file
coopmap did not write — is refused, and so are folders and symbolic links.

Any ROS 1 or ROS 2 bag (MCAP, sqlite3) is read with ``rosbags.highlevel.AnyReader``
(:func:`open_bag`, :func:`bag_messages`); a file that is not a bag, or a damaged one, is one
``EstimationError`` naming the file.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import sqlite3
import struct
import tempfile
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.interfaces import Connection
from rosbags.rosbag1 import ReaderError as Rosbag1Error
from rosbags.rosbag2 import ReaderError as Rosbag2Error
from rosbags.serde import SerdeError

from estimation import __version__
from estimation.app.ros.messages import RosMessages
from estimation.errors import EstimationError
from sensors.atomic import MARKER, remove_leftovers
from sensors.errors import OutputError

__all__ = [
    "BagMessage",
    "bag_messages",
    "check_mcap_replaceable",
    "coopmap_wrote",
    "header_stamp_ns",
    "open_bag",
    "write_mcap",
]

MCAP_MAGIC = b"\x89MCAP0\r\n"
#: A footer record: opcode, length (20), summary start, summary offset start, summary CRC.
_FOOTER = struct.Struct("<BQQQI")
_OP_METADATA, _OP_METADATA_INDEX = 0x0C, 0x0D
#: rosbag2 metadata of a bag of a few hundred topics stays far below this.
_METADATA_LIMIT_BYTES = 16 * 2**20
_KIND = "mcap"
#: What a damaged or foreign file makes rosbags raise while it is opened or read.
_READ_ERRORS = (AnyReaderError, Rosbag1Error, Rosbag2Error, SerdeError, sqlite3.Error,
                struct.error, EOFError, ValueError, KeyError, IndexError, TypeError,
                OverflowError, UnicodeDecodeError, AssertionError, MemoryError)  # fmt: skip


@dataclass(frozen=True)
class BagMessage:
    """One message for the bag: topic, ROS type name, log time (ns) and the message."""

    topic: str
    msgtype: str
    stamp_ns: int
    message: Any
    latched: bool = False


def _string(data: bytes, pos: int) -> tuple[str, int]:
    (size,) = struct.unpack_from("<I", data, pos)
    end = pos + 4 + size
    if end > len(data):
        raise ValueError("string beyond its record")
    return data[pos + 4 : end].decode("utf-8"), end


def _rosbag2_metadata(path: Path) -> str | None:
    """The ``serialized_metadata`` text of an MCAP file's ``rosbag2`` metadata record."""
    with path.open("rb") as f:
        size = f.seek(0, os.SEEK_END)
        if size < 2 * len(MCAP_MAGIC) + _FOOTER.size:
            return None
        f.seek(0)
        if f.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
            return None
        f.seek(size - len(MCAP_MAGIC) - _FOOTER.size)
        footer = f.read(_FOOTER.size + len(MCAP_MAGIC))
        op, length, summary_start, _, _ = _FOOTER.unpack_from(footer)
        if op != 0x02 or length != 20 or footer[_FOOTER.size :] != MCAP_MAGIC:
            return None
        end = size - len(MCAP_MAGIC) - _FOOTER.size
        if not 0 < summary_start <= end or end - summary_start > _METADATA_LIMIT_BYTES:
            return None
        f.seek(summary_start)
        summary = f.read(end - summary_start)
        pos = 0
        while pos + 9 <= len(summary):
            op, length = struct.unpack_from("<BQ", summary, pos)
            body = summary[pos + 9 : pos + 9 + length]
            pos += 9 + length
            if op != _OP_METADATA_INDEX or len(body) < 20:
                continue
            offset, record_length = struct.unpack_from("<QQ", body)
            name, _ = _string(body, 16)
            if name != "rosbag2" or record_length > _METADATA_LIMIT_BYTES:
                continue
            f.seek(offset)
            record = f.read(record_length)
            if len(record) < 9 or record[0] != _OP_METADATA:
                return None
            name, at = _string(record, 9)
            (map_bytes,) = struct.unpack_from("<I", record, at)
            at += 4
            stop = at + map_bytes
            while at < stop:
                key, at = _string(record, at)
                value, at = _string(record, at)
                if key == "serialized_metadata":
                    return value
    return None


def coopmap_wrote(path: Path | str) -> bool:
    """Whether ``path`` is an MCAP bag that coopmap wrote (its rosbag2 metadata says so)."""
    try:
        text = _rosbag2_metadata(Path(path))
        document = yaml.safe_load(text) if text is not None else None
    except (OSError, ValueError, struct.error, UnicodeDecodeError, yaml.YAMLError):
        return False
    if not isinstance(document, dict):
        return False
    info = document.get("rosbag2_bagfile_information", document)
    custom = info.get("custom_data") if isinstance(info, dict) else None
    return isinstance(custom, dict) and "coopmap" in custom


def check_mcap_replaceable(path: Path | str) -> None:
    """Refuse a target that is not a ``.mcap`` name, or exists and is not coopmap's bag."""
    path = Path(path)
    if path.suffix.lower() != ".mcap":
        raise OutputError(f"{path}: an MCAP bag's name must end in .mcap")
    if path.is_symlink():
        raise OutputError(f"{path}: is a symbolic link; refusing to replace it")
    if not path.exists():
        return
    if not path.is_file():
        raise OutputError(f"{path}: exists and is not a file; refusing to replace it")
    if not coopmap_wrote(path):
        raise OutputError(
            f"{path}: exists and is not a bag coopmap wrote; refusing to replace it "
            "(choose another file)"
        )


def write_mcap(path: Path | str, messages: Iterable[BagMessage], ros: RosMessages) -> Path:
    """Write ``messages`` (in log-time order, each topic's in the given order) as one MCAP bag
    at ``path``; returns ``path``."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability
    from rosbags.interfaces import QosTime as T
    from rosbags.rosbag2 import StoragePlugin, Writer

    path = Path(path)
    check_mcap_replaceable(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_leftovers(path, _KIND)
    work = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent))
    infinite = T(0x7FFFFFFF, 0xFFFFFFFF)  # rosbag2's "no limit"
    latched = Qos(
        QosHistory.KEEP_LAST,
        1,
        QosReliability.RELIABLE,
        QosDurability.TRANSIENT_LOCAL,
        infinite,
        infinite,
        QosLiveliness.AUTOMATIC,
        infinite,
        False,
    )
    try:
        (work / MARKER).write_text(json.dumps({"kind": _KIND, "pid": os.getpid()}) + "\n")
        bag = work / path.stem
        ordered = sorted(messages, key=lambda m: m.stamp_ns)
        with Writer(bag, version=Writer.VERSION_LATEST, storage_plugin=StoragePlugin.MCAP) as w:
            w.set_custom_data("coopmap", __version__)
            connections: dict[str, Any] = {}
            for m in ordered:
                if m.topic not in connections:
                    qos = [latched] if m.latched else []
                    connections[m.topic] = w.add_connection(
                        m.topic, m.msgtype, typestore=ros.store, offered_qos_profiles=qos
                    )
                w.write(connections[m.topic], m.stamp_ns, ros.serialize(m.message))
        written = bag / f"{path.stem}.mcap"
        os.chmod(written, 0o666 & ~_umask())
        check_mcap_replaceable(path)  # nothing else moved in while we wrote
        os.replace(written, path)
    finally:
        with contextlib.suppress(OSError):
            shutil.rmtree(work)
    return path


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def open_bag(bag: Path) -> AnyReader:
    """An open reader of a ROS 1 bag, a ROS 2 bag folder or a single ``.mcap``/``.db3`` file
    (close it when done); messages without definitions in the bag use ``RosMessages``' types."""
    if not bag.exists():
        raise EstimationError(f"{bag}: no such file or folder")
    try:
        reader = AnyReader([bag], default_typestore=RosMessages().store)
        reader.open()
    except FileNotFoundError:
        raise EstimationError(
            f"{bag}: not a ROS bag (a rosbag2 folder needs its metadata.yaml)"
        ) from None
    except _READ_ERRORS as exc:
        raise EstimationError(f"{bag}: not a readable ROS bag ({_reason(exc)})") from None
    return reader


def _reason(exc: BaseException) -> str:
    text = " ".join(str(a) for a in exc.args) or type(exc).__name__
    return text if len(text) <= 200 else text[:200] + "…"


def bag_messages(
    reader: AnyReader, connections: list[Connection], bag: Path
) -> Iterator[tuple[Connection, int, Any]]:
    """(connection, log time ns, message) of ``connections`` in log-time order (a topic's
    messages of one log time in the order they were written); a damaged bag is one error, and
    so is a topic of which fewer messages can be read than the bag's index counts."""
    if not connections:
        return
    stream = reader.messages(connections=connections)
    read = dict.fromkeys((c.topic for c in connections), 0)
    while True:
        try:
            connection, log_ns, raw = next(stream)
            message = reader.deserialize(raw, connection.msgtype)
        except StopIteration:
            break
        except _READ_ERRORS as exc:
            raise EstimationError(f"{bag}: corrupt bag ({_reason(exc)})") from None
        read[connection.topic] += 1
        yield connection, log_ns, message
    for topic, n in read.items():
        expected = sum(c.msgcount for c in connections if c.topic == topic)
        if n < expected:
            raise EstimationError(
                f"{bag}: corrupt bag ({topic}: {n:,} of its {expected:,} messages are readable)"
            )


def header_stamp_ns(message: Any, log_ns: int) -> int:
    """A message's header stamp (ns), or ``log_ns`` when the header has none (zero)."""
    stamp = message.header.stamp
    ns = int(stamp.sec) * 10**9 + int(stamp.nanosec)
    return ns if ns > 0 else log_ns
