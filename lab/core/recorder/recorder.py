"""`RunRecorder`: one chunked MCAP file per run, written as things happen.

Invariants (docs/recording.md):
- the first message is a `RunStart` (written and fsynced at open), the last a `RunStop`, on every
  exit path: normal exit -> "completed", exception -> "failed" with the traceback,
  KeyboardInterrupt -> "aborted"; interpreter exit without a stop -> "failed" (atexit);
- at the end of every step (and at least every `sync_interval_s` while messages arrive) the
  current chunk is ended, written, flushed and fsynced, so a SIGKILL loses at most the unfinished
  step; `lab recover` turns such a footer-less file into a complete one;
- every write goes through one lock, so drivers may log comms from several threads.
"""

from __future__ import annotations

import atexit
import functools
import json
import os
import socket
import subprocess
import sys
import threading
import time
import traceback as traceback_mod
import uuid
from contextlib import contextmanager
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping, Sequence

import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.PosesInFrame_pb2 import PosesInFrame
from google.protobuf.message import Message as ProtoMessage
from mcap.well_known import MessageEncoding
from mcap.writer import CompressionType, Writer as McapWriter
from mcap_protobuf.schema import register_schema

from lab.core.comms import CommsRecord
from lab.core.errors import UserError
from lab.core.geometry import Pose3
from lab.core.recorder import messages as m
from lab.core.recorder import topics

LOG_LEVELS = {"debug": Log.DEBUG, "info": Log.INFO, "warning": Log.WARNING, "warn": Log.WARNING,
              "error": Log.ERROR, "fatal": Log.FATAL}
IMAGE_FORMATS = ("png", "jpeg")

# Distributions whose versions go into the start record (what produced these numbers).
_VERSIONED = ("truss-lab", "numpy", "scipy", "gtsam", "opencv-contrib-python-headless", "pyserial", "mcap",
              "mcap-protobuf-support", "foxglove-schemas-protobuf", "protobuf", "rerun-sdk")


def _json(value: Any) -> str:
    def default(o: Any) -> Any:
        if isinstance(o, np.ndarray):
            return o.tolist()
        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, Pose3):
            return o.matrix().tolist()
        return str(o)

    return json.dumps(value if value is not None else {}, default=default, sort_keys=True)


@functools.lru_cache(maxsize=1)
def software_versions() -> dict[str, str]:
    out = {"python": sys.version.split()[0]}
    for dist in _VERSIONED:
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            pass
    return out


