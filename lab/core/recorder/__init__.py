"""The MCAP run recorder (docs/recording.md): one chunked MCAP file per run with Foxglove schemas
for images, calibration, transforms, poses and logs and our own `lab.*` protobuf messages for
domain records; a start and a stop record on every exit path; a chunk ended and fsynced at the
end of every step; `recover` for files left without their footer; readers for tests and review.

    from lab.core.recorder import RunRecorder, topics, messages
"""

from lab.core.recorder import messages, topics
from lab.core.recorder.reader import RecordedMessage, RunSummary, ScanState, iter_messages, read_summary
from lab.core.recorder.recorder import RunRecorder, StepInfo
from lab.core.recorder.recover import RecoverReport, default_output, recover

__all__ = [
    "RunRecorder", "StepInfo", "messages", "topics", "iter_messages", "read_summary", "RecordedMessage",
    "RunSummary", "ScanState", "recover", "RecoverReport", "default_output",
]
