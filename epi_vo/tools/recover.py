"""``epi-vo recover``: make the ``output.mcap`` of a killed replay readable again.

A replay killed without the chance to finalise (SIGKILL, the OOM killer, a power cut) leaves an
``output.mcap`` without its summary section and end magic: no reader opens it ("File end magic is
invalid"). Its data section is still a run of complete chunks (the replay closes one every
``OUTPUT_FLUSH_FRAMES`` frames, :mod:`epi_vo.tools.replay_outputs`) and perhaps a last one cut short.
:func:`recover_bag` reads the file from its start record by record (CRCs checked), keeps every schema,
channel and message up to the first record that is cut or damaged, and writes them into a new file with a
summary. The damaged file is never modified: it is renamed to ``output.mcap.damaged`` and the recovered
one takes its name, so ``epi-vo report`` and any ROS 2 tool read it as usual.

A directory whose ``output.mcap`` is complete is left as it is; one whose rename happened but not the
second (a crash during recover) is recovered from ``output.mcap.damaged``.
"""

from __future__ import annotations

import argparse
import collections
import os
import struct
import sys
from dataclasses import dataclass
from pathlib import Path

from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Header, Message, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter

from epi_vo.core.errors import OutputError
from epi_vo.io.paths import special_file_kind
from epi_vo.tools.fleet_summary import find_output_dirs
from epi_vo.tools.replay_outputs import DAMAGED_BAG, FRAMES_FILE, OUTPUT_BAG, os_reason

# What reading a cut or damaged MCAP can raise: the library's own errors (EndOfFile, CRC, record length),
# and the struct / decompression errors of a record whose bytes are cut in the middle.
_READ_ERRORS = (McapError, ValueError, struct.error, EOFError, OSError, KeyError)


@dataclass(frozen=True)
class Recovery:
    """What ``epi-vo recover`` did in one replay directory."""

    directory: Path
    recovered: bool  # False: output.mcap was complete, nothing done
    messages: dict[str, int]  # messages kept per topic
    last_log_time_ns: int | None  # of the last message kept
    stopped_at: str  # why reading stopped ('' when the file ended cleanly)
    frames_records: int  # lines in frames.jsonl (every frame written)

    def line(self) -> str:
        d = self.directory
        if not self.recovered:
            return f"{d}: {OUTPUT_BAG} is complete, nothing to recover"
        total = sum(self.messages.values())
        topics = ", ".join(f"{t} {n}" for t, n in sorted(self.messages.items())) or "none"
        until = "" if self.last_log_time_ns is None else f" up to log time {self.last_log_time_ns * 1e-9:.6f} s"
        return (f"{d}: recovered {total} messages of {OUTPUT_BAG}{until} ({topics}); {FRAMES_FILE} holds "
                f"{self.frames_records} frame records; the damaged file is kept as {DAMAGED_BAG}"
                + (f"; reading stopped at {self.stopped_at}" if self.stopped_at else ""))


def is_complete(path: Path) -> bool:
    """Whether an MCAP file has its summary and end magic (a reader can open it)."""
    try:
        with path.open("rb") as f:
            return make_reader(f).get_summary() is not None
    except _READ_ERRORS:
        return False


def _readable_prefix(path: Path) -> tuple[Header | None, list[Schema], list[Channel], list[Message], str]:
    """The header, schemas, channels and messages of ``path`` up to its first cut or damaged record, and
    where and why reading stopped ('' at a clean end)."""
    header: Header | None = None
    schemas: list[Schema] = []
    channels: list[Channel] = []
    messages: list[Message] = []
    size = path.stat().st_size
    with path.open("rb") as f:
        reader = StreamReader(f, validate_crcs=True, record_size_limit=max(size, 1))
        try:
            for record in reader.records:
                if isinstance(record, Header):
                    header = record
                elif isinstance(record, Schema):
                    schemas.append(record)
                elif isinstance(record, Channel):
                    channels.append(record)
                elif isinstance(record, Message):
                    messages.append(record)
        except _READ_ERRORS as exc:
            why = f"{type(exc).__name__}: {exc}" if str(exc) else "the file ends inside a record"
            return header, schemas, channels, messages, f"byte {f.tell()} of {size} ({why})"
    return header, schemas, channels, messages, ""


