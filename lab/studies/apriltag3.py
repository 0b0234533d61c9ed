"""The AprilTag 3 C library (through `pupil-apriltags`), as the reference our detector is measured
against: its detections with the corners converted to our convention.

Only the benchmark and the script that made the photographs' stored reference use it; the lab's
detector does not (it is 10x slower than aruco on a noisy 1280x720 frame: docs/fiducials.md).
`pupil-apriltags` is an optional dependency (the `test` extra); `available()` says whether it is
installed.
"""

from __future__ import annotations

from functools import lru_cache
from typing import NamedTuple

import numpy as np

from estimation.fiducials import apriltag_to_opencv_corners

__all__ = ["AprilTag3Detection", "available", "detect", "version"]


class AprilTag3Detection(NamedTuple):
    tag_id: int
    corners_px: np.ndarray     # (4, 2), ours: OpenCV pixel centres, aruco's corner order
    hamming: int               # bits the library corrected


def available() -> bool:
    from importlib.util import find_spec

    return find_spec("pupil_apriltags") is not None


def version() -> str:
    from importlib.metadata import version as v

    return f"pupil-apriltags {v('pupil-apriltags')}"


@lru_cache(maxsize=4)
def _detector(decimate: float, threads: int):
    import pupil_apriltags

    class Detector(pupil_apriltags.Detector):
        # pupil-apriltags 1.0.4 frees the tag family before the detector that still points at it,
        # which crashes the interpreter at exit (pupil-labs/apriltags#65, open); these detectors
        # live as long as the process, so they are simply never freed
        def __del__(self) -> None:
            pass

    return Detector(families="tag36h11", nthreads=threads, quad_decimate=decimate)


def detect(grey: np.ndarray, decimate: float = 1.0, threads: int = 1) -> list[AprilTag3Detection]:
    """AprilTag 3's tag36h11 detections in an 8-bit grey image.  `decimate` is its quad_decimate
    (1: full resolution, its most sensitive setting; 2: its default)."""
    img = np.ascontiguousarray(grey, dtype=np.uint8)
    return [AprilTag3Detection(int(d.tag_id), apriltag_to_opencv_corners(d.corners), int(d.hamming))
            for d in _detector(float(decimate), int(threads)).detect(img)]
