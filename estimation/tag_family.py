"""The tag families the lab prints and the detector reads.

A BORG numbers its tags from 0 (the turntable's 12 last): 550 tags at N = 8, 630 at N = 9, 926 at
N = 10.  AprilTag 36h11 has 587 codes (minimum Hamming distance 11, rotations included), enough up
to N = 8.  A larger structure is printed in the lab's extension of 36h11 to 1024 codes: OpenCV's
`extendDictionary(1024, 6, 36h11, randomSeed=0)`, whose first 587 codes are 36h11's own (tags
already printed stay valid) and whose 437 new ones keep a minimum distance of 9 to every other
code and rotation.  A structure whose ids fit 36h11 is read in 36h11 alone, for its larger
distance; only a larger one reads the extension.  The extension is generated, not stored: a test
pins its codes' checksum, so an OpenCV that generated different codes (tags printed by another
version would not be read) fails CI rather than a run.
"""

from __future__ import annotations

from functools import lru_cache

import cv2

__all__ = ["BASE", "EXTENDED", "FAMILIES", "family_for", "family_name", "family_size", "dictionary"]

BASE = "36h11"
EXTENDED = "36h11x1024"
FAMILIES = (BASE, EXTENDED)          # smallest first
_SIZES = {BASE: 587, EXTENDED: 1024}
_NAMES = {BASE: "AprilTag 36h11",
          EXTENDED: "AprilTag 36h11 extended to 1024 codes (OpenCV extendDictionary, seed 0)"}


def family_size(family: str) -> int:
    return _SIZES[family]


def family_name(family: str) -> str:
    return _NAMES[family]


def family_for(max_id: int) -> str | None:
    """The smallest family that prints ids 0..max_id, or None if none does."""
    for family in FAMILIES:
        if max_id < _SIZES[family]:
            return family
    return None


@lru_cache(maxsize=None)
def dictionary(family: str) -> cv2.aruco.Dictionary:
    """The family's OpenCV dictionary (the extension takes ~4 s to generate, once per process)."""
    base = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    if family == BASE:
        return base
    if family == EXTENDED:
        return cv2.aruco.extendDictionary(_SIZES[EXTENDED], 6, base, 0)
    raise ValueError(f"unknown tag family {family!r}: one of {', '.join(FAMILIES)}")