def recover_bag(source: Path, target: Path) -> tuple[dict[str, int], int | None, str]:
    """Write the readable prefix of ``source`` (see module doc) into a new MCAP file ``target``; the messages
    kept per topic, the log time of the last one and why reading stopped. OutputError when ``source`` is no
    MCAP file at all."""
    header, schemas, channels, messages, stopped = _readable_prefix(source)
    if header is None:
        raise OutputError(f"{source} is not an MCAP file (no header: {stopped or 'empty'})")
    counts: collections.Counter[str] = collections.Counter()
    with target.open("wb") as stream:
        writer = McapWriter(stream, compression=CompressionType.ZSTD)
        writer.start(profile=header.profile, library=header.library)
        schema_ids = {s.id: writer.register_schema(name=s.name, encoding=s.encoding, data=s.data) for s in schemas}
        channel_ids = {}
        topics = {}
        for c in channels:
            channel_ids[c.id] = writer.register_channel(topic=c.topic, message_encoding=c.message_encoding,
                                                        schema_id=schema_ids.get(c.schema_id, 0),
                                                        metadata=dict(c.metadata))
            topics[c.id] = c.topic
        last = None
        for m in messages:
            if m.channel_id not in channel_ids:
                continue  # a message whose channel record was lost: nothing can read it
            writer.add_message(channel_ids[m.channel_id], log_time=m.log_time, data=m.data,
                               publish_time=m.publish_time, sequence=m.sequence)
            counts[topics[m.channel_id]] += 1
            last = m.log_time
        writer.finish()
        stream.flush()
        os.fsync(stream.fileno())
    return dict(counts), last, stopped


def recover_directory(directory: Path) -> Recovery:
    """Recover the output.mcap of one replay directory (see module doc); OutputError naming the problem when
    it cannot be."""
    bag, damaged = directory / OUTPUT_BAG, directory / DAMAGED_BAG
    for path in (bag, damaged):
        kind = special_file_kind(path)
        if kind is not None:
            raise OutputError(f"{path} is a {kind}, not an MCAP file: refused")
    frames = _count_lines(directory / FRAMES_FILE)
    if bag.is_file() and is_complete(bag):
        return Recovery(directory, False, {}, None, "", frames)
    if bag.is_file():
        if damaged.exists():
            raise OutputError(f"{damaged} exists already: move it away to recover {bag} again")
        source = bag
    elif damaged.is_file():
        source = damaged  # a recover that stopped between its two renames
    else:
        raise OutputError(f"{directory} has no {OUTPUT_BAG} to recover")
    tmp = directory / f".{OUTPUT_BAG}.recovering"
    try:
        counts, last, stopped = recover_bag(source, tmp)
        if source == bag:
            os.rename(bag, damaged)
        os.replace(tmp, bag)
    except OSError as exc:
        raise OutputError(f"cannot recover {source}: {os_reason(exc)}") from None
    finally:
        tmp.unlink(missing_ok=True)
    return Recovery(directory, True, counts, last, stopped, frames)


def _count_lines(path: Path) -> int:
    try:
        with path.open("rb") as f:
            return sum(1 for line in f if line.endswith(b"\n"))
    except OSError:
        return 0


def run(args: argparse.Namespace) -> int:
    """``epi-vo recover DIR...``: one line per replay directory; exit status 0 when every one is readable
    now, 2 when one could not be recovered (its line says why)."""
    failed = 0
    for directory in find_output_dirs(args.dirs):
        try:
            print(recover_directory(directory).line(), flush=True)
        except OutputError as exc:
            failed += 1
            print(f"epi-vo: error: {exc}", file=sys.stderr, flush=True)
    return 2 if failed else 0
