"""`lab calibrate camera` (ChArUco intrinsic calibration), `lab calibrate board` (a printable
board) and `lab calibrate rig` (camera mount, Stewart base, turntable axis from a survey of the
turntable tags).  docs/calibration.md; the work happens in procedures/calibrate_camera.py and
procedures/calibrate_rig.py."""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path
from typing import Any

DEFAULT_OUT = "camera_calibration.json"
DEFAULT_RIG_OUT = "rig_calibration.json"
# procedures.calibrate_camera holds the defaults; it imports OpenCV, so `lab --help` must not import it.
# These strings only describe them (a test checks they agree).
_HELP_BOARD = "9x6:30:22:DICT_5X5_100"
_HELP_MIN_CORNERS = 10
_HELP_MIN_FRAMES = 8


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("calibrate", help="calibrate the camera (ChArUco intrinsics) and the rig (camera mount, Stewart base, turntable axis)")
    csub = p.add_subparsers(dest="what", metavar="WHAT")
    csub.required = True

    c = csub.add_parser(
        "camera", help="camera intrinsics from views of a ChArUco board: live, from image files, or simulated",
        description="Camera intrinsic calibration with a ChArUco board (or a plain chessboard: --board "
                    "chessboard:COLSxROWS:SQUARE_MM). Frames come from the rig's camera "
                    "(default; the operator is told where to hold the board), from image files (--frames DIR), or "
                    "from the simulated camera's true lens and imaging (--sim N, compared with that truth). Writes the "
                    "intrinsics file the camera driver reads (docs/hardware.md).")
    c.add_argument("--rig", metavar="FILE", help="rig file (default: the simulated bench, lab/rigs/sim.toml)")
    src = c.add_mutually_exclusive_group()
    src.add_argument("--frames", metavar="DIR", help="calibrate from the image files in DIR (png, jpg, bmp, tif)")
    src.add_argument("--sim", type=int, metavar="N",
                     help="render N views of the board with the rig's simulated true camera and its imaging "
                          "([sim.camera], [sim.rig_error]), compared with that true lens")
    c.add_argument("--board", metavar="SPEC",
                   help=f"the printed board, COLSxROWS:SQUARE_MM:MARKER_MM[:DICT][:legacy] (default {_HELP_BOARD}), "
                        f"or a plain chessboard, chessboard:COLSxROWS:SQUARE_MM (inner corners, e.g. chessboard:9x6:25)")
    c.add_argument("--out", metavar="FILE", default=DEFAULT_OUT,
                   help=f"intrinsics file to write (default {DEFAULT_OUT}); point the rig's [camera] calibration at it")
    c.add_argument("--force", action="store_true", help="replace --out if it exists")
    c.add_argument("--auto", action="store_true",
                   help="live: no prompts, grab a frame every --interval-s while the operator moves the board")
    c.add_argument("--record", metavar="FILE.mcap", help="record frames, detections and the result to an MCAP file")
    c.add_argument("--count", type=int, default=15, metavar="N", help="live: usable views to collect (default 15)")
    c.add_argument("--interval-s", type=float, default=1.0, metavar="S", help="live --auto: seconds between grabs")
    c.add_argument("--min-corners", type=int, metavar="N",
                   help=f"reject a frame with fewer chessboard corners (default {_HELP_MIN_CORNERS})")
    c.add_argument("--min-frames", type=int, metavar="N",
                   help=f"refuse to calibrate from fewer usable views (default {_HELP_MIN_FRAMES})")
    c.add_argument("--fit-k3", action="store_true", help="also fit k3 (wide-angle lenses); default: k3 = 0")
    c.add_argument("--seed", type=int, default=None, help="--sim: seed of the views and noise (default: the rig's)")
    c.add_argument("--save-frames", metavar="DIR", help="--sim: also write the rendered frames to DIR as PNG")
    c.add_argument("--scenario", metavar="FILE",
                   help="--sim: a scenario whose [camera] keys replace the rig's imaging, whose [rig_error] the "
                        "rig's, whose seed the lens's (docs/scenarios.md; e.g. docs/scenarios/ideal_camera.toml)")
    c.add_argument("--json", action="store_true", help="print the result as JSON instead of the report")
    c.set_defaults(func=_camera)

    r = csub.add_parser(
        "rig", help="camera mount, Stewart base and turntable axis from a survey of the turntable tags",
        description="Rig calibration: the Stewart platform and the turntable move the camera through a survey of the "
                    "turntable's rim tags; OpenCV's robot-world/hand-eye calibration gives a first solution, GTSAM "
                    "refines it with the focal length, principal point and the tags as glued. Writes the rig "
                    "calibration file the rig's [calibration] file key references, with 1-sigma uncertainties and "
                    "residuals, and refuses (exit 2, nothing written) when a parameter is poorly conditioned. "
                    "Run it after `lab calibrate camera` (docs/calibration.md).")
    r.add_argument("--rig", metavar="FILE", help="rig file (default: the simulated bench, lab/rigs/sim.toml)")
    r.add_argument("--scenario", metavar="FILE", help="simulation scenario: seed, noise, [rig_error] (docs/scenarios.md)")
    r.add_argument("--out", metavar="FILE", default=DEFAULT_RIG_OUT,
                   help=f"rig calibration file to write (default {DEFAULT_RIG_OUT}); point the rig's [calibration] "
                        f"file at it")
    r.add_argument("--force", action="store_true", help="replace --out if it exists")
    r.add_argument("--n", type=int, default=None, metavar="N",
                   help="the BORG size the rig is calibrated for, 2..10 (default: the rig's [sim] borg_n, else 3): "
                        "its turntable's rim tags, and the station the Stewart base stands at for it")
    r.add_argument("--angle-step-deg", type=float, default=None, metavar="DEG",
                   help="turntable step between survey angles (default 30, the rim tags' spacing, up to the 3x3x3's "
                        "turntable; finer on a bigger one: 15 for N = 4..6, 10 for 7..9, 7.5 for 10; larger is a "
                        "quicker, coarser survey)")
    r.add_argument("--run-dir", metavar="DIR", help="where the run's MCAP log goes (default <runs root>/calibrate-rig-<time>, "
                                                          "the root as for lab run)")
    r.add_argument("--auto", action="store_true", help="answer operator prompts automatically (simulation)")
    r.add_argument("--dry-run", action="store_true", help="check every planned move against limits; move nothing")
    r.add_argument("--speedup", type=float, default=None, help="simulated devices move this many times faster")
    r.add_argument("--quiet", action="store_true", help="no progress bars")
    r.add_argument("--json", action="store_true",
                   help="print the estimates with their sigmas (and, in simulation, the errors against the truth) as JSON")
    r.set_defaults(func=_rig)

    b = csub.add_parser("board", help="write a printable ChArUco board image (PNG or PDF at true scale)")
    b.add_argument("--board", metavar="SPEC", help=f"board spec (default {_HELP_BOARD})")
    b.add_argument("--out", metavar="FILE", required=True, help="output file, .png or .pdf")
    b.add_argument("--dpi", type=int, default=300, help="print resolution (default 300)")
    b.add_argument("--margin-mm", type=float, default=10.0, help="white margin around the squares (default 10 mm)")
    b.set_defaults(func=_board)


