"""Our own protobuf messages for the domain records of a run (package `lab`), plus helpers that
turn `Pose3` / covariances into messages and back.

No `protoc` is needed: the `.proto` below is built at import time as a `FileDescriptorProto`,
added to protobuf's default descriptor pool, and the message classes are made from it.  The schema
written into each MCAP file is that same descriptor (mcap-protobuf-support serialises it with its
dependencies), so any protobuf-aware reader (Foxglove, Rerun, `mcap` CLI) decodes our records.

Poses inside our messages use `foxglove.Pose` (position + quaternion x, y, z, w); covariances are
6x6 row-major in GTSAM's tangent order (rotation first, then translation; rad and m).  String
enums (`result`, `phase`, `verdict`, `direction`) are plain strings so that generic viewers show
them as words; the allowed values are the tuples below and the helpers check them.

The schema, as a reader sees it::

    message RunStart { google.protobuf.Timestamp start_time = 1; string run_id = 2;
      string procedure = 3; string params_json = 4; string rig_json = 5; string scenario_json = 6;
      string structure = 7; map<string, string> versions = 8; string git_sha = 9; bool git_dirty = 10;
      repeated string argv = 11; string hostname = 12; }
    message RunStop { google.protobuf.Timestamp stop_time = 1; string result = 2; string reason = 3;
      string traceback = 4; uint32 steps_completed = 5; double duration_s = 6; bool recovered = 7;
      string last_step = 8; }
    message StepEvent { timestamp = 1; int32 index = 2; string name = 3; string phase = 4;
      string params_json = 5; double duration_s = 6; string error = 7; }
    message DeviceIO { timestamp = 1; string device = 2; string url = 3; string direction = 4;
      bytes data = 5; string text = 6; string note = 7; }
    message TagDetection { int32 tag_id = 1; repeated double corners_px = 2; foxglove.Pose camera_T_tag = 3;
      repeated double covariance = 4; double reprojection_error_px = 5; double ambiguity_ratio = 6; }
    message TagDetections { timestamp = 1; string frame_id = 2; repeated TagDetection detections = 3; }
    message PoseEstimate { timestamp = 1; string entity = 2; string frame_id = 3; foxglove.Pose pose = 4;
      repeated double covariance = 5; }
    message PoseEstimateSet { timestamp = 1; string frame_id = 2; repeated PoseEstimate estimates = 3; }
    message ModuleVerdict { timestamp = 1; string module = 2; string verdict = 3; string reason = 4;
      double position_error_m = 5; double rotation_error_rad = 6; int32 step_index = 7;
      repeated int32 tag_ids = 8; repeated int32 rejected_tag_ids = 9; }
    message LengthMeasurement { timestamp = 1; string strut = 2; int32 node_a = 3; int32 node_b = 4;
      string device = 5; double nominal_m = 6; double commanded_m = 7; double measured_m = 8;
      double sigma_m = 9; double volts = 10; }
    message OperatorPrompt { timestamp = 1; string question = 2; string answer = 3; bool automatic = 4; }
    message Metric { timestamp = 1; string name = 2; double value = 3; string unit = 4; int32 step_index = 5; }
    message DesignTag { int32 id = 1; string label = 2; string module = 3; foxglove.Pose pose = 4; double size_m = 5; }
    message StructureDesign { timestamp = 1; string name = 2; string frame_id = 3;
      repeated double node_positions = 4; repeated uint32 edges = 5; repeated DesignTag tags = 6; }
    message JsonRecord { timestamp = 1; string kind = 2; string json = 3; }

(`timestamp` is a `google.protobuf.Timestamp` everywhere.)
"""

from __future__ import annotations

import time
from typing import Any, Iterable, Mapping, Sequence

import numpy as np
from foxglove_schemas_protobuf.Pose_pb2 import Pose as FoxglovePose
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from google.protobuf import timestamp_pb2  # noqa: F401  (registers google/protobuf/timestamp.proto)
from google.protobuf.timestamp_pb2 import Timestamp

from lab.core.geometry import Pose3, from_quaternion, to_quaternion
from lab.core.verdicts import VERDICTS, Verdict

PROTO_FILE = "lab/messages.proto"
PACKAGE = "lab"

RUN_RESULTS = ("completed", "aborted", "failed")
STEP_PHASES = ("start", "end", "error")
DIRECTIONS = ("tx", "rx", "event")

_T = descriptor_pb2.FieldDescriptorProto
_SCALARS = {
    "double": _T.TYPE_DOUBLE,
    "string": _T.TYPE_STRING,
    "bytes": _T.TYPE_BYTES,
    "bool": _T.TYPE_BOOL,
    "int32": _T.TYPE_INT32,
    "uint32": _T.TYPE_UINT32,
}
_TS = ".google.protobuf.Timestamp"
_POSE = ".foxglove.Pose"

