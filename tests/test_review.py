"""`lab review --save` writes an .rrd with the design structure, estimated vs design tags, the
camera path and plots; plain Rerun reads our MCAP files (images, poses, transforms) with no glue.
No test starts a viewer."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from rerun.chunk import McapReader, RrdReader

from lab.cli import main as lab_main
from lab.core.geometry import Pose3, from_xyzrpy, look_at, pose
from lab.core.recorder import RunRecorder, messages as m, topics
from lab.core.review import FrameTree, review


@pytest.fixture(autouse=True)
def _strict_rerun():
    """Make a malformed Rerun archetype raise instead of only warning."""
    import rerun as rr

    rr.set_strict_mode(True)
    yield
    rr.set_strict_mode(False)


def _chunks(rrd: Path) -> dict[str, list]:
    out: dict[str, list] = {}
    for chunk in RrdReader(rrd).stream():
        out.setdefault(chunk.entity_path, []).append(chunk.to_record_batch())
    return out


def _column(batches: list, name: str) -> list:
    return [v for b in batches if name in b.schema.names for v in b.column(name).to_pylist()]


def _write_run(path: Path, structure: str = "", record_design: bool = True,
               snapshot: Path | None = None) -> dict[int, Pose3]:
    """A two-step run: camera views, a 2 mm displaced tag estimate, verdicts, metrics.
    `snapshot` gets a copy of the file as it is on disk after step 0 (what a kill would leave)."""
    design = {7: from_xyzrpy([0.0, 0.0, 0.0, np.pi / 2, 0, 0]), 9: from_xyzrpy([1.0, 0.0, 0.0, np.pi / 2, 0, 0])}
    K = np.array([[400.0, 0, 80], [0, 400, 60], [0, 0, 1]])
    img = np.full((120, 160), 128, np.uint8)
    with RunRecorder(path, "review-test", {"n": 1}, structure=structure) as rec:
        if record_design:
            rec.log_structure("bar", np.array([[0, 0, 0], [1, 0, 0], [0.5, 0.5, 0.0]]), [(0, 1), (1, 2)],
                              [m.DesignTag(id=i, label=f"T{i}", module="bar", pose=m.pose_to_proto(p), size_m=0.1)
                               for i, p in design.items()])
        rec.log_calibration(topics.CAMERA_CALIBRATION, K, [], 160, 120, "camera")
        world_T_structure = from_xyzrpy([0.2, 0.1, 0.0, 0.0, 0.0, 0.3])
        rec.log_transform("world", "structure", world_T_structure)
        for i in range(2):
            with rec.step(f"view {i}", i):
                cam = look_at([0.5 + 0.2 * i, -2.0, 1.0], [0.5, 0.0, 0.0])
                rec.log_transform("world", "camera", cam)
                rec.log_image(topics.CAMERA_IMAGE, img, None, "camera")
                rec.log_record(topics.DETECTIONS, m.TagDetections(
                    frame_id="camera", detections=[m.tag_detection(7, [[10, 10], [30, 10], [30, 30], [10, 30]],
                                                                   reprojection_error_px=0.4)]))
                shifted = design[7].compose(pose(None, (0.002, 0.0, 0.0)))  # 2 mm along the tag's x
                if i == 0:
                    rec.log_tag_estimates({7: shifted, 9: design[9]}, "structure")
                else:  # the same estimate expressed in the world frame: review must bring the design there
                    rec.log_tag_estimates({7: world_T_structure * shifted, 9: world_T_structure * design[9]}, "world")
                rec.log_pose(topics.estimate_topic("camera"), cam, "world", None, np.eye(6) * 1e-6)
                rec.log_record(topics.VERDICTS, m.module_verdict("bar", "ok" if i == 0 else "flagged", "check",
                                                                 0.002, 0.001, step_index=i))
                rec.log_metric("residual", 0.5 - 0.1 * i)
                rec.log_text("info", f"view {i} done")
            if snapshot is not None and i == 0:
                shutil.copyfile(path, snapshot)
    return design


def test_review_save_writes_design_estimates_camera_path_and_plots(tmp_path: Path) -> None:
    run, rrd = tmp_path / "run.mcap", tmp_path / "run.rrd"
    _write_run(run)
    assert lab_main(["review", str(run), "--save", str(rrd)]) == 0
    ch = _chunks(rrd)
    for entity in ["/world/structure/design/nodes", "/world/structure/design/edges", "/world/structure/design/tags",
                   "/world/structure/estimate/tags", "/world/structure/estimate/tags/errors", "/world/camera",
                   "/world/camera/image", "/world/camera/image/detections", "/world/paths/camera",
                   "/world/estimate/camera", "/verdicts", "/steps", "/log", "/run/info",
                   "/plots/tag_error_mm/7", "/plots/tag_error_mm/max", "/plots/residual",
                   "/plots/verdict_position_error_mm/bar", "/plots/reprojection_error_px/7"]:
        assert entity in ch, f"{entity} missing; have {sorted(ch)}"
    assert len(_column(ch["/world/structure/design/nodes"], "Points3D:positions")[0]) == 3
    assert _column(ch["/world/structure/design/tags"], "LineStrips3D:labels")[0] == ["7 T7", "9 T9"]
    # Estimated vs design: the 2 mm displacement of tag 7 comes out as 2 mm, tag 9 as 0.
    assert np.allclose(_column(ch["/plots/tag_error_mm/7"], "Scalars:scalars"), [[2.0], [2.0]], atol=1e-6)
    assert np.allclose(_column(ch["/plots/tag_error_mm/9"], "Scalars:scalars"), [[0.0], [0.0]], atol=1e-6)
    # The step index is a timeline; the camera path grows by one view per step.
    assert "step" in ch["/plots/residual"][0].schema.names
    assert sorted(v for b in ch["/plots/residual"] for v in b.column("step").to_pylist()) == [0, 1]
    path_strips = _column(ch["/world/paths/camera"], "LineStrips3D:strips")
    assert [len(s[0]) for s in path_strips] == [1, 2]
    # The structure frame is placed by the recorded /tf world -> structure.
    assert np.allclose(_column(ch["/world/structure"], "Transform3D:translation")[0], [0.2, 0.1, 0.0])
    assert "/world/estimate/tags" in ch  # step 1's estimate was in the world frame
    info = _column(ch["/run/info"], "TextDocument:text")[0][0]
    assert "review-test" in info and "completed" in info
    texts = [t[0] for t in _column(ch["/verdicts"], "TextLog:text")]
    assert texts[1].startswith("bar: FLAGGED, position error 2.00 mm")


def test_review_draws_the_borg_design_from_lab_structures_when_the_run_only_names_it(tmp_path: Path) -> None:
    borg = pytest.importorskip("lab.core.structures.borg")
    model = borg.build_borg(3)
    run, rrd = tmp_path / "borg.mcap", tmp_path / "borg.rrd"
    _write_run(run, structure="borg:3", record_design=False)
    rep = review(run, rrd)
    assert rep.design == "borg:3 (lab.structures)"
    ch = _chunks(rrd)
    assert len(_column(ch["/world/structure/design/nodes"], "Points3D:positions")[0]) == len(model.nodes)
    assert len(_column(ch["/world/structure/design/edges"], "LineStrips3D:strips")[0]) == len(model.edges)
    labels = _column(ch["/world/structure/design/tags"], "LineStrips3D:labels")[0]
    assert len(labels) == len(model.tags) == 48 and "1 2D-B" in labels
    # The same model recorded into the run with its tags (RunRecorder.log_design).
    small = borg.build_borg(2)
    run2, rrd2 = tmp_path / "borg2.mcap", tmp_path / "borg2.rrd"
    with RunRecorder(run2, "borg", {}) as rec:
        rec.log_design("borg:2", small)
    review(run2, rrd2)
    labels2 = _column(_chunks(rrd2)["/world/structure/design/tags"], "LineStrips3D:labels")[0]
    assert len(labels2) == len(small.tags)


def test_a_design_recorded_in_the_run_is_drawn_as_recorded(tmp_path: Path) -> None:
    trusses = pytest.importorskip("lab.core.structures.trusses")
    model = trusses.build_truss("tetrahelix:6")
    run, rrd = tmp_path / "truss.mcap", tmp_path / "truss.rrd"
    with RunRecorder(run, "truss", {}, structure="borg:2") as rec:  # the recorded design wins over the name
        rec.log_design("tetrahelix:6", model)
    rep = review(run, rrd)
    assert rep.design == "tetrahelix:6 (recorded)"
    ch = _chunks(rrd)
    assert np.allclose(_column(ch["/world/structure/design/nodes"], "Points3D:positions")[0], model.nodes)
    assert len(_column(ch["/world/structure/design/edges"], "LineStrips3D:strips")[0]) == len(model.edges)


def test_review_of_a_killed_run_shows_what_was_recorded(tmp_path: Path) -> None:
    cut = tmp_path / "cut.mcap"
    _write_run(tmp_path / "full.mcap", snapshot=cut)
    rep = review(cut, tmp_path / "cut.rrd")
    assert rep.scan.stop_reason and rep.steps == 1 and rep.result.startswith("unknown")
    ch = _chunks(tmp_path / "cut.rrd")
    assert "no stop record" in _column(ch["/run/info"], "TextDocument:text")[0][0]
    assert "/world/structure/estimate/tags" in ch and "/world/camera/image" in ch


def test_plain_rerun_reads_images_poses_and_transforms_from_a_run(tmp_path: Path) -> None:
    """What `rerun RUN.mcap` shows, through Rerun's own MCAP loader (no lab code involved)."""
    run = tmp_path / "plain.mcap"
    _write_run(run)
    components: dict[str, set[str]] = {}
    for chunk in McapReader(run).stream():
        components.setdefault(chunk.entity_path, set()).update(chunk.to_record_batch().schema.names)
    assert "EncodedImage:blob" in components["/camera/image"]
    assert "Pinhole:image_from_camera" in components["/camera/calibration"]
    assert {"Transform3D:parent_frame", "Transform3D:child_frame"} <= components["/tf"]
    assert "InstancePoses3D:translations" in components["/estimate/tags"]
    assert "InstancePoses3D:translations" in components["/estimate/camera"]
    assert "TextLog:text" in components["/log"]
    assert "lab.ModuleVerdict:message" in components["/verdicts"]  # our records, decoded generically


def test_frame_tree_resolves_chains_to_the_root() -> None:
    tree = FrameTree()
    tree.set("world", "turntable", from_xyzrpy([0, 0, 0.1, 0, 0, 0.5]))
    tree.set("turntable", "structure", pose(None, (0.3, 0.0, 0.0)))
    root, world_T_structure = tree.root_T("structure")
    assert root == "world"
    expected = from_xyzrpy([0, 0, 0.1, 0, 0, 0.5]).compose(pose(None, (0.3, 0.0, 0.0)))
    assert world_T_structure.equals(expected, 1e-12)
    assert tree.descendants("turntable") == ["structure"] and set(tree.descendants("world")) == {"turntable", "structure"}
    assert tree.root_T("camera")[0] == "camera"
