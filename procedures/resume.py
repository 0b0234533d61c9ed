"""Resume support: carry the completed steps of an interrupted run into the resumed run's log."""

from __future__ import annotations

from pathlib import Path

from lab.recorder import messages as m
from lab.recorder import topics
from lab.recorder.reader import iter_messages

_SKIP = {topics.RUN_START, topics.RUN_STOP, topics.STRUCTURE}


def copy_completed_steps(previous: Path, recorder, steps_completed: int) -> int:
    """Copy every record of `previous` up to the end of its step `steps_completed - 1` (what the
    checkpoint says was finished) into `recorder`; the interrupted step's partial records stay in
    the archived file only.  Returns how many records were copied."""
    copied = 0
    if steps_completed <= 0:
        return 0
    for rm in iter_messages(previous):
        if rm.topic in _SKIP:
            continue
        recorder.copy_message(rm.topic, rm.message, rm.log_time_ns)
        copied += 1
        if (rm.topic == topics.RUN_STEP and isinstance(rm.message, m.StepEvent) and rm.message.phase == "end"
                and rm.message.index == steps_completed - 1):
            break
    return copied