# (message name, [(field name, type, repeated?)]); field numbers follow the list order from 1.
# A type starting with "." is a message type; "map" is map<string, string>.
_SPEC: list[tuple[str, list[tuple[str, str, bool]]]] = [
    ("RunStart", [
        ("start_time", _TS, False), ("run_id", "string", False), ("procedure", "string", False),
        ("params_json", "string", False), ("rig_json", "string", False),
        ("scenario_json", "string", False), ("structure", "string", False),
        ("versions", "map", False), ("git_sha", "string", False), ("git_dirty", "bool", False),
        ("argv", "string", True), ("hostname", "string", False),
    ]),
    ("RunStop", [
        ("stop_time", _TS, False), ("result", "string", False), ("reason", "string", False),
        ("traceback", "string", False), ("steps_completed", "uint32", False),
        ("duration_s", "double", False), ("recovered", "bool", False), ("last_step", "string", False),
    ]),
    ("StepEvent", [
        ("timestamp", _TS, False), ("index", "int32", False), ("name", "string", False),
        ("phase", "string", False), ("params_json", "string", False),
        ("duration_s", "double", False), ("error", "string", False),
    ]),
    ("DeviceIO", [
        ("timestamp", _TS, False), ("device", "string", False), ("url", "string", False),
        ("direction", "string", False), ("data", "bytes", False), ("text", "string", False),
        ("note", "string", False),
    ]),
    ("TagDetection", [
        ("tag_id", "int32", False), ("corners_px", "double", True), ("camera_T_tag", _POSE, False),
        ("covariance", "double", True), ("reprojection_error_px", "double", False),
        ("ambiguity_ratio", "double", False),
    ]),
    ("TagDetections", [
        ("timestamp", _TS, False), ("frame_id", "string", False),
        ("detections", ".lab.TagDetection", True),
    ]),
    ("PoseEstimate", [
        ("timestamp", _TS, False), ("entity", "string", False), ("frame_id", "string", False),
        ("pose", _POSE, False), ("covariance", "double", True),
    ]),
    ("PoseEstimateSet", [
        ("timestamp", _TS, False), ("frame_id", "string", False),
        ("estimates", ".lab.PoseEstimate", True),
    ]),
    ("ModuleVerdict", [
        ("timestamp", _TS, False), ("module", "string", False), ("verdict", "string", False),
        ("reason", "string", False), ("position_error_m", "double", False),
        ("rotation_error_rad", "double", False), ("step_index", "int32", False),
        ("tag_ids", "int32", True), ("rejected_tag_ids", "int32", True),
    ]),
    ("LengthMeasurement", [
        ("timestamp", _TS, False), ("strut", "string", False), ("node_a", "int32", False),
        ("node_b", "int32", False), ("device", "string", False), ("nominal_m", "double", False),
        ("commanded_m", "double", False), ("measured_m", "double", False),
        ("sigma_m", "double", False), ("volts", "double", False),
    ]),
    ("OperatorPrompt", [
        ("timestamp", _TS, False), ("question", "string", False), ("answer", "string", False),
        ("automatic", "bool", False),
    ]),
    ("Metric", [
        ("timestamp", _TS, False), ("name", "string", False), ("value", "double", False),
        ("unit", "string", False), ("step_index", "int32", False),
    ]),
    ("DesignTag", [
        ("id", "int32", False), ("label", "string", False), ("module", "string", False),
        ("pose", _POSE, False), ("size_m", "double", False),
    ]),
    ("StructureDesign", [
        ("timestamp", _TS, False), ("name", "string", False), ("frame_id", "string", False),
        ("node_positions", "double", True), ("edges", "uint32", True),
        ("tags", ".lab.DesignTag", True),
    ]),
    ("JsonRecord", [
        ("timestamp", _TS, False), ("kind", "string", False), ("json", "string", False),
    ]),
]


def _file_descriptor() -> descriptor_pb2.FileDescriptorProto:
    fd = descriptor_pb2.FileDescriptorProto(name=PROTO_FILE, package=PACKAGE, syntax="proto3")
    fd.dependency.extend(["google/protobuf/timestamp.proto", FoxglovePose.DESCRIPTOR.file.name])
    for msg_name, fields in _SPEC:
        msg = fd.message_type.add(name=msg_name)
        for number, (fname, ftype, repeated) in enumerate(fields, start=1):
            f = msg.field.add(name=fname, number=number, json_name=_json_name(fname))
            f.label = _T.LABEL_REPEATED if repeated else _T.LABEL_OPTIONAL
            if ftype == "map":
                entry_name = "".join(p.capitalize() for p in fname.split("_")) + "Entry"
                entry = msg.nested_type.add(name=entry_name)
                entry.options.map_entry = True
                entry.field.add(name="key", number=1, type=_T.TYPE_STRING, label=_T.LABEL_OPTIONAL, json_name="key")
                entry.field.add(name="value", number=2, type=_T.TYPE_STRING, label=_T.LABEL_OPTIONAL, json_name="value")
                f.label = _T.LABEL_REPEATED
                f.type = _T.TYPE_MESSAGE
                f.type_name = f".{PACKAGE}.{msg_name}.{entry_name}"
            elif ftype.startswith("."):
                f.type = _T.TYPE_MESSAGE
                f.type_name = ftype
            else:
                f.type = _SCALARS[ftype]
    return fd


