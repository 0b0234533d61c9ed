"""`lab review RUN.mcap`: a run in Rerun, laid out for a person to look at.

Plain `rerun RUN.mcap` already shows the Foxglove channels (images, calibration, /tf, poses, logs).
This adds what the raw channels don't say by themselves:

- `world/...`          one 3D scene, z up.  Every frame named in /tf gets an entity `world/<frame>`
                       placed by the chain of recorded transforms (resolved here, so the scene does
                       not depend on the viewer's frame handling); data in frame F lives under it.
- `world/structure/design`   the design structure: nodes, struts, tag outlines with labels and face
                       normals (from the run's /structure record, else rebuilt with lab.core.structures
                       from the start record's structure name, e.g. "borg:3", "tetrahelix:20").
- `world/<frame>/estimate/tags`  estimated tag outlines per step, with error lines to the design.
- `world/<frame>/estimate/<entity>`  other estimated poses (axes), `world/paths/<name>` their path.
- `world/<camera>/image`  camera images with the pinhole from the calibration and the detected tag
                       corners on top; `world/paths/<camera>` the camera path.
- `plots/...`          scalars over steps: tag position errors (per tag and max/mean), verdict
                       errors, metrics (residuals, costs), strut length errors.
- `verdicts`, `steps`, `log`, `operator`, `comms/<device>`, `records/<kind>`  text logs.
- `run/info`           the start and stop records as a markdown document.

Timelines: `step` (the index of the step the message was written in) and `time` (log time).
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lab.core.errors import UserError
from lab.core.geometry import Pose3
from lab.core.recorder import messages as m
from lab.core.recorder import topics
from lab.core.recorder.reader import RecordedMessage, ScanState, iter_messages
from lab.core.verdicts import FLAGGED, OK, UNCERTAIN, UNVERIFIED

DESIGN_COLOR = (150, 150, 150)
TAG_DESIGN_COLOR = (80, 160, 255)
TAG_ESTIMATE_COLOR = (255, 140, 0)
ERROR_COLOR = (255, 0, 0)
VERDICT_LEVEL = {OK: "INFO", FLAGGED: "WARN", UNCERTAIN: "WARN", UNVERIFIED: "DEBUG"}
LOG_LEVEL = {0: "TRACE", 1: "DEBUG", 2: "INFO", 3: "WARN", 4: "ERROR", 5: "CRITICAL"}


# ---- the design to draw -----------------------------------------------------------------------

@dataclass
class DesignTag:
    id: int
    pose: Pose3           # structure_T_tag (tag frame x right, y up, z out of the face)
    label: str = ""
    module: str = ""
    size_m: float = 0.10


@dataclass
class Design:
    name: str
    frame_id: str
    nodes: np.ndarray                      # (N, 3) m
    edges: list[tuple[int, int]]
    tags: dict[int, DesignTag] = field(default_factory=dict)
    source: str = ""                       # "recorded" or "lab.structures"


def design_from_message(msg: Any) -> Design:
    nodes = np.asarray(msg.node_positions, dtype=float).reshape(-1, 3)
    e = list(msg.edges)
    edges = [(int(e[k]), int(e[k + 1])) for k in range(0, len(e) - 1, 2)]
    tags = {t.id: DesignTag(t.id, m.pose_from_proto(t.pose), t.label, t.module, t.size_m or 0.10) for t in msg.tags}
    return Design(msg.name, msg.frame_id or "structure", nodes, edges, tags, "recorded")


def design_from_spec(spec: str) -> Design | None:
    """Rebuild a design from its name with lab.core.structures: "borg", "borg:N", "borg:N:SPACING",
    or a truss name ("tetrahelix:20", "telescope:84").  None if the generators are unavailable."""
    spec = spec.strip()
    if not spec:
        return None
    kind, _, rest = spec.partition(":")
    try:
        if kind == "borg":
            from lab.core.structures.borg import build_borg

            parts = [p for p in rest.split(":") if p]
            n = int(parts[0]) if parts else 3
            model = build_borg(n, float(parts[1])) if len(parts) > 1 else build_borg(n)
            tags = {tid: DesignTag(tid, t.structure_T_tag, t.label, t.module, t.size_m) for tid, t in model.tags.items()}
            return Design(spec, "structure", np.asarray(model.nodes, dtype=float), list(model.edges), tags,
                          "lab.structures")
        from lab.core.structures.trusses import build_truss

        model = build_truss(spec)
        return Design(spec, "structure", np.asarray(model.nodes, dtype=float), list(model.edges), {}, "lab.structures")
    except (ImportError, AttributeError):
        return None  # the generators are not there (yet): draw only what the run recorded


def structure_spec(start: Any) -> str:
    """The structure a run worked on: RunStart.structure, else params/scenario "structure"."""
    if start is None:
        return ""
    if start.structure:
        return start.structure
    for blob in (start.params_json, start.scenario_json):
        try:
            value = json.loads(blob or "{}")
        except json.JSONDecodeError:
            continue
        if isinstance(value, dict) and isinstance(value.get("structure"), str):
            return value["structure"]
    return ""


# ---- frames -----------------------------------------------------------------------------------

def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_\-]", "_", name.strip("/")) or "_"


class FrameTree:
    """parent_T_child transforms from /tf, resolved to the root of each chain."""

    def __init__(self) -> None:
        self.parent: dict[str, tuple[str, Pose3]] = {}

    def set(self, parent: str, child: str, p: Pose3) -> None:
        self.parent[child] = (parent, p)

    def root_T(self, frame: str) -> tuple[str, Pose3]:
        """(root frame, root_T_frame); a frame with no recorded parent is its own root."""
        acc = Pose3()
        seen = {frame}
        f = frame
        while f in self.parent:
            parent, p = self.parent[f]
            acc = p.compose(acc)
            if parent in seen:  # a cycle in /tf: stop rather than loop
                break
            seen.add(parent)
            f = parent
        return f, acc

    def descendants(self, frame: str) -> list[str]:
        """Frames whose chain to the root passes through `frame`."""
        out = []
        for child in self.parent:
            f, seen = child, {child}
            while f in self.parent:
                f = self.parent[f][0]
                if f == frame and child != frame:
                    out.append(child)
                    break
                if f in seen:
                    break
                seen.add(f)
        return out


def frame_entity(frame: str) -> str:
    """The entity of frame `frame` in the 3D scene ("world" for the world frame itself)."""
    return "world" if frame in ("", "world") else f"world/{_safe(frame)}"


# ---- geometry to draw -------------------------------------------------------------------------

def tag_outline(p: Pose3, size_m: float) -> np.ndarray:
    """The 5-point closed outline of a tag's black square, in the pose's parent frame."""
    h = size_m / 2
    corners = np.array([[-h, -h, 0], [h, -h, 0], [h, h, 0], [-h, h, 0], [-h, -h, 0]])
    R, t = p.rotation().matrix(), p.translation()
    return corners @ R.T + t


@dataclass
class ReviewReport:
    path: Path
    messages: int
    steps: int
    result: str
    design: str               # what was drawn: "borg:3 (lab.structures)", or "" if none
    entities: list[str]
    scan: ScanState
    recording_id: str = ""
    sink: Any = None          # lab.core.viewer.Sink: where the recording went


class _Review:
    def __init__(self, rec: Any, live: bool = False) -> None:
        """`live`: messages arrive one by one as the run writes them (lab.core.live), so the design and
        the image entities are learnt from the messages instead of from a look at the whole file."""
        import rerun as rr

        self.rr = rr
        self.rec = rec
        self.live = live
        self.tree = FrameTree()
        self.step = -1
        self.start: Any = None
        self.stop: Any = None
        self.design: Design | None = None
        self.design_T: dict[str, Pose3] = {}
        self.calib: dict[str, Any] = {}
        self.image_entity: dict[str, str] = {}
        self.paths: dict[str, list[np.ndarray]] = {}
        self.path_frames: set[str] = set()
        self.entities: set[str] = set()
        self.steps_done = 0

    # -- plumbing
    def log(self, entity: str, *archetypes: Any, static: bool = False) -> None:
        self.entities.add(entity)
        self.rec.log(entity, *archetypes, static=static)

    def set_time(self, r: RecordedMessage) -> None:
        self.rec.set_time("time", timestamp=r.log_time_ns * 1e-9)
        if self.step >= 0:
            self.rec.set_time("step", sequence=self.step)

    # -- static scene
    def draw_static(self) -> None:
        self.log("world", self.rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        if self.design is not None:
            self.draw_design(self.design)

    def setup(self, messages: list[RecordedMessage], path: Path) -> None:
        """Read what the scene needs before anything is logged: the design and the image entities."""
        recorded = [r.message for r in messages if r.topic == topics.STRUCTURE]
        self.start = next((r.message for r in messages if r.topic == topics.RUN_START), None)
        if recorded:
            self.design = design_from_message(recorded[-1])
        else:
            self.design = design_from_spec(structure_spec(self.start))
        # Images go under their camera frame when the run placed that frame; else a 2D entity.
        tf_children = {r.message.child_frame_id for r in messages if r.topic == topics.TF}
        for r in messages:
            if r.schema_name == "foxglove.CompressedImage" and r.topic not in self.image_entity:
                fid = r.message.frame_id
                self.image_entity[r.topic] = (f"{frame_entity(fid)}/image" if fid in tf_children
                                              else f"images/{_safe(r.topic)}")
        self.path_frames = set(r.message.frame_id for r in messages if r.schema_name == "foxglove.CompressedImage")

    def draw_design(self, d: Design) -> None:
        rr = self.rr
        base = f"{frame_entity(d.frame_id)}/design"
        if len(d.nodes):
            self.log(f"{base}/nodes", rr.Points3D(d.nodes, radii=0.012, colors=DESIGN_COLOR), static=True)
        if d.edges:
            strips = [[d.nodes[i], d.nodes[j]] for i, j in d.edges]
            self.log(f"{base}/edges", rr.LineStrips3D(strips, radii=0.004, colors=DESIGN_COLOR), static=True)
        if d.tags:
            ids = sorted(d.tags)
            outlines = [tag_outline(d.tags[i].pose, d.tags[i].size_m) for i in ids]
            labels = [f"{i} {d.tags[i].label}".strip() for i in ids]
            self.log(f"{base}/tags", rr.LineStrips3D(outlines, radii=0.003, colors=TAG_DESIGN_COLOR, labels=labels),
                     static=True)
            origins = np.array([d.tags[i].pose.translation() for i in ids])
            normals = np.array([d.tags[i].pose.rotation().matrix()[:, 2] * d.tags[i].size_m * 0.6 for i in ids])
            self.log(f"{base}/tag_normals", rr.Arrows3D(origins=origins, vectors=normals, colors=TAG_DESIGN_COLOR),
                     static=True)

    def info_document(self, path: Path, scan: ScanState) -> None:
        s, stop = self.start, self.stop
        lines = [f"# Run `{path.name}`", ""]
        if s is not None:
            lines += [f"- procedure: **{s.procedure}**  (run id {s.run_id})",
                      f"- started: {_iso(m.timestamp_s(s.start_time))} on {s.hostname}",
                      f"- git: {s.git_sha or 'unknown'}{' (dirty)' if s.git_dirty else ''}",
                      f"- structure: {structure_spec(s) or 'not named'}",
                      f"- argv: `{' '.join(s.argv)}`"]
        else:
            lines.append("- **no start record**")
        if stop is not None:
            lines += [f"- result: **{stop.result}**{' (recovered file)' if stop.recovered else ''}",
                      f"- reason: {stop.reason or '-'}",
                      f"- steps completed: {stop.steps_completed}, duration {stop.duration_s:.1f} s"]
        else:
            lines.append(f"- **no stop record**: the recording was cut short ({scan.stop_reason}); "
                         f"{self.steps_done} steps completed")
        if self.design is not None:
            lines.append(f"- design drawn: {self.design.name} ({self.design.source}, {len(self.design.nodes)} nodes, "
                         f"{len(self.design.edges)} struts, {len(self.design.tags)} tags)")
        if s is not None:
            for title, blob in (("Parameters", s.params_json), ("Rig", s.rig_json), ("Scenario", s.scenario_json)):
                if blob and blob != "{}":
                    lines += ["", f"## {title}", "```json", _pretty(blob), "```"]
            if s.versions:
                lines += ["", "## Versions", *[f"- {k}: {v}" for k, v in sorted(s.versions.items())]]
        if stop is not None and stop.traceback:
            lines += ["", "## Traceback", "```", stop.traceback, "```"]
        self.log("run/info", self.rr.TextDocument("\n".join(lines), media_type=self.rr.MediaType.MARKDOWN), static=True)

    # -- per message
    def handle(self, r: RecordedMessage) -> None:
        rr, msg, topic = self.rr, r.message, r.topic
        if topic == topics.RUN_STEP:
            if msg.phase == "start":
                self.step = msg.index
            self.set_time(r)
            level = "ERROR" if msg.phase == "error" else "INFO"
            text = f"step {msg.index} {msg.name}: {msg.phase}"
            if msg.phase != "start":
                text += f" after {msg.duration_s:.2f} s"
            if msg.error:
                text += f" ({msg.error})"
            self.steps_done += msg.phase == "end"
            self.log("steps", rr.TextLog(text, level=level))
            return
        self.set_time(r)
        name = r.schema_name
        if topic == topics.RUN_START:
            self.start = msg
        elif topic == topics.RUN_STOP:
            self.stop = msg
            level = {"completed": "INFO", "aborted": "WARN"}.get(msg.result, "ERROR")
            self.log("steps", rr.TextLog(f"run {msg.result}: {msg.reason}", level=level))
        elif name == "foxglove.FrameTransform":
            self.on_transform(msg)
        elif name == "foxglove.CameraCalibration":
            self.calib[msg.frame_id] = msg
        elif name == "foxglove.CompressedImage":
            self.on_image(topic, msg)
        elif name == "lab.TagDetections":
            self.on_detections(msg)
        elif name == "lab.PoseEstimateSet":
            self.on_tag_estimates(msg)
        elif name == "foxglove.PosesInFrame" and topic == topics.TAG_POSES:
            pass  # drawn from the PoseEstimateSet written alongside, which has the tag ids
        elif name == "foxglove.PosesInFrame":
            pts = [[p.position.x, p.position.y, p.position.z] for p in msg.poses]
            self.log(f"{frame_entity(msg.frame_id)}/estimate/{_safe(topic)}", rr.Points3D(pts, radii=0.01))
        elif name == "foxglove.PoseInFrame":
            entity = topic[len(topics.ESTIMATE_PREFIX):] if topic.startswith(topics.ESTIMATE_PREFIX) else topic
            self.on_pose(entity, msg.frame_id, m.pose_from_proto(msg.pose))
        elif name == "lab.PoseEstimate":
            pass  # the covariance companion of a PoseInFrame already drawn
        elif name == "lab.ModuleVerdict":
            self.on_verdict(msg)
        elif name == "lab.Metric":
            self.log(f"plots/{_plot_name(msg.name)}", rr.Scalars([msg.value]))
        elif name == "lab.LengthMeasurement":
            if msg.nominal_m and msg.measured_m:
                strut = _safe(msg.strut or f"{msg.node_a}-{msg.node_b}")
                self.log(f"plots/length_error_mm/{strut}", rr.Scalars([(msg.measured_m - msg.nominal_m) * 1e3]))
        elif name == "foxglove.Log":
            self.log("log", rr.TextLog(msg.message, level=LOG_LEVEL.get(msg.level, "INFO")))
        elif name == "lab.DeviceIO":
            text = msg.text.rstrip("\n") if msg.text else repr(bytes(msg.data))
            note = f"  ({msg.note})" if msg.note else ""
            self.log(f"comms/{_safe(msg.device)}", rr.TextLog(f"{msg.direction} {text}{note}", level="DEBUG"))
        elif name == "lab.OperatorPrompt":
            who = "auto" if msg.automatic else "operator"
            self.log("operator", rr.TextLog(f"{msg.question} -> {msg.answer} ({who})"))
        elif name == "lab.JsonRecord":
            self.log(f"records/{_safe(msg.kind)}", rr.TextLog(_shorten(msg.json, 4000)))
        elif name == "lab.StructureDesign":
            if self.live:   # a review draws it from setup(), before the first message
                self.design = design_from_message(msg)
                self.draw_design(self.design)

    def on_transform(self, msg: Any) -> None:
        rr = self.rr
        p = m.pose_from_proto(_pose_of_transform(msg))
        self.tree.set(msg.parent_frame_id, msg.child_frame_id, p)
        for frame in [msg.child_frame_id, *self.tree.descendants(msg.child_frame_id)]:
            root, root_T = self.tree.root_T(frame)
            if frame_entity(frame) == frame_entity(root):
                continue
            q = m.pose_to_proto(root_T).orientation
            self.log(frame_entity(frame), rr.Transform3D(translation=root_T.translation(),
                                                         quaternion=rr.Quaternion(xyzw=[q.x, q.y, q.z, q.w])),
                     rr.TransformAxes3D(0.1))
            if frame in self.path_frames:
                self.extend_path(frame, root_T.translation())

    def extend_path(self, name: str, point: np.ndarray) -> None:
        pts = self.paths.setdefault(name, [])
        pts.append(np.asarray(point, dtype=float))
        self.log(f"world/paths/{_safe(name)}", self.rr.LineStrips3D([np.array(pts)], radii=0.004),
                 self.rr.Points3D(np.array(pts), radii=0.01))

    def on_image(self, topic: str, msg: Any) -> None:
        rr = self.rr
        if self.live and topic not in self.image_entity:
            # live, the camera's transform may come just after its first image: an image with a
            # frame goes under that frame, as the review puts it once the run placed the frame
            self.image_entity[topic] = f"{frame_entity(msg.frame_id)}/image" if msg.frame_id else f"images/{_safe(topic)}"
            self.path_frames.add(msg.frame_id)
        entity = self.image_entity.get(topic, f"images/{_safe(topic)}")
        cal = self.calib.get(msg.frame_id)
        if cal is not None and entity.startswith("world/"):
            K = np.asarray(cal.K, dtype=float).reshape(3, 3)
            self.log(entity, rr.Pinhole(image_from_camera=K, resolution=[cal.width, cal.height],
                                        camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=0.2))
        media = "image/png" if msg.format.lower() == "png" else "image/jpeg"
        self.log(entity, rr.EncodedImage(contents=bytes(msg.data), media_type=media))

    def on_detections(self, msg: Any) -> None:
        rr = self.rr
        if not msg.detections:
            return
        entity = next((e for t, e in self.image_entity.items() if e.startswith(frame_entity(msg.frame_id) + "/")),
                      f"images/{_safe(msg.frame_id)}")
        quads = []
        labels = []
        for det in msg.detections:
            c = np.asarray(det.corners_px, dtype=float).reshape(-1, 2)
            quads.append(np.vstack([c, c[:1]]))
            labels.append(str(det.tag_id))
            if not math.isnan(det.reprojection_error_px):
                self.log(f"plots/reprojection_error_px/{det.tag_id}", rr.Scalars([det.reprojection_error_px]))
        self.log(f"{entity}/detections", rr.LineStrips2D(quads, colors=(0, 255, 0), labels=labels))

    def on_tag_estimates(self, msg: Any) -> None:
        rr = self.rr
        base = f"{frame_entity(msg.frame_id)}/estimate/tags"
        outlines, labels, errs, lines = [], [], [], []
        d = self.design
        est_T_design = self.frame_transform(d.frame_id, msg.frame_id) if d is not None else None
        for est in msg.estimates:
            tid = m.tag_id_of(est.entity)
            p = m.pose_from_proto(est.pose)
            size = d.tags[tid].size_m if d is not None and tid in d.tags else 0.10
            outlines.append(tag_outline(p, size))
            labels.append(str(tid) if tid is not None else est.entity)
            if tid is not None and d is not None and tid in d.tags and est_T_design is not None:
                design_in_est = est_T_design.compose(d.tags[tid].pose)  # the design pose, in the estimate's frame
                err = float(np.linalg.norm(p.translation() - design_in_est.translation()))
                errs.append(err)
                lines.append([design_in_est.translation(), p.translation()])
                self.log(f"plots/tag_error_mm/{tid}", rr.Scalars([err * 1e3]))
        if outlines:
            self.log(f"{base}", rr.LineStrips3D(outlines, radii=0.003, colors=TAG_ESTIMATE_COLOR, labels=labels))
        if lines:
            self.log(f"{base}/errors", rr.LineStrips3D(lines, radii=0.002, colors=ERROR_COLOR))
        if errs:
            self.log("plots/tag_error_mm/max", rr.Scalars([max(errs) * 1e3]))
            self.log("plots/tag_error_mm/mean", rr.Scalars([float(np.mean(errs)) * 1e3]))

    def frame_transform(self, a: str, b: str) -> Pose3 | None:
        """b_T_a from the transforms so far (identity if a == b), None if not connected."""
        if a == b:
            return Pose3()
        ra, root_T_a = self.tree.root_T(a)
        rb, root_T_b = self.tree.root_T(b)
        if ra != rb:
            return None
        return root_T_b.inverse().compose(root_T_a)

    def on_pose(self, entity: str, frame_id: str, p: Pose3) -> None:
        rr = self.rr
        q = m.pose_to_proto(p).orientation
        self.log(f"{frame_entity(frame_id)}/estimate/{_safe(entity)}",
                 rr.Transform3D(translation=p.translation(), quaternion=rr.Quaternion(xyzw=[q.x, q.y, q.z, q.w])),
                 rr.TransformAxes3D(0.08))
        root, root_T_frame = self.tree.root_T(frame_id)
        self.extend_path(f"estimate_{entity}", root_T_frame.compose(p).translation())

    def on_verdict(self, msg: Any) -> None:
        rr = self.rr
        parts = [f"{msg.module}: {msg.verdict.upper()}"]
        if not math.isnan(msg.position_error_m):
            parts.append(f"position error {msg.position_error_m * 1e3:.2f} mm")
            self.log(f"plots/verdict_position_error_mm/{_safe(msg.module)}", rr.Scalars([msg.position_error_m * 1e3]))
        if not math.isnan(msg.rotation_error_rad):
            parts.append(f"rotation error {math.degrees(msg.rotation_error_rad):.3f} deg")
            self.log(f"plots/verdict_rotation_error_deg/{_safe(msg.module)}",
                     rr.Scalars([math.degrees(msg.rotation_error_rad)]))
        if msg.rejected_tag_ids:
            parts.append(f"rejected tags {list(msg.rejected_tag_ids)}")
        if msg.reason:
            parts.append(msg.reason)
        self.log("verdicts", rr.TextLog(", ".join(parts), level=VERDICT_LEVEL.get(msg.verdict, "INFO")))


def _pose_of_transform(msg: Any) -> Any:
    from foxglove_schemas_protobuf.Pose_pb2 import Pose as FoxglovePose

    p = FoxglovePose()
    p.position.CopyFrom(msg.translation)
    p.orientation.CopyFrom(msg.rotation)
    return p


def _plot_name(name: str) -> str:
    return "/".join(_safe(p) for p in name.split("/") if p) or "_"


def _pretty(blob: str) -> str:
    try:
        return _shorten(json.dumps(json.loads(blob), indent=1, sort_keys=True), 20000)
    except json.JSONDecodeError:
        return _shorten(blob, 20000)


def _shorten(text: str, n: int) -> str:
    return text if len(text) <= n else text[:n] + f"... ({len(text) - n} more characters)"


def _iso(t_s: float) -> str:
    import datetime as dt

    return dt.datetime.fromtimestamp(t_s, tz=dt.timezone.utc).isoformat(timespec="seconds")


APPLICATION_ID = "lab_review"

# Plot groups of the saved layout: (tab name, origin, contents).  Per-tag curves stay in the store
# (the selection panel finds them) but the default tabs show summaries, not 151 lines at once.
PLOT_GROUPS = [
    ("tag error (mm)", "plots/tag_error_mm", ["+ $origin/max", "+ $origin/mean"]),
    ("verdict position error (mm)", "plots/verdict_position_error_mm", ["+ $origin/**"]),
    ("verdict rotation error (deg)", "plots/verdict_rotation_error_deg", ["+ $origin/**"]),
    ("reprojection error (px)", "plots/reprojection_error_px", ["+ $origin/**"]),
    ("strut length error (mm)", "plots/length_error_mm", ["+ $origin/**"]),
    ("metrics", "plots", ["+ $origin/**", "- plots/tag_error_mm/**", "- plots/verdict_position_error_mm/**",
                          "- plots/verdict_rotation_error_deg/**", "- plots/reprojection_error_px/**",
                          "- plots/length_error_mm/**"]),
]


def recording_id(start: Any, path: Path) -> str:
    """One recording id per run: the run's own id from its start record (so two runs opened in one
    viewer stay apart, and a run reviewed twice replaces itself), else one from the file's path."""
    if start is not None and getattr(start, "run_id", ""):
        return f"lab-run-{start.run_id}"
    import hashlib

    return "lab-file-" + hashlib.sha1(str(Path(path).resolve()).encode()).hexdigest()[:12]


