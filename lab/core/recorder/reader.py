"""Reading a run back: decoded messages in file order and a summary of the run.

The scanner reads records front to back and stops cleanly at the first incomplete or corrupt
record, so it reads a finished file and a file cut short by a kill alike (it never needs the
footer or the summary section).  A chunk counts only if its body is complete and its CRC matches.
Messages are decoded with our own classes for `lab.*` and `foxglove.*` schemas (so
`isinstance(msg, messages.ModuleVerdict)` holds) and with mcap-protobuf-support's decoder for
anything else."""

from __future__ import annotations

import io
import os
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Message, Schema
from mcap.stream_reader import MAGIC_SIZE, breakup_chunk

from lab.core.errors import UserError
from lab.core.recorder import topics

MAGIC = bytes([137, 77, 67, 65, 80, 48, 13, 10])


@dataclass
class ScanState:
    """What a scan found besides the messages: is the file complete, where did it stop."""

    complete: bool = False        # footer and trailing magic present
    data_end: bool = False        # the data section was closed (writer.finish() ran)
    valid_bytes: int = 0          # bytes in complete, intact records (plus the magic at both ends)
    file_bytes: int = 0
    chunks: int = 0
    stop_reason: str = ""         # why the scan stopped early, "" if it reached the footer
    damaged: list[str] = field(default_factory=list)   # salvage: what was skipped, and why
    lost_messages: int = 0        # salvage: messages whose channel definition was lost
    budget_reached: bool = False  # the scan stopped at its byte budget (`max_bytes`), not at the end

    @property
    def dropped_bytes(self) -> int:
        return self.file_bytes - self.valid_bytes

    @property
    def intact(self) -> bool:
        """Complete, and nothing inside was damaged: there is nothing to recover."""
        return self.complete and not self.damaged and not self.lost_messages and self.dropped_bytes == 0


@dataclass(frozen=True)
class RecordedMessage:
    topic: str
    log_time_ns: int
    schema_name: str
    message: Any

    @property
    def t_s(self) -> float:
        return self.log_time_ns * 1e-9


def _open(path: str | os.PathLike[str]) -> io.BufferedReader:
    p = Path(path)
    if not p.is_file():
        raise UserError(f"no such run file: {p}")
    f = open(p, "rb")
    if f.read(MAGIC_SIZE) != MAGIC:
        f.close()
        raise UserError(f"{p} is not an MCAP file (bad magic bytes)")
    return f


_KNOWN_OPCODES = {int(o) for o in Opcode}


def _decode(opcode: int, body: bytes, length: int) -> list[Any]:
    stream = ReadDataStream(io.BytesIO(body))
    if opcode == Opcode.CHUNK:
        return breakup_chunk(Chunk.read(stream), validate_crc=True)
    if opcode == Opcode.SCHEMA:
        return [Schema.read(stream)]
    if opcode == Opcode.CHANNEL:
        return [Channel.read(stream)]
    if opcode == Opcode.MESSAGE:
        return [Message.read(stream, length)]
    return []


def _summary_definitions(f: io.BufferedReader) -> tuple[dict[int, Schema], dict[int, Channel]]:
    """Schemas and channels from the summary section of a file whose footer is intact: with them a
    chunk after a damaged one can be read even if its channels were defined in the damaged one."""
    try:
        from mcap.reader import SeekingReader

        f.seek(0)
        summary = SeekingReader(f, validate_crcs=True).get_summary()
        if summary is None:
            return {}, {}
        return dict(summary.schemas), dict(summary.channels)
    except Exception:
        return {}, {}
    finally:
        f.seek(MAGIC_SIZE)


def _resync(f: io.BufferedReader, start: int, file_bytes: int) -> tuple[int, list[Any]] | None:
    """The next offset at or after `start` where an intact chunk begins (its CRC checked), with
    its records; None if there is none."""
    f.seek(start)
    data = f.read()
    pos = 0
    while True:
        pos = data.find(bytes([Opcode.CHUNK]), pos)
        if pos < 0 or pos + 9 > len(data):
            return None
        length = struct.unpack_from("<Q", data, pos + 1)[0]
        if 0 < length <= len(data) - pos - 9:
            try:
                records = _decode(Opcode.CHUNK, data[pos + 9: pos + 9 + length], length)
                return start + pos, records
            except Exception:
                pass
        pos += 1