def _json_name(name: str) -> str:
    head, *rest = name.split("_")
    return head + "".join(p[:1].upper() + p[1:] for p in rest)


def _build_classes() -> dict[str, type]:
    pool = descriptor_pool.Default()
    try:
        file_desc = pool.FindFileByName(PROTO_FILE)  # already added (module reloaded)
    except KeyError:
        file_desc = pool.Add(_file_descriptor())
        file_desc = pool.FindFileByName(PROTO_FILE)
    return {name: message_factory.GetMessageClass(file_desc.message_types_by_name[name]) for name, _ in _SPEC}


_CLASSES = _build_classes()
RunStart: Any = _CLASSES["RunStart"]
RunStop: Any = _CLASSES["RunStop"]
StepEvent: Any = _CLASSES["StepEvent"]
DeviceIO: Any = _CLASSES["DeviceIO"]
TagDetection: Any = _CLASSES["TagDetection"]
TagDetections: Any = _CLASSES["TagDetections"]
PoseEstimate: Any = _CLASSES["PoseEstimate"]
PoseEstimateSet: Any = _CLASSES["PoseEstimateSet"]
ModuleVerdict: Any = _CLASSES["ModuleVerdict"]
LengthMeasurement: Any = _CLASSES["LengthMeasurement"]
OperatorPrompt: Any = _CLASSES["OperatorPrompt"]
Metric: Any = _CLASSES["Metric"]
DesignTag: Any = _CLASSES["DesignTag"]
StructureDesign: Any = _CLASSES["StructureDesign"]
JsonRecord: Any = _CLASSES["JsonRecord"]

MESSAGE_TYPES: tuple[type, ...] = tuple(_CLASSES.values())


# ---- conversions -------------------------------------------------------------------------------

