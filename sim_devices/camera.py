"""Simulated camera (docs/protocols.md §6): an HTTP snapshot endpoint that renders the world's
AprilTags and truss from the true camera pose with `sim_devices.render.render_tags`.

`GET <the rig's path>` (the sim rig's `/frame.jpg`) renders the view at the moment of the request
and sends it as an IP camera does: a JPEG at the camera's `jpeg_quality` (`image/jpeg`), or with
jpeg_quality 0 a lossless PNG (`image/png`, the detector then sees exactly the rendered pixels);
the Content-Type says which, whatever the path's extension.  Headers `X-Frame-Seq` and
`X-Frame-Time-S`.  `GET /intrinsics.json` reports the camera's nominal model (the rig's
`[sim.camera]` as written, what its calibration file holds), never the true lens the frames are
rendered with: as a real camera, it does not know its own lens's errors.  `GET /id`.

The frame shows the truss built so far too (`sim_devices.render_truss`: struts and nodes in front
of and behind the tags), always, imaged as the tags are (the lens's depth of field, vignetting
and light, the sensor's noise, then the JPEG).

Known limitations: those of the renderer (no shadows, no glare, no motion blur: a frame taken
while something moves shows one instant); JPEG is OpenCV's baseline encoder with its default
4:2:0 chroma subsampling, not a particular camera's."""

from __future__ import annotations

import itertools
import threading
import time

import cv2
import numpy as np

from sim_devices.http_server import Reply, json_reply
from sim_devices.line_server import E_INTERNAL, E_SYNTAX, Refuse
from sim_devices.world import SimWorld

MODEL = "LAB-SIMCAM"


def encode_frame(img: np.ndarray, jpeg_quality: int) -> tuple[bytes, str]:
    """(bytes, content type) of a frame as the camera sends it: JPEG at `jpeg_quality` (1..100), or
    a lossless PNG for 0."""
    if jpeg_quality > 0:
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
        if not ok:
            raise Refuse(E_INTERNAL, "JPEG encoding failed")
        return buf.tobytes(), "image/jpeg"
    ok, buf = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise Refuse(E_INTERNAL, "PNG encoding failed")
    return buf.tobytes(), "image/png"


def camera_routes(world: SimWorld, name: str = "camera", frame_path: str = "/frame.jpg"):
    cam = world.camera
    assert cam is not None
    counter = itertools.count(1)
    # what the maker states, not the lens the frames are rendered with (TrueCamera.K, .dist)
    assert cam.nominal_K is not None and cam.nominal_dist is not None
    nominal_K, nominal_dist = cam.nominal_K, cam.nominal_dist
    lock = threading.Lock()

    def no_args(q: dict[str, str], path: str) -> None:
        if q:
            raise Refuse(E_SYNTAX, f"{path} takes no parameters, got {sorted(q)}")

    def frame(q: dict[str, str], stuck: bool) -> Reply:
        no_args(q, frame_path)
        t = time.time()
        body, content_type = encode_frame(world.render(), cam.jpeg_quality)
        with lock:
            seq = next(counter)
        return 200, content_type, body, {"X-Frame-Seq": str(seq), "X-Frame-Time-S": f"{t:.6f}"}

    def intrinsics(q: dict[str, str], stuck: bool) -> Reply:
        no_args(q, "/intrinsics.json")
        return json_reply({
            "format": "lab-camera-calibration", "version": 1, "camera": name, "model": "opencv-pinhole-radtan",
            "width_px": cam.width_px, "height_px": cam.height_px, "K": nominal_K.tolist(), "dist": nominal_dist.tolist(),
            "rms_reprojection_px": None, "source": "simulated camera: nominal model (not the true lens)",
            "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(world.started_s)),
        })

    def ident(q: dict[str, str], stuck: bool) -> Reply:
        no_args(q, "/id")
        return json_reply({"device": "camera", "model": MODEL, "name": name, "width_px": cam.width_px,
                           "height_px": cam.height_px})

    return {frame_path: frame, "/intrinsics.json": intrinsics, "/id": ident}