def scan_records(path: str | os.PathLike[str], state: ScanState | None = None, *, salvage: bool = False,
                 max_bytes: int | None = None) -> Iterator[tuple[Schema | None, Channel, Message]]:
    """(schema, channel, message) for every complete message in file order; fills `state`.
    `max_bytes`: stop (`state.budget_reached`) before a record that starts beyond it.

    By default the scan stops at the first incomplete or corrupt record (what a reader of a run in
    progress wants).  With `salvage` it skips a corrupt record and carries on at the next intact
    chunk, noting each skip in `state.damaged` (what `lab recover` wants)."""
    st = state if state is not None else ScanState()
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    with _open(path) as f:
        st.file_bytes = os.fstat(f.fileno()).st_size
        st.valid_bytes = MAGIC_SIZE
        if salvage:
            schemas, channels = _summary_definitions(f)
        while True:
            offset = f.tell()
            if max_bytes is not None and offset > max_bytes:
                st.budget_reached = True
                st.stop_reason = f"read the first {offset} of {st.file_bytes} bytes only"
                return
            head = f.read(9)
            if len(head) < 9:
                st.stop_reason = "file ends without a footer" if not head else "file ends inside a record header"
                return
            opcode, length = struct.unpack("<BQ", head)
            problem = ""
            records: list[Any] = []
            body = b""
            if opcode == 0:
                # MCAP reserves opcode 0: zeros where a record should start are a file cut and padded
                # (a crash before the data reached the disk), not records; read as empty ones they
                # took 9 bytes a step through the whole padding
                problem = "zero bytes where a record should start (the file was cut short and padded)"
            elif opcode not in _KNOWN_OPCODES and salvage:
                problem = f"unknown opcode {opcode:#x}"
            elif length > st.file_bytes:
                problem = f"record claims {length} bytes, more than the file holds"
            else:
                body = f.read(length)
                if len(body) < length:
                    st.stop_reason = f"last record (opcode {opcode:#x}) is cut short"
                    if not salvage:
                        return
                    problem = st.stop_reason
                else:
                    try:
                        records = _decode(opcode, body, length)
                    except (McapError, ValueError, struct.error, EOFError) as exc:
                        problem = f"corrupt record (opcode {opcode:#x}): {exc}"
                    except Exception as exc:  # zstd/lz4 errors on a damaged chunk have their own types
                        problem = f"corrupt record (opcode {opcode:#x}): {type(exc).__name__}: {exc}"
            if problem:
                if not salvage:
                    st.stop_reason = problem
                    return
                found = _resync(f, offset + 1, st.file_bytes)
                if found is None:
                    st.damaged.append(f"bytes {offset}-{st.file_bytes} ({st.file_bytes - offset} bytes): {problem}; "
                                      f"no intact chunk after it")
                    st.stop_reason = problem
                    return
                nxt, records = found
                st.damaged.append(f"bytes {offset}-{nxt} ({nxt - offset} bytes): {problem}")
                f.seek(nxt + 1)
                length = struct.unpack("<Q", f.read(8))[0]
                f.seek(nxt + 9 + length)
                opcode = Opcode.CHUNK
            # A record counts as valid only once decoded; messages of a chunk are yielded after it.
            st.valid_bytes += 9 + length
            if opcode == Opcode.CHUNK:
                st.chunks += 1
            for rec in records:
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec
                elif isinstance(rec, Message):
                    channel = channels.get(rec.channel_id)
                    if channel is None:
                        if salvage:
                            st.lost_messages += 1
                            continue
                        st.stop_reason = f"message on unknown channel {rec.channel_id}"
                        return
                    yield schemas.get(channel.schema_id), channel, rec
            if opcode == Opcode.DATA_END:
                st.data_end = True
            if opcode == Opcode.FOOTER:
                st.complete = f.read(MAGIC_SIZE) == MAGIC
                if st.complete:
                    st.valid_bytes += MAGIC_SIZE
                st.stop_reason = "" if st.complete else "footer without trailing magic"
                return


