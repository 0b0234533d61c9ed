"""Rewrite a run file left without its footer (killed writer, power loss) or damaged inside (bad
sectors, a stray write) into a complete MCAP.

Every intact record is kept: schemas and channels as they were, messages in file order with their
original times.  A corrupt record does not end the salvage: the scan carries on at the next chunk
whose CRC checks, so one damaged chunk costs only its own messages.  A file that is complete and
intact is left alone (nothing is written).  A file with no stop record gets one, marked `recovered`, with result "failed" and
a reason saying the recording ended without one, so every recovered run still ends in a stop
record and `steps_completed` tells how far it got."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from mcap.writer import CompressionType, Writer as McapWriter

from lab.core.errors import UserError
from lab.core.recorder import messages as m
from lab.core.recorder import topics
from lab.core.recorder.reader import Decoders, ScanState, scan_records


@dataclass(frozen=True)
class RecoverReport:
    path_out: Path
    messages: int            # messages written to path_out (without an added stop record)
    steps_completed: int     # step end records kept
    interrupted_step: str    # "index name" of a step started and never ended, "" if none
    had_stop: bool           # the input already had a stop record
    was_complete: bool       # the input already had its footer
    dropped_bytes: int       # bytes not in any intact record (a cut-off tail, damaged chunks)
    stop_reason: str         # why the scan of the input stopped ("" = reached the footer)
    damaged: tuple[str, ...] = ()   # damaged stretches skipped, with why
    lost_messages: int = 0          # messages dropped because their channel definition was lost
    intact: bool = False            # complete and undamaged: nothing was written


def default_output(path_in: str | os.PathLike[str]) -> Path:
    """RUN.mcap -> RUN.recovered.mcap"""
    p = Path(path_in)
    stem = p.name[:-5] if p.name.endswith(".mcap") else p.name
    return p.with_name(stem + ".recovered.mcap")


def recover(path_in: str | os.PathLike[str], path_out: str | os.PathLike[str] | None = None, *,
            overwrite: bool = False) -> RecoverReport:
    src = Path(path_in)
    dst = Path(path_out) if path_out is not None else default_output(src)
    check = ScanState()
    steps_seen = 0
    decoders0 = Decoders()
    for schema, channel, msg in scan_records(src, check, salvage=True):
        if channel.topic == topics.RUN_STEP and decoders0.decoder(schema, channel)(msg.data).phase == "end":
            steps_seen += 1
    if check.intact:
        return RecoverReport(src, 0, steps_seen, "", True, True, 0, "", (), 0, intact=True)
    if src.resolve() == dst.resolve():
        raise UserError(f"recover writes a new file; output {dst} is the input")
    if dst.exists() and not overwrite:
        raise UserError(f"output {dst} already exists; pass another -o or remove it")
    state = ScanState()
    decoders = Decoders()
    schema_map: dict[int, int] = {}
    channel_map: dict[int, int] = {}
    messages = steps = 0
    had_stop = False
    last_ns = 0
    open_steps: dict[int, str] = {}
    tmp = dst.with_name(dst.name + ".part")
    with open(tmp, "wb") as f:
        writer = McapWriter(f, compression=CompressionType.ZSTD)
        writer.start(profile="", library="lab.recorder.recover")
        for schema, channel, msg in scan_records(src, state, salvage=True):
            if schema is not None and schema.id not in schema_map:
                schema_map[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channel_map:
                channel_map[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding,
                    schema_map.get(channel.schema_id, 0), dict(channel.metadata))
            writer.add_message(channel_map[channel.id], msg.log_time, msg.data, msg.publish_time, msg.sequence)
            messages += 1
            last_ns = max(last_ns, msg.log_time)
            if channel.topic == topics.RUN_STOP:
                had_stop = True
            elif channel.topic == topics.RUN_STEP:
                ev = decoders.decoder(schema, channel)(msg.data)
                if ev.phase == "start":
                    open_steps[ev.index] = ev.name
                else:
                    open_steps.pop(ev.index, None)
                    steps += ev.phase == "end"
        if messages == 0 and not state.complete:
            f.close()
            tmp.unlink()
            raise UserError(f"{src} holds no complete message to recover ({state.stop_reason})")
        interrupted = ""
        if open_steps:
            i = max(open_steps)
            interrupted = f"{i} {open_steps[i]}"
        if not had_stop:
            reason = (f"recording ended without a stop record ({state.stop_reason or 'no stop written'}); "
                      f"recovered by lab recover")
            if interrupted:
                reason += f"; step {interrupted} was running"
            stop = m.RunStop(stop_time=m.timestamp((last_ns + 1) / 1e9), result="failed", reason=reason,
                             steps_completed=steps, recovered=True,
                             last_step=interrupted + " (unfinished)" if interrupted else "")
            stop_channel = _stop_channel(writer, schema_map, channel_map)
            writer.add_message(stop_channel, last_ns + 1, stop.SerializeToString(), last_ns + 1)
        writer.finish()
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, dst)
    return RecoverReport(dst, messages, steps, interrupted, had_stop, state.complete, state.dropped_bytes,
                         state.stop_reason, tuple(state.damaged), state.lost_messages)


def _stop_channel(writer: McapWriter, schema_map: dict[int, int], channel_map: dict[int, int]) -> int:
    from mcap_protobuf.schema import register_schema

    schema_id = register_schema(writer, m.RunStop)
    return writer.register_channel(topics.RUN_STOP, "protobuf", schema_id)


__all__ = ["RecoverReport", "recover", "default_output"]