# ---- lab calibrate camera ---------------------------------------------------------------------


def _camera(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from drivers.camera import Intrinsics, save_calibration
    from lab.core.config import load_rig
    from lab.core.errors import UserError
    from procedures import calibrate_camera as cal
    from procedures.calibrate_camera import CalibrationSession, capture_live, parse_board, read_frames

    board = parse_board(args.board or cal.DEFAULT_BOARD)
    min_corners = cal.DEFAULT_MIN_CORNERS if args.min_corners is None else args.min_corners
    min_frames = cal.DEFAULT_MIN_FRAMES if args.min_frames is None else args.min_frames
    out = Path(args.out)
    if out.is_dir():
        raise UserError(f"--out {out} is a directory; give a file name such as {out / DEFAULT_OUT}")
    if out.exists() and not args.force:
        raise UserError(f"--out {out} already exists; choose another file or add --force to replace it")
    from lab.core.paths import check_output_dir, check_output_file

    # written at the end, after every view: checked before the first
    check_output_file(out, "--out")
    if args.record:
        check_output_file(args.record, "--record")
    if args.save_frames:
        check_output_dir(args.save_frames, "--save-frames")
    if args.sim is not None and not 1 <= args.sim <= 500:
        raise UserError(f"--sim {args.sim}: the number of simulated views must be 1..500")
    if args.sim is not None and isinstance(board, cal.ChessboardSpec):
        raise UserError(f"--board {board.text()}: --sim renders ChArUco boards only; give a ChArUco --board, or "
                        f"--frames DIR for chessboard photographs")
    if args.save_frames and args.sim is None:
        raise UserError("--save-frames writes simulated frames; use it with --sim N")
    if args.scenario and args.sim is None:
        raise UserError("--scenario sets up the simulated camera; use it with --sim N")
    if args.interval_s < 0:
        raise UserError(f"--interval-s {args.interval_s}: must be 0 or more seconds")
    rig = load_rig(args.rig)
    camera_name = rig.camera.name if rig.camera else "camera"

    truth: Intrinsics | None = None
    nominal: Intrinsics | None = None
    frames: list[tuple[str, Any]] | None = None
    if args.sim is not None:
        truth, nominal, frames = _sim_frames(rig, board, args.sim, args.seed, args.save_frames, args.scenario)
    elif args.frames:
        frames = read_frames(args.frames)
    else:
        if rig.camera is None:
            raise UserError(f"rig {rig.source} has no [camera]; give --frames DIR or a rig with a camera")
        if rig.simulated:
            raise UserError(f"rig {rig.source} is simulated: its camera shows the BORG bench, not a board; "
                            f"use --sim N to calibrate from simulated board views, or --frames DIR")

    params = {k: v for k, v in vars(args).items() if k not in ("func", "command", "what")}
    params.update(board=board.text(), min_corners=min_corners, min_frames=min_frames)
    say = (lambda s: print(s, file=sys.stderr)) if args.json else print

    def run(recorder: Any) -> Any:
        session = CalibrationSession(board, min_corners=min_corners, recorder=recorder, camera=camera_name)
        if frames is not None:
            for label, image in frames:
                d = session.add(label, image)
                if not d.usable:
                    say(f"{label}: not used: {d.reason}")
        else:
            from drivers.camera import Camera
            from lab.core.comms import null_sink
            from procedures.runner import Operator

            # The old calibration is not loaded: it may be for another resolution, the reason to recalibrate.
            cam = Camera.open(replace(rig.camera, calibration=None), recorder.comms_sink if recorder else null_sink)
            try:
                say(f"camera {camera_name} at {rig.camera.url}: {cam.identify()}; board {board.text()} "
                    f"({board.size_m[0] * 1000:.0f} x {board.size_m[1] * 1000:.0f} mm)")
                capture_live(session, cam, Operator(args.auto, recorder), args.count, interval_s=args.interval_s,
                             say=say)
            finally:
                cam.close()
        result = session.finish(fit_k3=args.fit_k3, min_frames=min_frames, truth=truth, nominal=nominal)
        save_calibration(out, result.intrinsics, camera=camera_name)
        if recorder is not None:
            recorder.log_text("info", f"wrote {out}")
        return result

    if args.record:
        from lab.core.recorder import RunRecorder

        with RunRecorder(args.record, "calibrate_camera", params, rig=rig.to_dict(), argv=sys.argv) as rec:
            result = run(rec)
    else:
        result = run(None)

    if args.json:
        print(json.dumps({"out": str(out), **result.to_json()}, indent=2))
    else:
        for line in result.report():
            print(line)
        print(f"wrote {out}")
        print(_rig_hint(rig, out))
    return 0


def _sim_frames(rig: Any, board: Any, n: int, seed: int | None, save_dir: str | None, scenario_path: str | None = None):
    """The simulated rig's true camera (the world's: `sim_devices.world.true_camera`, the rig's
    imaging with the scenario's [camera] keys, its [rig_error] or the rig's) and `n` board views it
    renders with that imaging.  The lens and the light across the frame are the bench's (the
    scenario's seed, as `lab sim` has them); `seed` (default the same) picks the views and noise."""
    import cv2
    import numpy as np

    from drivers.camera import Intrinsics
    from lab.core.errors import UserError
    from lab.core.scenario import Scenario, load_scenario
    from sim_devices.charuco_render import imaged_calibration_session
    from sim_devices.world import camera_gain_map, true_camera

    if rig.sim is None or rig.camera is None:
        raise UserError(f"--sim needs a simulated rig with a camera ([sim.camera]); rig {rig.source} has "
                        f"{'no [sim] table' if rig.sim is None else 'no [camera]'}")
    scenario = load_scenario(scenario_path) if scenario_path else Scenario(seed=rig.sim.seed)
    imaging = rig.sim.imaging.with_overrides(scenario.camera.overrides())
    rig_error = scenario.rig_error if scenario.rig_error is not None else rig.sim.rig_error
    cam = true_camera(rig, imaging, rig_error, scenario.seed)
    truth = Intrinsics(cam.K, cam.dist, cam.width_px, cam.height_px)
    nominal = Intrinsics(cam.nominal_K, cam.nominal_dist, cam.width_px, cam.height_px)
    view_seed = scenario.seed if seed is None else seed
    rng = np.random.default_rng([view_seed, 0xCA1])
    try:
        views = imaged_calibration_session(cam, board.make(), n, rng, gain=camera_gain_map(cam, scenario.seed),
                                           light_rng=np.random.default_rng([view_seed, 0xCA1, 1]))
    except ValueError as exc:
        raise UserError(f"board {board.text()} with the simulated camera: {exc}") from None
    frames = [(f"sim-{i:03d}", img) for i, (_pose, img) in enumerate(views)]
    if save_dir:
        d = Path(save_dir)
        d.mkdir(parents=True, exist_ok=True)
        for label, img in frames:   # lossless: the frame as the detector read it (after the camera's JPEG)
            cv2.imwrite(str(d / f"{label}.png"), img)
    return truth, nominal, frames


def _rig_hint(rig: Any, out: Path) -> str:
    if rig.camera is not None and rig.camera.calibration is not None and \
            rig.camera.calibration.resolve() == out.resolve():
        return f"the rig's [camera] calibration already points at {out}"
    where = Path(rig.source).parent if Path(rig.source).exists() else Path.cwd()
    try:
        rel = os.path.relpath(out.resolve(), where.resolve())
    except ValueError:   # another drive
        rel = ".."
    if rel.startswith(".."):
        rel = str(out.resolve())   # a path climbing out of the rig's folder reads better absolute
    return (f"to use it, set in the rig file's [camera] table: calibration = \"{rel}\"  "
            f"(a relative path is taken from the rig file's folder)")


# ---- lab calibrate rig ------------------------------------------------------------------------


def _rig(args: argparse.Namespace) -> int:
    import time

    from lab.core.errors import UserError
    from lab.core.recorder import RunRecorder
    from procedures import runner
    from procedures.calibrate_rig import RigCalibrationProcedure
    from procedures.setup import open_bench

    t0 = time.perf_counter()
    out = Path(args.out)
    if out.is_dir():
        raise UserError(f"--out {out} is a directory; give a file name such as {out / DEFAULT_RIG_OUT}")
    if out.exists() and not args.force and not args.dry_run:
        raise UserError(f"--out {out} already exists; choose another file or add --force to replace it")
    if args.speedup is not None and not args.speedup > 0:
        raise UserError(f"--speedup {args.speedup}: must be a positive factor")
    if args.angle_step_deg is not None and not 5.0 <= args.angle_step_deg <= 180.0:
        raise UserError(f"--angle-step-deg {args.angle_step_deg}: must be 5..180 degrees")
    from lab.core.runs import runs_root

    run_dir = Path(args.run_dir) if args.run_dir else runs_root()[0] / f"calibrate-rig-{time.strftime('%Y%m%d-%H%M%S')}"
    if not args.dry_run:
        from lab.core.paths import check_output_dir, check_output_file

        # both are written after the survey: find out now, before anything moves, that they can be
        check_output_file(out, "--out")
        check_output_dir(run_dir, "--run-dir" if args.run_dir else "the run directory (--run-dir)")
        if (run_dir / runner.RUN_FILE).exists():
            raise UserError(f"--run-dir {run_dir} already holds a run; choose another")
    from procedures.setup import check_borg_n

    n = check_borg_n(args.n)
    bench = open_bench(args.rig, args.scenario, speedup=args.speedup, only=None, borg_n=n)
    try:
        step = None if args.angle_step_deg is None else math.radians(args.angle_step_deg)
        proc = RigCalibrationProcedure(bench, out, angle_step_rad=step, borg_n=n)
    except BaseException:
        bench.close()
        raise
    if args.dry_run:
        try:
            return runner.dry_run(proc)
        finally:
            proc.close()
    params = {k: v for k, v in vars(args).items() if k not in ("func", "command", "what")}
    info = {"procedure": proc.name, "params": params, "structure": f"borg:{proc.model.n}", "argv": sys.argv}

    def recorder_factory(path: Path) -> RunRecorder:
        rec = RunRecorder(path, proc.name, params, rig=bench.rig.data, scenario=bench.scenario.to_dict(),
                          structure=f"borg:{proc.model.n}")
        bench.relay.target = rec.comms_sink
        rec.log_design(f"borg:{proc.model.n}", proc.model)
        return rec

    outcome = runner.run(proc, run_dir, info=info, operator_auto=bool(args.auto), recorder_factory=recorder_factory,
                         show_progress=not (args.quiet or args.json))
    summary = dict(outcome.summary)
    summary["run"] = str(run_dir / runner.RUN_FILE)
    summary["wall_s"] = time.perf_counter() - t0
    problems = proc.result.problems
    if args.json:
        print(json.dumps(summary, indent=2, default=float))
    else:
        for line in _rig_report(summary):
            print(line)
    for p in problems:       # one line per poorly conditioned parameter, on stderr like every error
        print(f"lab: error: {p}", file=sys.stderr)
    if problems:
        print(f"lab: error: rig calibration not written ({len(problems)} poorly conditioned "
              f"parameter{'s' if len(problems) > 1 else ''}); run: {summary['run']}", file=sys.stderr)
        return 2
    if outcome.result != "completed":
        print(f"lab: {outcome.result}: {outcome.reason}; run: {summary['run']}", file=sys.stderr)
        return outcome.exit_code
    if not args.json:
        print(_rig_calibration_hint(bench.rig, out))
    return 0


def _rig_report(s: dict[str, Any]) -> list[str]:
    """The console report: each estimate with its 1 sigma, the residuals, the errors against the truth."""
    lines = [f"rig calibration from {s['views']} views ({s['sightings']} tag sightings); run {s['run']}"]
    est = s.get("estimates")
    if est:
        names = {"platform_T_camera": "camera mount", "world_T_base": "Stewart base", "world_T_axis": "turntable axis"}
        for key, label in names.items():
            e = est[key]
            xyz = " ".join(f"{v:+9.2f}+-{sd:.2f}" for v, sd in zip(e["xyz_mm"], e["sigma_xyz_mm"]))
            rpy = " ".join(f"{v:+8.3f}+-{sd:.3f}" for v, sd in zip(e["rpy_deg"], e["sigma_rpy_deg"]))
            lines.append(f"  {label:<15} xyz mm {xyz}   rpy deg {rpy}")
        c = est["camera"]
        sg = c["sigma"]
        lines.append(f"  {'camera':<15} fx {c['fx_px']:.2f}+-{sg['fx_px']:.2f} fy {c['fy_px']:.2f}+-{sg['fy_px']:.2f} "
                     f"cx {c['cx_px']:.2f}+-{sg['cx_px']:.2f} cy {c['cy_px']:.2f}+-{sg['cy_px']:.2f} px")
        r = s["residuals_px"]
        lines.append(f"  corner residuals: rms {r['rms']:.3f} px, 95 % {r['p95']:.3f} px, max {r['max']:.3f} px "
                     f"over {r['corners']} corners; solve {s['solve_s']:.1f} s")
    te = s.get("truth_error")
    if te:
        lines.append(f"  against the simulated truth: camera mount {te['camera_mount_m'] * 1e3:.2f} mm / "
                     f"{math.degrees(te['camera_mount_rad']):.4f} deg, Stewart base {te['stewart_base_m'] * 1e3:.2f} mm / "
                     f"{math.degrees(te['stewart_base_rad']):.4f} deg, turntable axis {te['turntable_axis_m'] * 1e3:.2f} mm"
                     f" / {math.degrees(te['turntable_axis_rad']):.4f} deg; NEES mount "
                     f"{s['nees']['platform_T_camera']:.1f}, base {s['nees']['world_T_base']:.1f} (6 expected)")
    if s.get("written"):
        lines.append(f"wrote {s['written']}  ({s['wall_s']:.0f} s)")
    return lines


def _rig_calibration_hint(rig: Any, out: Path) -> str:
    f = rig.calibration.file
    if f is not None and Path(f).resolve() == out.resolve():
        return f"the rig's [calibration] file already points at {out}"
    where = Path(rig.source).parent if Path(rig.source).exists() else Path.cwd()
    try:
        rel = os.path.relpath(out.resolve(), where.resolve())
    except ValueError:
        rel = ".."
    if rel.startswith(".."):
        rel = str(out.resolve())
    return (f"to use it, set in the rig file: [calibration] file = \"{rel}\"  "
            f"(a relative path is taken from the rig file's folder)")


# ---- lab calibrate board ----------------------------------------------------------------------

ISO_A_MM = [("A4", 297.0, 210.0), ("A3", 420.0, 297.0), ("A2", 594.0, 420.0), ("A1", 841.0, 594.0),
            ("A0", 1189.0, 841.0)]


def _iso_sheet(w_mm: float, h_mm: float) -> tuple[str, float, float] | None:
    """The smallest ISO A sheet, landscape, that holds a w x h mm page (None: larger than A0)."""
    w, h = max(w_mm, h_mm), min(w_mm, h_mm)
    for name, sw, sh in ISO_A_MM:
        if w <= sw + 1e-6 and h <= sh + 1e-6:
            return name, sw, sh
    return None


def _board(args: argparse.Namespace) -> int:
    import cv2
    import numpy as np

    from lab.core.errors import UserError
    from procedures.calibrate_camera import DEFAULT_BOARD, parse_board

    board = parse_board(args.board or DEFAULT_BOARD)
    if not hasattr(board, "make"):
        raise UserError(f"--board {board.text()}: lab calibrate board prints ChArUco boards only (a plain "
                        f"chessboard is for photographs already taken; print a ChArUco board for new ones)")
    out = Path(args.out)
    if out.suffix.lower() not in (".png", ".pdf"):
        raise UserError(f"--out {out}: write a .png or a .pdf")
    if not 72 <= args.dpi <= 2400:
        raise UserError(f"--dpi {args.dpi}: must be 72..2400")
    if not 0 <= args.margin_mm <= 100:
        raise UserError(f"--margin-mm {args.margin_mm}: must be 0..100 mm")
    px_per_mm = args.dpi / 25.4
    w_mm, h_mm = (s * 1000 for s in board.size_m)
    img = board.make().generateImage((round(w_mm * px_per_mm), round(h_mm * px_per_mm)), marginSize=0, borderBits=1)
    m = round(args.margin_mm * px_per_mm)
    caption_px = max(round(6 * px_per_mm), 12)
    img = cv2.copyMakeBorder(img, m, m + caption_px, m, m, cv2.BORDER_CONSTANT, value=255)
    text = f"ChArUco {board.text()}  -  print at 100 %: a square must measure {board.square_m * 1000:g} mm"
    scale = caption_px / 2.0 / 22.0
    cv2.putText(img, text, (m, img.shape[0] - m - caption_px // 3), cv2.FONT_HERSHEY_SIMPLEX, scale, 0,
                max(1, round(scale * 1.5)), cv2.LINE_AA)
    # The page is a real paper size: the board centred on the smallest ISO A sheet (landscape) that
    # holds it with its margins. A page cut to the board (290 x 206 mm for the default, called "A4")
    # is not a size a printer knows; dialogs then scale it "to fit" and the print is off scale.
    sheet = _iso_sheet(img.shape[1] / px_per_mm, img.shape[0] / px_per_mm)
    if sheet is not None:
        name, sw, sh = sheet
        pad_w, pad_h = round(sw * px_per_mm) - img.shape[1], round(sh * px_per_mm) - img.shape[0]
        img = cv2.copyMakeBorder(img, pad_h // 2, pad_h - pad_h // 2, pad_w // 2, pad_w - pad_w // 2,
                                 cv2.BORDER_CONSTANT, value=255)
    from lab.core.paths import check_output_file

    check_output_file(out, "--out")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.image

    # imsave stores the resolution (PNG pHYs) or sizes the page (PDF) so the print comes out to scale.
    matplotlib.image.imsave(out, np.asarray(img), cmap="gray", vmin=0, vmax=255, dpi=args.dpi)
    page_w, page_h = img.shape[1] / px_per_mm, img.shape[0] / px_per_mm
    paper = f"{sheet[0]} landscape" if sheet is not None else "larger than A0"
    print(f"wrote {out}: board {board.text()}, {w_mm:.0f} x {h_mm:.0f} mm of squares, page {page_w:.0f} x "
          f"{page_h:.0f} mm ({paper}) at {args.dpi} dpi; print at 100 % (actual size) on {paper.split()[0]}")
    print(f"check after printing: {board.cols} squares must span {w_mm:.1f} mm; glue it flat on a rigid board")
    return 0
