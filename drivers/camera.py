"""Camera driver: frames with timestamps, intrinsics from a calibration file.

Two sources, picked from the rig's URL:
- a snapshot endpoint (`http://HOST:PORT/frame.jpg`, docs/protocols.md §6): one GET, one frame of
  the current view, any format OpenCV decodes (JPEG as IP cameras send it, PNG lossless); the
  simulated camera serves one, so do many IP cameras;
- OpenCV capture (`cv2.VideoCapture`): a device index (`"0"`), `/dev/videoN`, or a stream URL
  (`rtsp://...`, `http://.../video.mjpg`).

The calibration file (JSON, docs/hardware.md §Camera calibration file) is what `lab calibrate
camera` writes; `load_calibration` / `save_calibration` read and write it."""

from __future__ import annotations

import json
import math
import threading
import time
import urllib.parse
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from drivers.driver import Driver
from drivers.errors import DeviceTimeout, Disconnected, ProtocolError, RigMismatch
from drivers.transport import HttpTransport
from lab.core.comms import CommsRecord, CommsSink, null_sink
from lab.core.config import CameraConfig
from lab.core.errors import UserError
from lab.core.files import read_json

CALIBRATION_FORMAT = "lab-camera-calibration"
SNAPSHOT_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
CLOSE_WAIT_S = 2.0    # close() lets a read under way finish this long before releasing the capture


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole camera with OpenCV's radial-tangential distortion."""

    K: np.ndarray                 # 3x3, pixels
    dist: np.ndarray              # (k1, k2, p1, p2[, k3[, ...]])
    width_px: int
    height_px: int
    rms_reprojection_px: float | None = None
    source: str = ""

    @staticmethod
    def from_fov(width_px: int, height_px: int, hfov_deg: float, dist: Any = (0, 0, 0, 0, 0)) -> Intrinsics:
        f = (width_px / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        K = np.array([[f, 0.0, (width_px - 1) / 2.0], [0.0, f, (height_px - 1) / 2.0], [0.0, 0.0, 1.0]])
        return Intrinsics(K, np.asarray(dist, dtype=float), width_px, height_px)

    @property
    def hfov_deg(self) -> float:
        return math.degrees(2.0 * math.atan(self.width_px / 2.0 / self.K[0, 0]))

    def to_json(self, camera: str = "camera", source: str = "", created: str | None = None) -> dict[str, Any]:
        return {
            "format": CALIBRATION_FORMAT,
            "version": 1,
            "camera": camera,
            "model": "opencv-pinhole-radtan",
            "width_px": int(self.width_px),
            "height_px": int(self.height_px),
            "K": np.asarray(self.K, dtype=float).tolist(),
            "dist": np.asarray(self.dist, dtype=float).ravel().tolist(),
            "rms_reprojection_px": self.rms_reprojection_px,
            "source": source or self.source,
            "created": created or datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        }


def parse_calibration(data: Any, source: str) -> Intrinsics:
    def bad(key: str, problem: str) -> UserError:
        return UserError(f"camera calibration {source}: {key}: {problem}")

    if not isinstance(data, dict):
        raise bad("top level", "expected a JSON object")
    if data.get("format") != CALIBRATION_FORMAT:
        raise bad("format", f"expected {CALIBRATION_FORMAT!r}, got {data.get('format')!r}")
    if data.get("version") != 1:
        raise bad("version", f"this lab reads version 1, got {data.get('version')!r}")
    model = data.get("model", "opencv-pinhole-radtan")
    if model != "opencv-pinhole-radtan":
        raise bad("model", f"only 'opencv-pinhole-radtan' is supported, got {model!r}")
    w, h = data.get("width_px"), data.get("height_px")
    for key, v in (("width_px", w), ("height_px", h)):
        if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
            raise bad(key, f"expected a positive integer, got {v!r}")
    try:
        K = np.array(data.get("K"), dtype=float)
    except (TypeError, ValueError):
        raise bad("K", "expected a 3x3 list of numbers") from None
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise bad("K", f"expected a 3x3 list of numbers, got {data.get('K')!r}")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or K[0, 1] != 0 or not np.allclose(K[2], [0, 0, 1]):
        raise bad("K", "expected [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0")
    try:
        dist = np.array(data.get("dist", []), dtype=float).ravel()
    except (TypeError, ValueError):
        raise bad("dist", "expected a list of numbers") from None
    if dist.size not in (4, 5, 8, 12, 14) or not np.all(np.isfinite(dist)):
        raise bad("dist", f"expected 4, 5, 8, 12 or 14 numbers (OpenCV order k1 k2 p1 p2 k3 ...), got {dist.size}")
    rms = data.get("rms_reprojection_px")
    return Intrinsics(K, dist, w, h, None if rms is None else float(rms), source)


def load_calibration(path: str | Path) -> Intrinsics:
    return parse_calibration(read_json(path, "camera calibration"), str(path))


def save_calibration(path: str | Path, intrinsics: Intrinsics, camera: str = "camera", source: str = "") -> Path:
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_suffix(p.suffix + ".tmp")
    tmp.write_text(json.dumps(intrinsics.to_json(camera, source), indent=2) + "\n")
    tmp.replace(p)  # never leave a half-written calibration behind
    return p


@dataclass(frozen=True)
class Frame:
    image: np.ndarray     # (H, W, 3) uint8 BGR
    t_s: float            # exposure time (device clock if it tells, else host receipt), unix s
    seq: int              # frame counter (device's if it tells)
    camera: str


def is_snapshot_url(url: str) -> bool:
    parts = urllib.parse.urlsplit(url)
    return parts.scheme in ("http", "https") and parts.path.lower().endswith(SNAPSHOT_SUFFIXES)


class _Snapshot:
    def __init__(self, name: str, url: str, sink: CommsSink, timeout_s: float) -> None:
        parts = urllib.parse.urlsplit(url)
        self.name = name
        self.path = parts.path + (f"?{parts.query}" if parts.query else "")
        self.link = HttpTransport(name, f"{parts.scheme}://{parts.netloc}", sink, reply_timeout_s=timeout_s, retries=1)

    def read(self) -> tuple[np.ndarray, float | None, int | None]:
        import cv2

        decoded: list[np.ndarray] = []

        def check(reply: Any) -> None:   # inside the retry loop: a garbled frame is fetched again
            if reply.status != 200:
                raise ProtocolError(self.name, f"GET {self.path} answered HTTP {reply.status} {reply.reason}")
            img = cv2.imdecode(np.frombuffer(reply.body, np.uint8), cv2.IMREAD_COLOR)
            if img is None:
                raise ProtocolError(self.name, f"GET {self.path} returned {len(reply.body)} bytes that are not an image")
            decoded[:] = [img]

        reply = self.link.get(self.path, idempotent=True, check=check)
        img = decoded[0]
        t = reply.headers.get("X-Frame-Time-S")
        seq = reply.headers.get("X-Frame-Seq")
        try:
            return img, (float(t) if t else None), (int(seq) if seq else None)
        except ValueError:
            raise ProtocolError(self.name, f"bad frame headers X-Frame-Time-S={t!r} X-Frame-Seq={seq!r}") from None

    def close(self) -> None:
        self.link.close()


class _Capture:
    """cv2.VideoCapture behind a deadline: a stalled stream must not hang the run."""

    def __init__(self, name: str, url: str, sink: CommsSink, timeout_s: float) -> None:
        import cv2

        self.name, self.url, self.sink, self.timeout_s = name, url, sink, timeout_s
        source: int | str = int(url) if url.isdigit() else url
        self.cap = cv2.VideoCapture(source)
        if not self.cap.isOpened():
            raise Disconnected(name, f"OpenCV cannot open camera {url!r}")
        self.sink(CommsRecord(name, url, "event", b"", time.time(), "opened with cv2.VideoCapture"))
        self._lock = threading.Lock()
        self._worker: threading.Thread | None = None

    def read(self) -> tuple[np.ndarray, float | None, int | None]:
        result: list[Any] = []
        with self._lock:
            worker = threading.Thread(target=lambda: result.append(self.cap.read()), daemon=True)
            self._worker = worker
            worker.start()
            worker.join(self.timeout_s)
            if worker.is_alive():
                self.sink(CommsRecord(self.name, self.url, "event", b"", time.time(), "frame timeout"))
                raise DeviceTimeout(self.name, f"no frame from {self.url!r} within {self.timeout_s:g} s")
        ok, img = result[0]
        if not ok or img is None:
            raise Disconnected(self.name, f"camera {self.url!r} returned no frame (unplugged or end of stream)")
        if img.ndim == 2:
            import cv2

            img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
        self.sink(CommsRecord(self.name, self.url, "event", b"", time.time(), f"frame {img.shape[1]}x{img.shape[0]}"))
        return img, None, None

    def close(self) -> None:
        # a read still under way (a timed-out frame, or a run aborted mid-read) is let finish first:
        # releasing the capture under it is undefined in OpenCV, and a daemon thread still inside
        # OpenCV when the interpreter exits aborts the process (SIGABRT instead of the run's exit code)
        worker = self._worker
        if worker is not None and worker.is_alive():
            worker.join(max(self.timeout_s, CLOSE_WAIT_S))
            if worker.is_alive():
                self.sink(CommsRecord(self.name, self.url, "event", b"", time.time(),
                                      "close: a read is still stalled; the capture is left open"))
                return
        self.cap.release()


class Camera(Driver):
    kind = "camera"
    moves = False

    def __init__(self, config: CameraConfig, sink: CommsSink = null_sink) -> None:
        self.config = config
        self.name = config.name
        self.url = config.url
        self._sink = sink
        self._source: _Snapshot | _Capture | None = None
        self._seq = 0
        self.intrinsics: Intrinsics | None = load_calibration(config.calibration) if config.calibration else None

    @classmethod
    def open(cls, config: CameraConfig, sink: CommsSink = null_sink) -> Camera:
        return cls(config, sink)

    @property
    def link(self) -> HttpTransport | None:
        return self._source.link if isinstance(self._source, _Snapshot) else None

    def _open(self) -> _Snapshot | _Capture:
        if self._source is None:
            if is_snapshot_url(self.url):
                self._source = _Snapshot(self.name, self.url, self._sink, self.config.timeout_s)
            else:
                self._source = _Capture(self.name, self.url, self._sink, self.config.timeout_s)
        return self._source

    def identify(self) -> str:
        if is_snapshot_url(self.url):
            src = self._open()
            assert isinstance(src, _Snapshot)
            try:
                r = src.link.get_json("/id", idempotent=True)
                return f"{r.get('model', '?')} {r.get('width_px', '?')}x{r.get('height_px', '?')}"
            except Exception:
                return "snapshot camera"
        return f"OpenCV capture {self.url}"

    def grab(self) -> Frame:
        """One frame of the current view, checked against the calibration's image size.  A frame
        that does not decode is fetched once more (a snapshot GET is safe to repeat)."""
        try:
            img, t, seq = self._open().read()
        except ProtocolError as exc:
            self._sink(CommsRecord(self.name, self.url, "event", b"", time.time(), f"retry after: {exc.message}"))
            img, t, seq = self._open().read()
        self._seq += 1
        if self.intrinsics and (img.shape[1], img.shape[0]) != (self.intrinsics.width_px, self.intrinsics.height_px):
            raise RigMismatch(self.name, f"frame is {img.shape[1]}x{img.shape[0]} px but the calibration "
                                         f"{self.config.calibration} is for {self.intrinsics.width_px}x"
                                         f"{self.intrinsics.height_px} px")
        return Frame(img, t if t is not None else time.time(), seq if seq is not None else self._seq, self.name)

    def check(self) -> str:
        ident = self.identify()
        t0 = time.monotonic()
        frame = self.grab()
        ms = (time.monotonic() - t0) * 1000
        cal = (f"calibration {self.config.calibration.name} ({self.intrinsics.hfov_deg:.1f} deg HFOV)"
               if self.intrinsics else "NO calibration file (set [camera] calibration)")
        return f"{ident}; frame {frame.image.shape[1]}x{frame.image.shape[0]} in {ms:.0f} ms; {cal}"

    def close(self) -> None:
        if self._source is not None:
            self._source.close()
            self._source = None
