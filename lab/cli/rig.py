"""`lab rig check FILE [--json]`: check a rig file without connecting to anything, and say what it
is ready for (docs/hardware.md, "First day on hardware")."""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict, dataclass, field


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("rig", help="rig files: `lab rig check FILE` validates one without connecting")
    rsub = p.add_subparsers(dest="rig_command", metavar="check")
    rsub.required = True
    c = rsub.add_parser("check", help="validate a rig file without connecting; say what it is ready for",
                        description="Read and check a rig file (every table, key, unit and limit; the camera and "
                                    "rig calibration files it names; the Stewart platform's home pose against its "
                                    "own limits) without opening any port, then list what is still missing for "
                                    "which command. Exit 0 if valid, 2 with one line naming the problem if not.")
    c.add_argument("file", metavar="FILE", help="the rig file (TOML; docs/hardware.md)")
    c.add_argument("--json", action="store_true", help="machine-readable report")
    c.set_defaults(func=_check)


@dataclass
class RigReport:
    rig: str
    source: str
    simulated: bool
    devices: list[dict[str, str]] = field(default_factory=list)
    todo: list[str] = field(default_factory=list)         # what is missing, and the command that supplies it
    ready: list[str] = field(default_factory=list)        # commands this rig can be used with now
    not_ready: list[str] = field(default_factory=list)


def check_rig(path: str) -> RigReport:
    """Everything that can be checked without a device; a problem raises UserError (one line)."""
    from drivers.camera import load_calibration
    from drivers.stewart_kinematics import StewartKinematics
    from lab.core.config import load_rig
    from lab.core.errors import UserError

    rig = load_rig(path)
    rep = RigReport(rig.name, rig.source, rig.sim is not None)
    if rig.turntable is not None:
        t = rig.turntable
        rep.devices.append({"device": t.name, "url": t.link.url,
                            "note": f"travel {_deg(t.min_rad):.0f}..{_deg(t.max_rad):.0f} deg"})
    if rig.stewart is not None:
        s = rig.stewart
        ik = StewartKinematics(s.geometry).inverse([0, 0, 0, 0, 0, 0])
        if not ik.reachable:
            raise UserError(f"rig {rig.source}: [stewart]: the home pose is outside the platform's own limits "
                            f"({ik.reason}); check home_height_m, leg_min_m/leg_max_m and the joint positions")
        rep.devices.append({"device": s.name, "url": s.link.url,
                            "note": f"home legs {min(ik.legs_m) * 1000:.0f}..{max(ik.legs_m) * 1000:.0f} mm "
                                    f"(limits {s.geometry.leg_min_m * 1000:.0f}..{s.geometry.leg_max_m * 1000:.0f})"})
    if rig.lift is not None:
        lf = rig.lift
        rep.devices.append({"device": lf.name, "url": lf.link.url,
                            "note": f"travel {lf.min_m * 1000:.0f}..{lf.max_m * 1000:.0f} mm"})
    camera_ready = False
    intr = None
    if rig.camera is not None:
        c = rig.camera
        if c.calibration is None:
            note = "no calibration file yet"
            rep.todo.append(f"camera intrinsics: `lab calibrate camera --rig {path} --out camera_calibration.json`, "
                            f"then set calibration = \"camera_calibration.json\" in [camera]")
        else:
            intr = load_calibration(c.calibration)          # parses it: a bad file is one line here
            note = f"calibration {c.calibration} ({intr.width_px}x{intr.height_px} px)"
            camera_ready = True
        rep.devices.append({"device": c.name, "url": c.url, "note": note})
    for ipjr in rig.ipjrs.values():
        rep.devices.append({"device": ipjr.name, "url": ipjr.link.url,
                            "note": f"stroke {ipjr.stroke_m * 1000:.0f} mm, "
                                    f"{ipjr.volts_retracted:.3f}..{ipjr.volts_extended:.3f} V"})
    borg_rig = rig.turntable is not None and rig.stewart is not None and rig.camera is not None
    if rig.calibration.file is not None:
        from lab.core.rig_calibration_file import load_rig_calibration
        from lab.core.rig_calibration_check import check_for_rig
        from lab.core.structures.borg import build_borg

        cal = load_rig_calibration(rig.calibration.file)      # its covariances' meaning too
        if borg_rig:
            # made for this rig, close to its nominal geometry and the rim tags of the structure
            # `lab calibrate rig` surveys (the camera's part once the camera is calibrated)
            check_for_rig(cal, rig, intr if camera_ready else None,
                          build_borg(rig.sim.borg_n if rig.sim is not None else 3), str(rig.calibration.file))
    elif borg_rig:
        rep.todo.append(f"rig calibration (camera mount, Stewart base, turntable axis): `lab calibrate rig --rig "
                        f"{path} --out rig_calibration.json`, then set file = \"rig_calibration.json\" in "
                        f"[calibration] (without it `lab run borg` begins with the same survey)")
    rep.ready.append("lab devices check")
    if rig.camera is not None:
        rep.ready.append("lab calibrate camera")
    if borg_rig:
        for cmd in ("lab calibrate rig", "lab run borg"):
            if camera_ready:
                rep.ready.append(cmd)
            else:
                rep.not_ready.append(f"{cmd} (needs the camera intrinsics)")
    if rig.ipjrs:
        if len(rig.ipjrs) >= 3:
            rep.ready.append("lab run truss")
        else:
            rep.not_ready.append(f"lab run truss (needs three IPJRs, the rig has {len(rig.ipjrs)})")
    return rep


def _deg(rad: float) -> float:
    import math

    return math.degrees(rad)


def _check(args: argparse.Namespace) -> int:
    rep = check_rig(args.file)
    if args.json:
        print(json.dumps(asdict(rep), indent=1))
        return 0
    kind = "simulated bench" if rep.simulated else "hardware (no [sim] table)"
    print(f"rig {rep.rig} ({rep.source}): valid, {kind}; nothing was connected")
    width = max((len(d["device"]) for d in rep.devices), default=0)
    for d in rep.devices:
        print(f"  {d['device']:<{width}}  {d['url']:<24}  {d['note']}")
    for t in rep.todo:
        print(f"to do: {t}")
    print(f"ready for: {', '.join(rep.ready)}")
    if rep.not_ready:
        print(f"not yet: {', '.join(rep.not_ready)}")
    return 0
