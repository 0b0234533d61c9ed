"""The live view of `lab run ... --view`: the run in Rerun as it happens, drawn by the same code
as `lab review` (lab.core.review's `_Review`), so the live picture and the picture afterwards are one.

The recorder hands every message it writes to `LiveView.feed` (RunRecorder.add_listener), which
only queues it: the drawing and the sending happen on a thread of their own, so a slow viewer
costs the run a queue, not time on its critical path.  Where the review reads the whole file
before drawing (it knows every frame and image topic in advance), the live view learns them as
they come: the design from the run's /structure record, an image's entity from its frame id.
"""

from __future__ import annotations

import queue
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lab.core import viewer
from lab.core.recorder import topics
from lab.core.recorder.reader import RecordedMessage, ScanState

_STOP = object()


@dataclass
class LiveReport:
    messages: int
    dropped: int
    sink: viewer.Sink
    problem: str = ""        # why the end of the live view did not reach the viewer ("" if it did)


class LiveView:
    def __init__(self, target: str, run_id: str, image_entities: list[str]) -> None:
        """`target`: "auto" (a local viewer with a display, else the web viewer on loopback) or a
        viewer URL to connect to.  `run_id`: the recorder's, so the recording id is the one
        `lab review` gives the same run."""
        import rerun as rr

        from lab.core.review import APPLICATION_ID, _Review, make_blueprint

        self.mode = viewer.choose_mode(None, None if target == "auto" else target, False)
        self.rec = rr.RecordingStream(APPLICATION_ID, recording_id=f"lab-run-{run_id}")
        self.sink = viewer.attach(self.rec, self.mode, blueprint=make_blueprint(image_entities),
                                  connect=None if target == "auto" else target)
        self.view = _Review(self.rec, live=True)
        self.view.draw_static()
        self.queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self.count = 0
        self.failed = 0
        self.thread = threading.Thread(target=self._drain, name="lab-live-view", daemon=True)
        self.thread.start()

    def feed(self, topic: str, message: Any, log_ns: int) -> None:
        """RunRecorder listener: queue, nothing else (it runs on the recorder's thread)."""
        self.queue.put((topic, message, log_ns))

    def _drain(self) -> None:
        while True:
            item = self.queue.get()
            if item is _STOP:
                return
            topic, message, log_ns = item
            try:
                self.view.handle(RecordedMessage(topic, log_ns, message.DESCRIPTOR.full_name, message))
                self.count += 1
            except Exception:   # a message the view cannot draw must not stop the others
                self.failed += 1

    def close(self, run_file: Path, timeout_s: float = 60.0) -> LiveReport:
        """Draw what is still queued, then the run's info document; flush to the viewer."""
        from lab.core.recorder.reader import iter_messages

        self.queue.put(_STOP)
        self.thread.join(timeout_s)
        if self.view.start is None:
            try:   # the start record was written before the view could listen: read it back
                self.view.start = next(iter(iter_messages(run_file, topics.RUN_START)), None)
                self.view.start = self.view.start.message if self.view.start is not None else None
            except Exception:
                pass
        problem = ""
        try:
            self.rec.reset_time()
            self.view.info_document(run_file, ScanState())
            self.rec.flush(timeout_sec=timeout_s)
        except Exception as exc:   # the viewer went away (closed window, killed server): the run is still whole
            problem = f"{type(exc).__name__}: {exc}"
        self.rec.disconnect()   # before the web viewer may stop: no "connection severed" errors at exit
        return LiveReport(self.count, self.failed, self.sink, problem)


__all__ = ["LiveView", "LiveReport"]
