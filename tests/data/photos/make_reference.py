"""Write reference.json: the tags in each photograph here, as the AprilTag 3 C library finds them
(pupil-apriltags, quad_decimate 1, its most sensitive setting), in our corner convention, plus the
tags only our detector finds, marked so; those were checked by eye (README.md).

    PYTHONPATH=. python tests/data/photos/make_reference.py

Needs pupil-apriltags (`pip install -e '.[test]'`).
"""

from __future__ import annotations

import json
import os
import sys

import cv2
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
PHOTOS = sorted(f for f in os.listdir(HERE) if f.endswith((".jpg", ".png")))


def _same(a: tuple[int, np.ndarray], b: tuple[int, np.ndarray]) -> bool:
    side = float(np.mean(np.linalg.norm(np.roll(b[1], -1, axis=0) - b[1], axis=1)))
    return a[0] == b[0] and float(np.linalg.norm(a[1].mean(axis=0) - b[1].mean(axis=0))) < 0.5 * side


def main() -> int:
    from lab.studies import apriltag3
    from estimation.fiducials import DetectorConfig, TagDetector

    ours = TagDetector(np.eye(3), np.zeros(5), {i: 1.0 for i in range(587)}, DetectorConfig(quiet_zone=False))
    out = {"convention": "corners in OpenCV pixel coordinates (pixel centres at integers), in aruco's order "
                         "(top-left, top-right, bottom-right, bottom-left of OpenCV 4's marker image); "
                         "AprilTag 3's corners p converted as p[[1, 0, 3, 2]] - 0.5",
           "made_with": apriltag3.version() + ", Detector(families='tag36h11', quad_decimate=1.0)",
           "photos": []}
    for name in PHOTOS:
        grey = cv2.imread(os.path.join(HERE, name), cv2.IMREAD_GRAYSCALE)
        ref = [(d.tag_id, d.corners_px) for d in apriltag3.detect(grey)]
        ids, corners = ours.find(grey)
        extra = [(t, c) for t, c in zip(ids, corners) if not any(_same((t, c), r) for r in ref)]
        tags = ([{"id": t, "corners": np.round(c, 4).tolist(), "source": "apriltag3"} for t, c in ref]
                + [{"id": t, "corners": np.round(c, 4).tolist(), "source": "lab detector only"} for t, c in extra])
        out["photos"].append({"file": name, "width": grey.shape[1], "height": grey.shape[0],
                              "ids": sorted({t["id"] for t in tags}), "tags": tags})
        print(f"{name}: {len(ref)} from AprilTag 3, {len(extra)} only ours", file=sys.stderr)
    # one line per tag, so a diff shows which tag changed
    lines = ["{", f' "convention": {json.dumps(out["convention"])},', f' "made_with": {json.dumps(out["made_with"])},',
             ' "photos": [']
    for k, photo in enumerate(out["photos"]):
        head = {key: photo[key] for key in ("file", "width", "height", "ids")}
        lines.append("  " + json.dumps(head)[:-1] + ', "tags": [')
        lines += ["   " + json.dumps(t) + ("," if i + 1 < len(photo["tags"]) else "") for i, t in enumerate(photo["tags"])]
        lines.append("  ]}" + ("," if k + 1 < len(out["photos"]) else ""))
    lines += [" ]", "}"]
    with open(os.path.join(HERE, "reference.json"), "w") as f:
        f.write("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
