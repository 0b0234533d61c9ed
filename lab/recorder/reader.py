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

from lab.errors import UserError
from lab.recorder import topics

MAGIC = bytes([137, 77, 67, 65, 80, 48, 13, 10])


@dataclass
class ScanState:
    """What a scan found besides the messages: is the file complete, where did it stop."""

    complete: bool = False        # footer and trailing magic present
    data_end: bool = False        # the data section was closed (writer.finish() ran)
    valid_bytes: int = 0          # bytes up to the end of the last complete record
    file_bytes: int = 0
    chunks: int = 0
    stop_reason: str = ""         # why the scan stopped early, "" if it reached the footer

    @property
    def dropped_bytes(self) -> int:
        return self.file_bytes - self.valid_bytes


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


def scan_records(path: str | os.PathLike[str], state: ScanState | None = None
                 ) -> Iterator[tuple[Schema | None, Channel, Message]]:
    """(schema, channel, message) for every complete message in file order; fills `state`."""
    st = state if state is not None else ScanState()
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    with _open(path) as f:
        st.file_bytes = os.fstat(f.fileno()).st_size
        st.valid_bytes = MAGIC_SIZE
        while True:
            head = f.read(9)
            if len(head) < 9:
                st.stop_reason = "file ends without a footer" if not head else "file ends inside a record header"
                return
            opcode, length = struct.unpack("<BQ", head)
            if length > st.file_bytes:
                st.stop_reason = f"record claims {length} bytes, more than the file holds"
                return
            body = f.read(length)
            if len(body) < length:
                st.stop_reason = f"last record (opcode {opcode:#x}) is cut short"
                return
            records: list[Any]
            try:
                stream = ReadDataStream(io.BytesIO(body))
                if opcode == Opcode.CHUNK:
                    records = breakup_chunk(Chunk.read(stream), validate_crc=True)
                    st.chunks += 1
                elif opcode == Opcode.SCHEMA:
                    records = [Schema.read(stream)]
                elif opcode == Opcode.CHANNEL:
                    records = [Channel.read(stream)]
                elif opcode == Opcode.MESSAGE:
                    records = [Message.read(stream, length)]
                else:
                    records = []
            except (McapError, ValueError, struct.error, EOFError) as exc:
                st.stop_reason = f"corrupt record (opcode {opcode:#x}): {exc}"
                return
            except Exception as exc:  # zstd/lz4 errors on a damaged chunk have their own types
                st.stop_reason = f"corrupt record (opcode {opcode:#x}): {type(exc).__name__}: {exc}"
                return
            # A record counts as valid only once decoded; messages of a chunk are yielded after it.
            st.valid_bytes += 9 + length
            for rec in records:
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec
                elif isinstance(rec, Message):
                    channel = channels.get(rec.channel_id)
                    if channel is None:
                        st.stop_reason = f"message on unknown channel {rec.channel_id}"
                        return
                    yield schemas.get(channel.schema_id), channel, rec
            if opcode == Opcode.DATA_END:
                st.data_end = True
            if opcode == Opcode.FOOTER:
                st.complete = f.read(MAGIC_SIZE) == MAGIC
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
                  state: ScanState | None = None) -> Iterator[RecordedMessage]:
    """Decoded messages of a run (complete or cut short), in file order, optionally only `topics_`."""
    wanted = {topics_} if isinstance(topics_, str) else (set(topics_) if topics_ is not None else None)
    decoders = Decoders()
    for schema, channel, msg in scan_records(path, state):
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