class Decoders:
    """Schema -> decode function, cached per schema id."""

    def __init__(self) -> None:
        self._cache: dict[tuple[int, str], Callable[[bytes], Any]] = {}

    def decoder(self, schema: Schema | None, channel: Channel) -> Callable[[bytes], Any]:
        if schema is None or schema.encoding != "protobuf" or channel.message_encoding != "protobuf":
            return lambda data: data  # not protobuf: hand back the bytes
        key = (schema.id, schema.name)
        fn = self._cache.get(key)
        if fn is None:
            fn = self._cache[key] = self._make(schema, channel)
        return fn

    @staticmethod
    def _make(schema: Schema, channel: Channel) -> Callable[[bytes], Any]:
        if schema.name.startswith(("lab.", "foxglove.")):
            from google.protobuf import descriptor_pool, message_factory

            try:
                cls = message_factory.GetMessageClass(descriptor_pool.Default().FindMessageTypeByName(schema.name))
                return cls.FromString
            except KeyError:
                pass  # a foxglove type whose module is not imported yet, or a newer lab type
            if schema.name.startswith("foxglove."):
                import importlib

                try:
                    mod = importlib.import_module(f"foxglove_schemas_protobuf.{schema.name.split('.')[1]}_pb2")
                    return getattr(mod, schema.name.split(".")[1]).FromString
                except (ImportError, AttributeError):
                    pass
        from mcap_protobuf.decoder import DecoderFactory

        fn = DecoderFactory().decoder_for(channel.message_encoding, schema)
        if fn is None:
            raise McapError(f"no protobuf decoder for schema {schema.name}")
        return fn


def iter_messages(path: str | os.PathLike[str], topics_: Iterable[str] | str | None = None,
                  state: ScanState | None = None, max_bytes: int | None = None) -> Iterator[RecordedMessage]:
    """Decoded messages of a run (complete or cut short), in file order, optionally only `topics_`
    (`max_bytes`: as for `scan_records`)."""
    wanted = {topics_} if isinstance(topics_, str) else (set(topics_) if topics_ is not None else None)
    decoders = Decoders()
    for schema, channel, msg in scan_records(path, state, max_bytes=max_bytes):
        if wanted is not None and channel.topic not in wanted:
            continue
        decoded = decoders.decoder(schema, channel)(msg.data)
        yield RecordedMessage(channel.topic, msg.log_time, schema.name if schema else "", decoded)


@dataclass
class RunSummary:
    start: Any = None                      # lab.RunStart or None
    stop: Any = None                       # lab.RunStop or None (killed run)
    steps_completed: list[tuple[int, str]] = field(default_factory=list)   # (index, name) with an end record
    steps_failed: list[tuple[int, str, str]] = field(default_factory=list)  # (index, name, error)
    interrupted_step: tuple[int, str] | None = None  # started, never ended (killed inside it)
    message_count: int = 0
    topic_counts: dict[str, int] = field(default_factory=dict)
    scan: ScanState = field(default_factory=ScanState)

    @property
    def result(self) -> str:
        """completed | aborted | failed, or "unknown" when the file has no stop record."""
        return self.stop.result if self.stop is not None else "unknown"

    @property
    def params(self) -> dict[str, Any]:
        import json

        return json.loads(self.start.params_json or "{}") if self.start is not None else {}


def read_summary(path: str | os.PathLike[str]) -> RunSummary:
    """Start and stop records, steps completed/failed/interrupted and message counts of a run."""
    s = RunSummary()
    open_steps: dict[int, str] = {}
    for rec in iter_messages(path, state=s.scan):
        s.message_count += 1
        s.topic_counts[rec.topic] = s.topic_counts.get(rec.topic, 0) + 1
        if rec.topic == topics.RUN_START:
            s.start = rec.message
        elif rec.topic == topics.RUN_STOP:
            s.stop = rec.message
        elif rec.topic == topics.RUN_STEP:
            ev = rec.message
            if ev.phase == "start":
                open_steps[ev.index] = ev.name
            elif ev.phase == "end":
                open_steps.pop(ev.index, None)
                s.steps_completed.append((ev.index, ev.name))
            elif ev.phase == "error":
                open_steps.pop(ev.index, None)
                s.steps_failed.append((ev.index, ev.name, ev.error))
    if open_steps:
        idx = max(open_steps)
        s.interrupted_step = (idx, open_steps[idx])
    return s


__all__ = ["RecordedMessage", "RunSummary", "ScanState", "iter_messages", "read_summary", "scan_records"]