@functools.lru_cache(maxsize=1)
def git_state() -> tuple[str, bool]:
    """(HEAD SHA, working tree dirty?) of the checkout `lab` runs from; ("", False) if none."""
    here = Path(__file__).resolve().parent
    try:
        sha = subprocess.run(["git", "-C", str(here), "rev-parse", "HEAD"], capture_output=True, text=True,
                             timeout=5).stdout.strip()
        if not sha:
            return "", False
        dirty = subprocess.run(["git", "-C", str(here), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=5).stdout.strip() != ""
        return sha, dirty
    except (OSError, subprocess.SubprocessError):
        return "", False


def _ns(t_s: float | None) -> int:
    return time.time_ns() if t_s is None else int(round(float(t_s) * 1e9))


@dataclass(frozen=True)
class StepInfo:
    index: int
    name: str
    t0_s: float


class RunRecorder:
    """Records one run to `path` (an .mcap file).  Use as a context manager::

        with RunRecorder(path, "borg", params, rig=rig, scenario=scenario) as rec:
            with rec.step("place 2D", 1, {"module": "2D"}):
                driver = Turntable(url, comms=rec.comms_sink)
                rec.log_image(topics.CAMERA_IMAGE, img, t, "camera")
                rec.log_record(topics.VERDICTS, messages.module_verdict("2D", "ok"))

    `structure` (e.g. "borg:3", "tetrahelix:20") tells `lab review` which design to draw.
    `sync_interval_s` bounds how long written messages may sit in memory inside a long step.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        procedure: str,
        params: Mapping[str, Any] | None,
        rig: Mapping[str, Any] | None = None,
        scenario: Mapping[str, Any] | None = None,
        *,
        structure: str = "",
        argv: Sequence[str] | None = None,
        overwrite: bool = False,
        chunk_size: int = 1024 * 1024,
        sync_interval_s: float = 2.0,
    ) -> None:
        self.path = Path(path)
        if self.path.exists() and not overwrite:
            raise UserError(f"run file {self.path} already exists; choose another path (runs are never overwritten)")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.procedure = procedure
        self.run_id = uuid.uuid4().hex[:12]
        self._lock = threading.RLock()
        self._sync_interval_s = float(sync_interval_s)
        self._file = open(self.path, "wb")
        self._writer = McapWriter(self._file, chunk_size=chunk_size, compression=CompressionType.ZSTD)
        self._writer.start(profile="", library=f"lab.recorder ({software_versions().get('truss-lab', '?')})")
        self._schema_ids: dict[str, int] = {}
        self._channels: dict[str, tuple[int, str]] = {}
        self._stopped = False
        self._current: StepInfo | None = None
        self._steps_completed = 0
        self._ended: set[int] = set()
        self._last_step = ""
        self._t0 = time.time()
        self._last_sync = time.monotonic()
        self.dropped_after_stop = 0
        self.stop_record: Any = None
        self._listeners: list[Callable[[str, ProtoMessage, int], None]] = []   # add_listener (live view)

        sha, dirty = git_state()
        start = m.RunStart(
            start_time=m.timestamp(self._t0), run_id=self.run_id, procedure=procedure,
            params_json=_json(params), rig_json=_json(rig), scenario_json=_json(scenario),
            structure=structure or "", versions=software_versions(), git_sha=sha, git_dirty=dirty,
            argv=list(sys.argv if argv is None else argv), hostname=socket.gethostname(),
        )
        self._write(topics.RUN_START, start, _ns(self._t0))
        self.sync()
        atexit.register(self._atexit)

    # ---- context manager and stop --------------------------------------------------------------

    def __enter__(self) -> "RunRecorder":
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: Any) -> bool:
        if exc_type is None:
            self.stop("completed")
        elif issubclass(exc_type, KeyboardInterrupt):
            self.stop("aborted", "interrupted by the operator (KeyboardInterrupt)",
                      "".join(traceback_mod.format_exception(exc_type, exc, tb)))
        elif issubclass(exc_type, SystemExit):
            code = getattr(exc, "code", None)
            result = "completed" if code in (None, 0) else "aborted"
            self.stop(result, f"SystemExit({code!r})")
        else:
            self.stop("failed", f"{exc_type.__name__}: {exc}",
                      "".join(traceback_mod.format_exception(exc_type, exc, tb)))
        return False  # never swallow the exception

    def stop(self, result: str, reason: str = "", traceback: str = "") -> None:
        """Write the stop record and close the file.  Idempotent: later calls do nothing."""
        if result not in m.RUN_RESULTS:
            raise ValueError(f"run result must be one of {m.RUN_RESULTS}, got {result!r}")
        with self._lock:
            if self._stopped:
                return
            now = time.time()
            last = self._last_step
            if self._current is not None:  # stopped from inside a step (e.g. rec.stop in an except)
                last = f"{self._current.index} {self._current.name} (unfinished)"
            stop = m.RunStop(stop_time=m.timestamp(now), result=result, reason=reason, traceback=traceback,
                             steps_completed=len(self._ended), duration_s=now - self._t0, last_step=last)
            try:
                self._write(topics.RUN_STOP, stop, _ns(now))
                self._writer.finish()
                self._file.flush()
                os.fsync(self._file.fileno())
            finally:
                self._stopped = True
                self.stop_record = stop
                self._file.close()
                atexit.unregister(self._atexit)

    @property
    def stopped(self) -> bool:
        return self._stopped

    @property
    def steps_completed(self) -> int:
        return self._steps_completed

    def _atexit(self) -> None:
        if not self._stopped:
            self.stop("failed", "the program exited without stopping the run recorder")

    # ---- steps ---------------------------------------------------------------------------------

    @contextmanager
    def step(self, name: str, index: int, params: Mapping[str, Any] | None = None) -> Iterator[StepInfo]:
        """Bracket one procedure step with start and end (or error) records.  The chunk is ended and
        fsynced after the start record and after the end record, so nothing of a finished step can
        be lost and a killed run still names the step it was in."""
        if self._current is not None:
            raise RuntimeError(f"step {name!r} started inside step {self._current.name!r}; steps do not nest")
        info = StepInfo(int(index), name, time.time())
        self._write(topics.RUN_STEP, m.StepEvent(timestamp=m.timestamp(info.t0_s), index=info.index, name=name,
                                                 phase="start", params_json=_json(params)), _ns(info.t0_s))
        self._current = info
        self.sync()  # so that after a kill the file tells which step was running (resume re-runs it)
        try:
            yield info
        except BaseException as exc:
            now = time.time()
            self._current = None
            self._write(topics.RUN_STEP, m.StepEvent(
                timestamp=m.timestamp(now), index=info.index, name=name, phase="error", params_json=_json(params),
                duration_s=now - info.t0_s, error=f"{type(exc).__name__}: {exc}"), _ns(now))
            self.sync()
            raise
        now = time.time()
        self._current = None
        self._write(topics.RUN_STEP, m.StepEvent(timestamp=m.timestamp(now), index=info.index, name=name,
                                                 phase="end", params_json=_json(params),
                                                 duration_s=now - info.t0_s), _ns(now))
        self._steps_completed += 1
        self._ended.add(info.index)
        self._last_step = f"{info.index} {name}"
        self.sync()

    @property
    def current_step(self) -> StepInfo | None:
        return self._current

    # ---- logging -------------------------------------------------------------------------------

    def comms_sink(self, record: CommsRecord) -> None:
        """A `CommsSink`: writes each `CommsRecord` to /comms.  After stop() records are counted in
        `dropped_after_stop` instead of raising, so a driver closing late cannot crash."""
        if self._stopped:
            self.dropped_after_stop += 1
            return
        msg = m.DeviceIO(timestamp=m.timestamp(record.t_s), device=record.device, url=record.url,
                         direction=record.direction, data=bytes(record.data),
                         text=bytes(record.data).decode("utf-8", errors="backslashreplace"), note=record.note)
        self._write(topics.COMMS, msg, _ns(record.t_s))

    def log_image(self, topic: str, bgr: np.ndarray, t_s: float | None, frame_id: str, *,
                  format: str = "png", jpeg_quality: int = 95) -> None:
        """A camera image (BGR or grey, uint8; 16-bit grey as PNG) as foxglove.CompressedImage."""
        import cv2

        img = np.asarray(bgr)
        if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] not in (1, 3, 4)):
            raise ValueError(f"image must be HxW or HxWx{{1,3,4}}, got shape {img.shape}")
        if format not in IMAGE_FORMATS:
            raise ValueError(f"image format must be one of {IMAGE_FORMATS}, got {format!r}")
        if img.dtype != np.uint8 and not (img.dtype == np.uint16 and format == "png"):
            raise ValueError(f"image dtype must be uint8 (or uint16 for png), got {img.dtype}")
        params = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)] if format == "jpeg" else [cv2.IMWRITE_PNG_COMPRESSION, 1]
        ok, buf = cv2.imencode("." + ("jpg" if format == "jpeg" else "png"), img, params)
        if not ok:
            raise ValueError(f"OpenCV could not encode a {img.shape} {img.dtype} image as {format}")
        msg = CompressedImage(timestamp=m.timestamp(t_s), frame_id=frame_id, data=buf.tobytes(), format=format)
        self._write(topic, msg, _ns(t_s))

    def log_calibration(self, topic: str, K: np.ndarray, dist: Sequence[float] | np.ndarray, w: int, h: int,
                        frame_id: str, t_s: float | None = None) -> None:
        """Camera intrinsics as foxglove.CameraCalibration (OpenCV K and distortion coefficients:
        5 -> "plumb_bob", 8 -> "rational_polynomial"; 4 are padded to 5)."""
        Km = np.asarray(K, dtype=float)
        if Km.shape != (3, 3):
            raise ValueError(f"camera matrix K must be 3x3, got shape {Km.shape}")
        d = [float(v) for v in np.asarray(dist, dtype=float).reshape(-1)]
        if len(d) in (0, 4):
            d = d + [0.0] * (5 - len(d))
        if len(d) == 5:
            model = "plumb_bob"
        elif len(d) in (8, 12, 14):
            model = "rational_polynomial"
            d = d[:8] if len(d) > 8 and not any(d[8:]) else d
        else:
            raise ValueError(f"distortion must have 0, 4, 5, 8, 12 or 14 coefficients, got {len(d)}")
        if int(w) <= 0 or int(h) <= 0:
            raise ValueError(f"image size must be positive, got {w}x{h} px")
        P = np.hstack([Km, np.zeros((3, 1))])
        msg = CameraCalibration(timestamp=m.timestamp(t_s), frame_id=frame_id, width=int(w), height=int(h),
                                distortion_model=model, D=d, K=Km.reshape(9).tolist(),
                                R=np.eye(3).reshape(9).tolist(), P=P.reshape(12).tolist())
        self._write(topic, msg, _ns(t_s))

    def log_pose(self, topic: str, pose: Pose3, frame_id: str, t_s: float | None = None,
                 covariance6x6: np.ndarray | None = None) -> None:
        """A pose in `frame_id` as foxglove.PoseInFrame on `topic`; with a covariance (6x6, GTSAM
        order) also a lab.PoseEstimate on `topic + "/covariance"` (entity = topic minus /estimate/)."""
        self._write(topic, PoseInFrame(timestamp=m.timestamp(t_s), frame_id=frame_id, pose=m.pose_to_proto(pose)),
                    _ns(t_s))
        if covariance6x6 is not None:
            entity = topic[len(topics.ESTIMATE_PREFIX):] if topic.startswith(topics.ESTIMATE_PREFIX) else topic.strip("/")
            self._write(topic + topics.COVARIANCE_SUFFIX,
                        m.pose_estimate(entity, pose, frame_id, covariance6x6, t_s), _ns(t_s))

    def log_tag_estimates(self, poses: Mapping[int, Pose3], frame_id: str, t_s: float | None = None,
                          covariances: Mapping[int, np.ndarray] | None = None) -> None:
        """Estimated tag poses: foxglove.PosesInFrame on /estimate/tags (ascending id, for plain
        viewers) and lab.PoseEstimateSet with ids and covariances on /estimate/tag_estimates."""
        ids = sorted(int(i) for i in poses)
        self._write(topics.TAG_POSES, PosesInFrame(timestamp=m.timestamp(t_s), frame_id=frame_id,
                                                   poses=[m.pose_to_proto(poses[i]) for i in ids]), _ns(t_s))
        covs = covariances or {}
        self._write(topics.TAG_ESTIMATES, m.pose_estimate_set(
            {m.tag_entity(i): poses[i] for i in ids}, frame_id,
            {m.tag_entity(i): c for i, c in covs.items()}, t_s), _ns(t_s))

    def log_transform(self, parent: str, child: str, pose: Pose3, t_s: float | None = None) -> None:
        """parent_T_child as foxglove.FrameTransform on /tf."""
        if not parent or not child or parent == child:
            raise ValueError(f"a transform needs two different frame names, got {parent!r} -> {child!r}")
        p = m.pose_to_proto(pose)
        self._write(topics.TF, FrameTransform(timestamp=m.timestamp(t_s), parent_frame_id=parent,
                                              child_frame_id=child, translation=p.position,
                                              rotation=p.orientation), _ns(t_s))

    def log_structure(self, name: str, nodes: np.ndarray, edges: Sequence[tuple[int, int]],
                      tags: Sequence[Any] = (), frame_id: str = "structure", t_s: float | None = None) -> None:
        """The design structure (nodes (N,3) m, edges (i, j), tags as lab.DesignTag) on /structure,
        so `lab review` can draw it even without the structure generators."""
        pts = np.asarray(nodes, dtype=float).reshape(-1, 3)
        flat_edges = [int(v) for e in edges for v in e]
        if any(v < 0 or v >= len(pts) for v in flat_edges):
            raise ValueError(f"an edge refers to a node outside 0..{len(pts) - 1}")
        self._write(topics.STRUCTURE, m.StructureDesign(timestamp=m.timestamp(t_s), name=name, frame_id=frame_id,
                                                        node_positions=pts.reshape(-1).tolist(), edges=flat_edges,
                                                        tags=list(tags)), _ns(t_s))

    def log_design(self, name: str, model: Any, frame_id: str = "structure", t_s: float | None = None) -> None:
        """Record a design model (a BORG `BorgModel` or a `TrussModel`: anything with `nodes` and
        `edges`, and optionally `tags` {id: TagSpec}) on /structure, so the run file carries the
        exact design it was checked against."""
        tags = [m.DesignTag(id=int(tid), label=getattr(t, "label", ""), module=getattr(t, "module", ""),
                            pose=m.pose_to_proto(t.structure_T_tag), size_m=float(getattr(t, "size_m", 0.10)))
                for tid, t in sorted(getattr(model, "tags", {}).items())]
        self.log_structure(name, model.nodes, list(model.edges), tags, frame_id, t_s)

    def log_record(self, topic: str, message: ProtoMessage) -> None:
        """Any protobuf message (our lab.* domain records, or a Foxglove schema).  Its `timestamp`
        field, if it has one and it is set, becomes the MCAP log time; unset, it is filled with now."""
        if not isinstance(message, ProtoMessage):
            raise TypeError(f"log_record takes a protobuf message, got {type(message).__name__}")
        log_ns = time.time_ns()
        if "timestamp" in message.DESCRIPTOR.fields_by_name:
            ts = message.timestamp
            if ts.seconds or ts.nanos:
                log_ns = ts.seconds * 1_000_000_000 + ts.nanos
            else:
                ts.CopyFrom(m.timestamp(log_ns / 1e9))
        self._write(topic, message, log_ns)

    def copy_message(self, topic: str, message: ProtoMessage, log_time_ns: int) -> None:
        """Re-record a message read from another run file with its original log time (resume
        keeps the completed steps of the interrupted run this way)."""
        self._write(topic, message, int(log_time_ns))
        if topic == topics.RUN_STEP and isinstance(message, m.StepEvent) and message.phase == "end":
            self._ended.add(int(message.index))

    @property
    def step_indices_ended(self) -> set[int]:
        """Indices of every step whose end record is in this file (copied or recorded): what a run
        may call `completed` only when it covers the whole plan."""
        return set(self._ended)

    def rename(self, path: str | os.PathLike[str]) -> None:
        """Give the open file another name (same directory), atomically; writing continues."""
        new = Path(path)
        with self._lock:
            self.sync()
            os.replace(self.path, new)
            self.path = new

    def log_text(self, level: str | int, text: str, t_s: float | None = None) -> None:
        """A log line (foxglove.Log on /log); level: debug, info, warning, error, fatal."""
        if isinstance(level, str):
            if level.lower() not in LOG_LEVELS:
                raise ValueError(f"log level must be one of {sorted(LOG_LEVELS)}, got {level!r}")
            lvl = LOG_LEVELS[level.lower()]
        else:
            lvl = int(level)
        self._write(topics.LOG, Log(timestamp=m.timestamp(t_s), level=lvl, message=str(text), name=self.procedure),
                    _ns(t_s))

    def log_metric(self, name: str, value: float, unit: str = "", t_s: float | None = None) -> None:
        """A named scalar to plot over steps (residuals, costs, errors) on /metrics."""
        step = self._current.index if self._current is not None else -1
        self._write(topics.METRICS, m.Metric(timestamp=m.timestamp(t_s), name=name, value=float(value), unit=unit,
                                             step_index=step), _ns(t_s))

    def log_prompt(self, question: str, answer: str, automatic: bool = False, t_s: float | None = None) -> None:
        """An operator prompt and its answer on /operator (automatic = answered by --auto)."""
        self._write(topics.OPERATOR, m.OperatorPrompt(timestamp=m.timestamp(t_s), question=question, answer=answer,
                                                      automatic=automatic), _ns(t_s))

    def log_json(self, kind: str, value: Any, t_s: float | None = None) -> None:
        """Anything else, as JSON with a kind, on /records."""
        self._write(topics.RECORDS, m.JsonRecord(timestamp=m.timestamp(t_s), kind=kind, json=_json(value)), _ns(t_s))

    # ---- MCAP plumbing -------------------------------------------------------------------------

    def sync(self) -> None:
        """End the current chunk, write it, flush and fsync: everything logged so far survives a kill."""
        with self._lock:
            if self._stopped:
                return
            flush = getattr(self._writer, "flush", None)
            if flush is not None:  # mcap >= 1.6: ends the chunk in progress and flushes the stream
                flush()
            else:  # older mcap: the same two steps through the writer's private methods
                self._writer._Writer__finalize_chunk()  # type: ignore[attr-defined]
                self._writer._Writer__flush()  # type: ignore[attr-defined]
                self._file.flush()
            os.fsync(self._file.fileno())
            self._last_sync = time.monotonic()

    def _channel(self, topic: str, message: ProtoMessage) -> int:
        type_name = message.DESCRIPTOR.full_name
        known = self._channels.get(topic)
        if known is not None:
            if known[1] != type_name:
                raise ValueError(f"topic {topic!r} carries {known[1]}, cannot write a {type_name} to it")
            return known[0]
        schema_id = self._schema_ids.get(type_name)
        if schema_id is None:
            schema_id = register_schema(self._writer, type(message))
            self._schema_ids[type_name] = schema_id
        channel_id = self._writer.register_channel(topic=topic, message_encoding=MessageEncoding.Protobuf,
                                                   schema_id=schema_id)
        self._channels[topic] = (channel_id, type_name)
        return channel_id

    def add_listener(self, fn: Callable[[str, ProtoMessage, int], None]) -> None:
        """Call `fn(topic, message, log_time_ns)` after each message is written (the live view of
        `lab run --view`).  A listener must be quick (queue the message, no more); one that raises is
        dropped and the run goes on: a viewer never breaks a recording."""
        self._listeners.append(fn)

    def _write(self, topic: str, message: ProtoMessage, log_ns: int) -> None:
        if not topic.startswith("/"):
            raise ValueError(f"topics start with '/', got {topic!r}")
        data = message.SerializeToString()
        with self._lock:
            if self._stopped:
                raise RuntimeError(f"run recorder for {self.path} is stopped; cannot write to {topic}")
            channel_id = self._channel(topic, message)
            self._writer.add_message(channel_id=channel_id, log_time=log_ns, data=data, publish_time=log_ns)
            if time.monotonic() - self._last_sync > self._sync_interval_s:
                self.sync()
        for fn in list(self._listeners):
            try:
                fn(topic, message, log_ns)
            except Exception:
                self._listeners.remove(fn)