def make_blueprint(image_entities: list[str], entities: set[str] | None = None) -> Any:
    """The layout a run opens with: the 3D structure on the left; on the right the camera image with
    its detections, the verdicts as they came (on the step timeline), and tabs of grouped plots;
    steps, log, operator and the run's info document in tabs below.  `entities`: what was logged,
    to leave out plot tabs with nothing in them (None: keep every tab, e.g. for a live run)."""
    import rerun.blueprint as rrb

    def present(origin: str) -> bool:
        return entities is None or any(e == origin or e.startswith(origin + "/") for e in entities)

    plots = [rrb.TimeSeriesView(name=name, origin=origin, contents=contents)
             for name, origin, contents in PLOT_GROUPS if present(origin)]
    right: list[Any] = [rrb.Spatial2DView(name="camera", origin=e) for e in image_entities[:1]]
    right.append(rrb.TextLogView(name="verdicts", origin="verdicts"))
    if plots:
        right.append(rrb.Tabs(*plots))
    logs = rrb.Tabs(rrb.TextLogView(name="steps", origin="steps"), rrb.TextLogView(name="log", origin="log"),
                    rrb.TextLogView(name="operator", origin="operator"),
                    rrb.TextDocumentView(name="run", origin="run/info"))
    scene = rrb.Spatial3DView(name="structure", origin="world")
    return rrb.Blueprint(rrb.Vertical(rrb.Horizontal(scene, rrb.Vertical(*right), column_shares=[3, 2]), logs,
                                      row_shares=[4, 1]),
                         collapse_panels=False)


