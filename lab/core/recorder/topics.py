"""The channels (topics) of a run's MCAP file.  Import these instead of spelling topics out.

Foxglove schemas (shown by plain `rerun RUN.mcap` and Foxglove with no glue) and our own `lab.*`
messages (lab/core/recorder/messages.py); each topic carries exactly one schema."""

from __future__ import annotations

RUN_START = "/run/start"          # lab.RunStart: procedure, params, rig, scenario, versions, git SHA, argv
RUN_STOP = "/run/stop"            # lab.RunStop: completed|aborted|failed, reason, traceback
RUN_STEP = "/run/step"            # lab.StepEvent: start|end|error of each procedure step
COMMS = "/comms"                  # lab.DeviceIO: every byte to/from a device, and transport events
CAMERA_IMAGE = "/camera/image"    # foxglove.CompressedImage (PNG unless told otherwise)
CAMERA_CALIBRATION = "/camera/calibration"  # foxglove.CameraCalibration
TF = "/tf"                        # foxglove.FrameTransform: parent_T_child (world, turntable, stewart, camera, structure)
TAG_POSES = "/estimate/tags"      # foxglove.PosesInFrame: estimated tag poses, ascending tag id
TAG_ESTIMATES = "/estimate/tag_estimates"  # lab.PoseEstimateSet: the same poses with tag ids and covariances
ESTIMATE_PREFIX = "/estimate/"    # "/estimate/<entity>": foxglove.PoseInFrame; "<topic>/covariance": lab.PoseEstimate
DETECTIONS = "/detections"        # lab.TagDetections: per image, corners, camera_T_tag, covariance, reprojection error
VERDICTS = "/verdicts"            # lab.ModuleVerdict
LENGTHS = "/lengths"              # lab.LengthMeasurement: IPJR strut lengths
METRICS = "/metrics"              # lab.Metric: named scalars to plot (residuals, costs, errors)
STRUCTURE = "/structure"          # lab.StructureDesign: the design nodes, edges and tag poses
LOG = "/log"                      # foxglove.Log: human-readable log lines
OPERATOR = "/operator"            # lab.OperatorPrompt: question asked and answer given
RECORDS = "/records"              # lab.JsonRecord: anything else, as JSON with a kind

COVARIANCE_SUFFIX = "/covariance"


def estimate_topic(entity: str) -> str:
    """Topic of an estimated pose of `entity`, e.g. "camera" -> "/estimate/camera"."""
    entity = entity.strip("/")
    if not entity:
        raise ValueError("estimate entity name is empty")
    return ESTIMATE_PREFIX + entity


ALL = (RUN_START, RUN_STOP, RUN_STEP, COMMS, CAMERA_IMAGE, CAMERA_CALIBRATION, TF, TAG_POSES,
       TAG_ESTIMATES, DETECTIONS, VERDICTS, LENGTHS, METRICS, STRUCTURE, LOG, OPERATOR, RECORDS)