def timestamp(t_s: float | None = None) -> Timestamp:
    """A protobuf Timestamp for unix time `t_s` (seconds; now if None)."""
    ns = time.time_ns() if t_s is None else int(round(float(t_s) * 1e9))
    return Timestamp(seconds=ns // 1_000_000_000, nanos=ns % 1_000_000_000)


def timestamp_s(ts: Timestamp) -> float:
    return ts.seconds + ts.nanos * 1e-9


def pose_to_proto(p: Pose3) -> FoxglovePose:
    """`Pose3` -> `foxglove.Pose` (metres; quaternion x, y, z, w)."""
    t = p.translation()
    qx, qy, qz, qw = to_quaternion(p)
    out = FoxglovePose()
    out.position.x, out.position.y, out.position.z = (float(v) for v in t)
    out.orientation.x, out.orientation.y, out.orientation.z, out.orientation.w = (float(qx), float(qy), float(qz), float(qw))
    return out


def pose_from_proto(msg: Any) -> Pose3:
    """`foxglove.Pose` -> `Pose3`.  An all-zero quaternion (unset field) is read as identity."""
    q = msg.orientation
    quat = (q.x, q.y, q.z, q.w) if (q.x, q.y, q.z, q.w) != (0.0, 0.0, 0.0, 0.0) else (0.0, 0.0, 0.0, 1.0)
    return from_quaternion(quat, (msg.position.x, msg.position.y, msg.position.z))


def covariance_to_list(cov: np.ndarray | Sequence[Sequence[float]] | None) -> list[float]:
    """A 6x6 covariance (GTSAM order: rotation first) -> 36 floats row-major; None -> []."""
    if cov is None:
        return []
    c = np.asarray(cov, dtype=float)
    if c.shape != (6, 6):
        raise ValueError(f"a pose covariance is 6x6 (rotation first, rad and m), got shape {c.shape}")
    if not np.all(np.isfinite(c)):
        raise ValueError("pose covariance has non-finite entries")
    return [float(v) for v in c.reshape(36)]


def covariance_from_list(values: Sequence[float]) -> np.ndarray | None:
    """36 floats row-major -> 6x6 array; an empty list (no covariance recorded) -> None."""
    if len(values) == 0:
        return None
    if len(values) != 36:
        raise ValueError(f"a recorded pose covariance has 36 entries, got {len(values)}")
    return np.asarray(values, dtype=float).reshape(6, 6)


def pose_estimate(entity: str, p: Pose3, frame_id: str, covariance: np.ndarray | None = None,
                  t_s: float | None = None) -> Any:
    """A `PoseEstimate` of `entity` (e.g. "camera", "tag/17", "module/2D") in `frame_id`."""
    return PoseEstimate(timestamp=timestamp(t_s), entity=entity, frame_id=frame_id,
                        pose=pose_to_proto(p), covariance=covariance_to_list(covariance))


def tag_entity(tag_id: int) -> str:
    """Entity name of a tag in `PoseEstimate.entity`: "tag/<id>"."""
    return f"tag/{int(tag_id)}"


def tag_id_of(entity: str) -> int | None:
    """The tag id of a "tag/<id>" entity name, else None."""
    head, _, tail = entity.partition("/")
    return int(tail) if head == "tag" and tail.isdigit() else None


def pose_estimate_set(poses: Mapping[str, Pose3], frame_id: str,
                      covariances: Mapping[str, np.ndarray] | None = None, t_s: float | None = None) -> Any:
    """A `PoseEstimateSet` from entity name -> pose (and optional entity -> 6x6 covariance)."""
    covs = covariances or {}
    return PoseEstimateSet(
        timestamp=timestamp(t_s), frame_id=frame_id,
        estimates=[pose_estimate(e, p, frame_id, covs.get(e), t_s) for e, p in poses.items()],
    )


def module_verdict(module: str, verdict: str, reason: str = "", position_error_m: float = float("nan"),
                   rotation_error_rad: float = float("nan"), step_index: int = -1,
                   tag_ids: Iterable[int] = (), rejected_tag_ids: Iterable[int] = (),
                   t_s: float | None = None) -> Any:
    """A `ModuleVerdict`; `verdict` is one of VERDICTS.  Errors are NaN when not measured."""
    if verdict not in VERDICTS:
        raise ValueError(f"verdict must be one of {VERDICTS}, got {verdict!r}")
    return ModuleVerdict(timestamp=timestamp(t_s), module=module, verdict=verdict, reason=reason,
                         position_error_m=float(position_error_m), rotation_error_rad=float(rotation_error_rad),
                         step_index=int(step_index), tag_ids=[int(i) for i in tag_ids],
                         rejected_tag_ids=[int(i) for i in rejected_tag_ids])


def verdict_message(v: Verdict, step_index: int, tag_ids: Iterable[int], rejected_tag_ids: Iterable[int],
                    t_s: float | None = None) -> Any:
    """The run log's `ModuleVerdict` of a verdict record: its errors against the truth, NaN where
    there is none (hardware)."""
    t = v.truth
    return module_verdict(v.module, v.verdict, v.reason, t.position_m if t else float("nan"),
                          t.rotation_rad if t else float("nan"), step_index, tag_ids, rejected_tag_ids, t_s)


def tag_detection(tag_id: int, corners_px: np.ndarray | Sequence[Sequence[float]], camera_T_tag: Pose3 | None = None,
                  covariance: np.ndarray | None = None, reprojection_error_px: float = float("nan"),
                  ambiguity_ratio: float = float("nan")) -> Any:
    """One `TagDetection`: 4 corners in pixels (4x2, detector order), optional pose of the tag
    (paper tag frame) in the camera frame with its 6x6 covariance."""
    c = np.asarray(corners_px, dtype=float)
    if c.shape != (4, 2):
        raise ValueError(f"tag corners are 4x2 pixel coordinates, got shape {c.shape}")
    msg = TagDetection(tag_id=int(tag_id), corners_px=[float(v) for v in c.reshape(8)],
                       covariance=covariance_to_list(covariance),
                       reprojection_error_px=float(reprojection_error_px), ambiguity_ratio=float(ambiguity_ratio))
    if camera_T_tag is not None:
        msg.camera_T_tag.CopyFrom(pose_to_proto(camera_T_tag))
    return msg


__all__ = [
    "RunStart", "RunStop", "StepEvent", "DeviceIO", "TagDetection", "TagDetections", "PoseEstimate",
    "PoseEstimateSet", "ModuleVerdict", "LengthMeasurement", "OperatorPrompt", "Metric", "DesignTag",
    "StructureDesign", "JsonRecord", "MESSAGE_TYPES", "RUN_RESULTS", "STEP_PHASES", "VERDICTS",
    "DIRECTIONS", "timestamp", "timestamp_s", "pose_to_proto", "pose_from_proto", "covariance_to_list",
    "covariance_from_list", "pose_estimate", "pose_estimate_set", "tag_entity", "tag_id_of",
    "module_verdict", "verdict_message", "tag_detection",
]
