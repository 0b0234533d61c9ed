"""Simulated camera (docs/protocols.md §6): an HTTP snapshot endpoint that renders the world's
AprilTags from the true camera pose with `sim_devices.render.render_tags`.

`GET /frame.png` renders the view at the moment of the request (a lossless PNG, so the detector
sees exactly the rendered pixels), with `X-Frame-Seq` and `X-Frame-Time-S` headers;
`GET /intrinsics.json` reports the true camera model in the calibration-file format; `GET /id`.

The frame shows the truss built so far too (`sim_devices.render_truss`: struts and nodes in front
of and behind the tags), always.

Known limitations: those of the renderer (no lighting model for the tags, no shadows, no motion
blur: a frame taken while something moves shows one instant)."""

from __future__ import annotations

import itertools
import threading
import time

import cv2

from sim_devices.http_server import Reply, json_reply
from sim_devices.line_server import E_INTERNAL, E_SYNTAX, Refuse
from sim_devices.world import SimWorld

MODEL = "LAB-SIMCAM"


def camera_routes(world: SimWorld, name: str = "camera", frame_path: str = "/frame.png"):
    cam = world.camera
    assert cam is not None
    counter = itertools.count(1)
    lock = threading.Lock()

    def no_args(q: dict[str, str], path: str) -> None:
        if q:
            raise Refuse(E_SYNTAX, f"{path} takes no parameters, got {sorted(q)}")

    def frame(q: dict[str, str], stuck: bool) -> Reply:
        no_args(q, frame_path)
        t = time.time()
        img = world.render()
        ok, png = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 1])
        if not ok:
            raise Refuse(E_INTERNAL, "PNG encoding failed")
        with lock:
            seq = next(counter)
        return 200, "image/png", png.tobytes(), {"X-Frame-Seq": str(seq), "X-Frame-Time-S": f"{t:.6f}"}

    def intrinsics(q: dict[str, str], stuck: bool) -> Reply:
        no_args(q, "/intrinsics.json")
        return json_reply({
            "format": "lab-camera-calibration", "version": 1, "camera": name, "model": "opencv-pinhole-radtan",
            "width_px": cam.width_px, "height_px": cam.height_px, "K": cam.K.tolist(), "dist": cam.dist.tolist(),
            "rms_reprojection_px": 0.0, "source": "simulated camera: true model",
            "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(world.started_s)),
        })

    def ident(q: dict[str, str], stuck: bool) -> Reply:
        no_args(q, "/id")
        return json_reply({"device": "camera", "model": MODEL, "name": name, "width_px": cam.width_px,
                           "height_px": cam.height_px})

    return {frame_path: frame, "/intrinsics.json": intrinsics, "/id": ident}