def review(path: str | Path, save: str | Path | None = None, *, spawn: bool | None = None,
           mode: str | None = None, connect: str | None = None) -> ReviewReport:
    """Log the run at `path` into Rerun.  `mode` (lab.core.viewer.choose_mode): "save" writes `save` as an
    .rrd, "spawn" a local viewer, "web" the web viewer on loopback (the report's `sink.web` is then
    running: the caller keeps it up and stops it), "connect" a running viewer at `connect`, "none"
    nothing (tests of the mapping).  Default: "save" with `save`, else a local viewer where there is
    a display and the web viewer where there is none (spawn=False: "none")."""
    import rerun as rr

    from lab.core import viewer

    src = Path(path)
    scan = ScanState()
    messages = list(iter_messages(src, state=scan))
    if not messages:
        raise UserError(f"{src} holds no complete message ({scan.stop_reason})")
    if mode is None:
        mode = "none" if spawn is False and save is None else viewer.choose_mode(save, connect, False)
    start = next((r.message for r in messages if r.topic == topics.RUN_START), None)
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id(start, src))
    view = _Review(rec)
    view.setup(messages, src)
    # the image entities are known before anything is logged, and the plot groups by name: the
    # layout goes to the sink first, so a viewer shows the run laid out from its first message
    sink = viewer.attach(rec, mode, blueprint=make_blueprint(sorted(set(view.image_entity.values()))), save=save,
                         connect=connect)
    try:
        with rec:
            view.draw_static()
            for r in messages:
                view.handle(r)
            rec.reset_time()
            view.info_document(src, scan)
            # now that every entity is known: the same layout without empty plot tabs
            rec.send_blueprint(make_blueprint(sorted(set(view.image_entity.values())), view.entities))
        rec.flush(timeout_sec=60.0)
        # closes the file (footer written); a web viewer's proxy keeps what it received for the
        # browser, and stopping it later leaves no severed connection for the SDK to complain about
        rec.disconnect()
    except BaseException:
        if sink.web is not None:
            sink.web.stop()
        raise
    design = f"{view.design.name} ({view.design.source})" if view.design is not None else ""
    result = view.stop.result if view.stop is not None else "unknown (no stop record)"
    return ReviewReport(src, len(messages), view.steps_done, result, design, sorted(view.entities), scan,
                        rec.get_recording_id() or "", sink)


def rrd_entity_paths(path: str | Path) -> set[str]:
    """Entity paths stored in an .rrd file (rerun.chunk.RrdReader), for tests and checks."""
    from rerun.chunk import RrdReader

    return {chunk.entity_path for chunk in RrdReader(Path(path)).stream()}


__all__ = ["review", "make_blueprint", "recording_id", "ReviewReport", "Design", "DesignTag", "design_from_spec", "design_from_message",
           "structure_spec", "FrameTree", "frame_entity", "rrd_entity_paths"]
