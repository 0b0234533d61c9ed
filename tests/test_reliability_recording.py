"""Issue 11, recording: `lab recover` salvages every intact chunk after a corrupt one, and leaves
a complete file alone with one honest line."""

from __future__ import annotations

import struct
from pathlib import Path

from lab.cli import main as lab_main
from lab.core.recorder import RunRecorder, iter_messages, messages as m, read_summary, recover, topics


def _log(path: Path, steps: int = 12) -> Path:
    with RunRecorder(path, "p", {}, sync_interval_s=1e9) as rec:
        for i in range(steps):
            with rec.step(f"s{i}", i):
                rec.log_record(topics.VERDICTS, m.module_verdict(f"M{i}", "ok", reason=f"{i}" * 300))
    return path


def _chunks(data: bytes) -> list[tuple[int, int]]:
    out, off = [], 8
    while off + 9 <= len(data):
        op, ln = struct.unpack_from("<BQ", data, off)
        if op == 0x06:
            out.append((off, ln))
        if op == 0x0F:   # data end
            break
        off += 9 + ln
    return out


def test_a_corrupt_chunk_costs_only_its_own_messages(tmp_path):
    data = bytearray(_log(tmp_path / "run.mcap").read_bytes())
    chunks = _chunks(bytes(data))
    off, ln = chunks[len(chunks) * 3 // 10]              # a chunk about 30 % into the file
    data[off + 9 + ln // 2: off + 9 + ln // 2 + 64] = bytes(range(64))
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    rep = recover(bad, tmp_path / "fixed.mcap")
    assert len(rep.damaged) == 1 and not rep.intact
    mods = [r.message.module for r in iter_messages(rep.path_out, topics.VERDICTS)]
    assert len(mods) >= 11 and mods[-1] == "M11"           # everything after the damage is kept
    s = read_summary(rep.path_out)
    assert s.scan.complete and s.stop.result == "completed" and len(s.steps_completed) >= 10


def test_a_torn_and_damaged_file_salvages_past_the_damage(tmp_path):
    data = bytearray(_log(tmp_path / "run.mcap").read_bytes())
    chunks = _chunks(bytes(data))
    off, _ = chunks[3]
    data[off:off + 9] = b"\xff" * 9                       # the record header itself destroyed
    cut = chunks[-2][0]                                   # and the tail cut off by a kill
    torn = tmp_path / "torn.mcap"
    torn.write_bytes(bytes(data[:cut]))
    rep = recover(torn, tmp_path / "fixed.mcap")
    assert rep.damaged and not rep.was_complete and not rep.had_stop
    mods = [r.message.module for r in iter_messages(rep.path_out, topics.VERDICTS)]
    assert "M1" in mods and mods[-1] in ("M9", "M10")     # chunks after the damaged header are kept


def test_a_complete_file_is_left_alone_with_one_honest_line(tmp_path, capsys):
    path = _log(tmp_path / "run.mcap", 3)
    assert lab_main(["recover", str(path)]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1 and "complete and intact" in out[0] and "dropped" not in out[0]
    assert not (tmp_path / "run.recovered.mcap").exists()
    assert read_summary(path).scan.dropped_bytes == 0
