"""`lab bench faults --only input-meaning`: the cases of issue 22, items 3-7, as the campaign's
section (lab/studies/bench_faults.py runs it like the others).

- calibration:  a rig calibration file (the survey's own, from a short `lab calibrate rig`) with
                one value no survey of this bench could give -- a negative or zero focal length, a
                principal point off the frame, the Stewart base 100 m away, a rim tag 50 m off,
                covariances zero, negative, non-symmetric, not positive definite, 1e44-conditioned,
                a file made on another rig: `lab rig check` and `lab run borg` refuse in one line
                (exit 2) and the run moves nothing; a plausible file that the camera disagrees with
                stops the run saying the rig is wrong, blaming no module (full run only);
- paths:        `lab calibrate rig --out` / `--run-dir` under a file or /proc, other commands'
                outputs, and a `--speedup` the simulated devices cannot do: one line, exit 2, within
                seconds (before the survey would have moved anything);
- catalogue:    `lab runs show` on a summary whose modules lack names or that is not JSON, `lab
                runs` with a FIFO named run.mcap or a run.mcap padded with zeros, `lab review
                --save DIR` and a malformed `--connect`: one line or a quick listing, no hang;
- journal:      a NaN typed into a study's trials.jsonl, or a value changed: refused naming the line
                and trial, not drawn;
- ctrl-c:       two SIGINT 50 ms apart inside one long C call abort; one asks for the pause.

A case is a `Case` as bench_faults.py's (name, what must follow, a check returning "" or what
happened); this module does not import that one, so the two stay free of an import cycle.  The
commands run in this process through `lab_main`, the CLI's entry point (`lab.cli.main`), which the
command running the campaign passes down: a study sits below the CLI and does not import it.
"""

from __future__ import annotations

import contextlib
import copy
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

LAB = [sys.executable, "-m", "lab"]
ROOT = Path(__file__).resolve().parents[2]
SIM_RIG = ROOT / "lab" / "rigs" / "sim.toml"
FAST = ["--auto", "--quiet", "--speedup", "100"]
QUICK_BEFORE_MOTION_S = 15.0     # the shortest survey moves for 20-30 s: a refusal sooner moved nothing


LabMain = Callable[[list[str]], Any]   # the CLI's entry point: `lab ARGV` in this process, its exit code


@dataclass
class Case:
    name: str
    expected: str
    check: Callable[[], str]          # "" when the case ends as expected, else what happened


def _main(lab_main: LabMain, argv: list[str]) -> tuple[Any, str, str]:
    """`lab ARGV` in this process: (exit code, stdout, stderr)."""
    # a command owns its process's signal handlers (`lab run` ignores a late Ctrl-C once its run is
    # closed, until it exits); here the process is the caller's, so they are given back
    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    err, out = io.StringIO(), io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
            try:
                code: Any = lab_main(argv)
            except SystemExit as exc:
                code = exc.code
            except Exception as exc:
                return "uncaught", "", f"{type(exc).__name__}: {exc}"
    finally:
        for sig, handler in handlers.items():
            if handler is not None:        # None: a handler not set from Python, left as it is
                signal.signal(sig, handler)
    return code, out.getvalue(), err.getvalue()


def _one_line(lab_main: LabMain, argv: list[str], names: str = "", within_s: float | None = None,
              absent: Path | None = None) -> str:
    """"" if `lab ARGV` exits 2 with one line on stderr that contains `names`, no traceback, within
    `within_s`, leaving `absent` absent."""
    t0 = time.monotonic()
    code, out, err = _main(lab_main, argv)
    dt = time.monotonic() - t0
    lines = [ln for ln in err.splitlines() if ln.strip()]
    if code != 2:
        return f"exit {code}: {(err or out).strip()[-200:]}"
    if "Traceback" in err:
        return "traceback on stderr"
    if len(lines) != 1:
        return f"{len(lines)} lines on stderr: {lines[:3]}"
    if names and names not in lines[0]:
        return f"the line does not name {names!r}: {lines[0][:200]}"
    if within_s is not None and dt > within_s:
        return f"refused only after {dt:.0f} s"
    if absent is not None and absent.exists():
        return f"{absent} was created"
    return ""


# ---- calibration-file contents -----------------------------------------------------------------------


def _survey(lab_main: LabMain, work: Path) -> dict[str, Any]:
    """The survey's own file (a short one: 45 deg turntable steps, devices 100x faster), made once."""
    out = work / "survey" / "rig_calibration.json"
    if not out.exists():
        out.parent.mkdir(parents=True, exist_ok=True)
        code, _, err = _main(lab_main, ["calibrate", "rig", *FAST, "--angle-step-deg", "45", "--out", str(out),
                              "--run-dir", str(work / "survey" / "run")])
        if code != 0:
            raise RuntimeError(f"the reference survey failed: exit {code}: {err.strip()[-300:]}")
    return json.loads(out.read_text())


def _rig_with(d: Path, name: str, data: dict[str, Any]) -> Path:
    """A copy of the default rig whose [calibration] file is `data`."""
    d.mkdir(parents=True, exist_ok=True)
    shutil.copy(SIM_RIG.parent / "sim_camera.json", d / "sim_camera.json")
    cal = d / f"cal-{name}.json"
    cal.write_text(json.dumps(data))
    rig = d / f"rig-{name}.toml"
    rig.write_text(SIM_RIG.read_text().replace("[lift]", f'[calibration]\nfile = "{cal.name}"\n\n[lift]', 1))
    return rig


def _edit(path: str, value: Any) -> Callable[[dict[str, Any]], None]:
    def f(d: dict[str, Any]) -> None:
        *keys, last = path.split(".")
        for k in keys:
            d = d[int(k)] if isinstance(d, list) else d[k]
        if isinstance(d, list):
            d[int(last)] = value
        else:
            d[last] = value
    return f


def _joint(make: Callable[[Any], Any]) -> Callable[[dict[str, Any]], None]:
    def f(d: dict[str, Any]) -> None:
        import numpy as np

        d["joint_covariance"] = make(np.asarray(d["joint_covariance"], float)).tolist()
    return f


def _nonsymmetric(J: Any) -> Any:
    import numpy as np

    s = np.sqrt(np.diag(J))
    out = J.copy()
    out[0, 1] += 0.01 * s[0] * s[1]
    return out


def _indefinite(J: Any) -> Any:
    import numpy as np

    s = np.sqrt(np.diag(J))
    out = J.copy()
    out[0, 1] = out[1, 0] = 1.5 * s[0] * s[1]        # a correlation beyond 1
    return out


def _zeros(J: Any) -> Any:
    import numpy as np

    return np.zeros_like(J)


# (name, edit, what the one line must name)
CALIBRATION_EDITS: list[tuple[str, Callable[[dict[str, Any]], None], str]] = [
    ("fx negative", _edit("camera.fx_px", -916.0), "camera.fx_px"),
    ("fx zero", _edit("camera.fx_px", 0.0), "camera.fx_px"),
    ("cx 50000", _edit("camera.cx_px", 50000.0), "camera.cx_px"),
    ("Stewart base 100 m away", _edit("world_T_base.xyz_m.0", -102.95), "world_T_base"),
    ("camera mount flipped", _edit("platform_T_camera.rpy_deg.0", 90.0), "platform_T_camera"),
    ("turntable tag 50 m off", _edit("turntable_tags.37.xyz_m.0", 50.0), "turntable_tags.37"),
    ("another rig", _edit("rig", "some-other-bench"), "some-other-bench"),
    ("all-zero joint covariance", _joint(_zeros), "joint_covariance"),
    ("negative mount covariance", _edit("platform_T_camera.covariance", [[-1e-6 if i == j else 0.0 for j in range(6)]
                                                                         for i in range(6)]), "platform_T_camera"),
    ("non-symmetric joint covariance", _joint(_nonsymmetric), "not symmetric"),
    ("joint covariance not positive definite", _joint(_indefinite), "not positive definite"),
    ("intrinsics covariance 1e44-conditioned", _edit("camera.covariance", [[1e22, 0, 0, 0], [0, 1e-22, 0, 0],
                                                                           [0, 0, 0.01, 0], [0, 0, 0, 0.03]]),
     "camera.covariance"),
]


def calibration_cases(lab_main: LabMain, work: Path, quick: bool) -> list[Case]:
    d = work / "calibration"
    cases: list[Case] = []

    def check_rig(edit: Callable[[dict[str, Any]], None], name: str, names: str) -> Callable[[], str]:
        def run() -> str:
            data = copy.deepcopy(_survey(lab_main, work))
            edit(data)
            return _one_line(lab_main, ["rig", "check", str(_rig_with(d, name, data))], names)
        return run

    def refuse_run(edit: Callable[[dict[str, Any]], None], name: str, names: str) -> Callable[[], str]:
        def run() -> str:
            data = copy.deepcopy(_survey(lab_main, work))
            edit(data)
            d.mkdir(parents=True, exist_ok=True)
            cal = d / f"run-{name}.json"
            cal.write_text(json.dumps(data))
            out = d / f"out-{name}"
            return _one_line(lab_main, ["run", "borg", *FAST, "--modules", "1", "--calibration", str(cal),
                                        "--out", str(out)], names, within_s=QUICK_BEFORE_MOTION_S, absent=out)
        return run

    cases.append(Case("input-meaning/calibration/the survey's own file", "lab rig check: valid, exit 0",
                      lambda: "" if (r := _main(lab_main, ["rig", "check",
                                                           str(_rig_with(d, "good", _survey(lab_main, work)))]))[0] == 0
                      else f"exit {r[0]}: {r[2].strip()[-200:]}"))
    for name, edit, names in CALIBRATION_EDITS:
        slug = name.replace(" ", "_")
        cases.append(Case(f"input-meaning/calibration/rig check: {name}",
                          f"exit 2, one line naming {names}", check_rig(edit, slug, names)))
    for name, edit, names in CALIBRATION_EDITS[:: 1 if not quick else 4]:
        slug = "run_" + name.replace(" ", "_")
        cases.append(Case(f"input-meaning/calibration/run borg: {name}",
                          f"exit 2 naming {names}, nothing moved, no run directory", refuse_run(edit, slug, names)))
    if not quick:
        cases.append(Case("input-meaning/calibration/the camera disagrees with the file",
                          "aborted (exit 3) saying the rig or its calibration is wrong; no module blamed",
                          lambda: _disagreement(lab_main, work, d)))
    return cases


def _disagreement(lab_main: LabMain, work: Path, d: Path) -> str:
    """Within every bound, but the Stewart base 15 cm from where it is."""
    data = copy.deepcopy(_survey(lab_main, work))
    data["world_T_base"]["xyz_m"][1] += 0.15
    d.mkdir(parents=True, exist_ok=True)
    cal = d / "shifted.json"
    cal.write_text(json.dumps(data))
    out = d / "shifted-run"
    shutil.rmtree(out, ignore_errors=True)
    code, _, err = _main(lab_main, ["run", "borg", *FAST, "--modules", "2", "--calibration", str(cal),
                                    "--out", str(out)])
    try:
        summary = json.loads((out / "summary.json").read_text())
    except (OSError, ValueError) as exc:
        return f"exit {code}, no summary ({exc}): {err.strip()[-200:]}"
    if code != 3 or "disagrees with the rig calibration" not in summary.get("reason", ""):
        return f"exit {code}, {summary.get('result')}: {summary.get('reason', '')[:200]}"
    if summary.get("modules"):
        return f"modules judged anyway: {[(m['name'], m['verdict']) for m in summary['modules']]}"
    return ""


# ---- command paths and values -------------------------------------------------------------------------


def path_cases(lab_main: LabMain, work: Path, quick: bool) -> list[Case]:
    d = work / "paths"
    d.mkdir(parents=True, exist_ok=True)
    f = d / "a-file"
    f.write_text("x")
    good = str(d / "c.json")
    survey = ["calibrate", "rig", *FAST, "--angle-step-deg", "90"]
    argvs: dict[str, tuple[list[str], str]] = {
        "calibrate rig --out under a file": (survey + ["--out", str(f / "c.json")], "--out"),
        "calibrate rig --out under /proc": (survey + ["--out", "/proc/lab-c.json"], "--out"),
        "calibrate rig --out in a missing folder": (survey + ["--out", str(d / "nope" / "c.json")], "--out"),
        "calibrate rig --run-dir a file": (survey + ["--out", good, "--run-dir", str(f)], "--run-dir"),
        "calibrate rig --run-dir under /proc": (survey + ["--out", good, "--run-dir", "/proc/lab-run"], "--run-dir"),
        "calibrate rig --speedup 1e-9": (["calibrate", "rig", "--auto", "--speedup", "1e-9", "--out", good,
                                          "--run-dir", str(d / "slow")], "--speedup"),
        "run borg --speedup 1e-9": (["run", "borg", "--auto", "--quiet", "--speedup", "1e-9", "--out",
                                     str(d / "slow-run")], "--speedup"),
        "run truss --speedup 0.01": (["run", "truss", "tetrahelix:6", "--auto", "--speedup", "0.01", "--out",
                                      str(d / "slow-truss")], "--speedup"),
        "calibrate board --out under /proc": (["calibrate", "board", "--out", "/proc/lab-b.png"], "--out"),
        "calibrate camera --out under a file": (["calibrate", "camera", "--sim", "3", "--out", str(f / "c.json")],
                                                "--out"),
        "calibrate camera --record under /proc": (["calibrate", "camera", "--sim", "3", "--out", good, "--force",
                                                   "--record", "/proc/lab-r.mcap"], "--record"),
    }
    if quick:
        argvs = {k: v for k, v in argvs.items() if k in ("calibrate rig --out under a file",
                                                         "calibrate rig --run-dir a file", "run borg --speedup 1e-9")}
    return [Case(f"input-meaning/paths/{name}", f"exit 2 naming {names} before anything moves",
                 lambda a=argv, n=names: _one_line(lab_main, a, n, within_s=QUICK_BEFORE_MOTION_S))
            for name, (argv, names) in argvs.items()]


# ---- catalogue and review -------------------------------------------------------------------------------


def _reference_run(lab_main: LabMain, work: Path) -> Path:
    """One short BORG run to damage copies of (made once)."""
    out = work / "catalogue" / "reference"
    if not (out / "summary.json").exists():
        shutil.rmtree(out, ignore_errors=True)
        code, _, err = _main(lab_main, ["run", "borg", *FAST, "--modules", "2", "--no-rig-survey", "--out", str(out)])
        if code != 0:
            raise RuntimeError(f"the reference run failed: exit {code}: {err.strip()[-300:]}")
    return out


def _root_with(lab_main: LabMain, work: Path, name: str, damage: Callable[[Path], None]) -> Path:
    root = work / "catalogue" / f"root-{name.replace(' ', '_')}"
    shutil.rmtree(root, ignore_errors=True)
    shutil.copytree(_reference_run(lab_main, work), root / "a")
    damage(root / "a")
    return root


def _summary_edit(edit: Callable[[dict[str, Any]], None]) -> Callable[[Path], None]:
    def f(run: Path) -> None:
        s = json.loads((run / "summary.json").read_text())
        edit(s)
        (run / "summary.json").write_text(json.dumps(s))
    return f


def _listing(root: Path, must: str, within_s: float) -> str:
    """`lab runs --root ROOT` in a child (a hang must not hang the campaign): exit 0, `must` listed."""
    t0 = time.monotonic()
    try:
        r = subprocess.run(LAB + ["runs", "--root", str(root)], capture_output=True, text=True, timeout=60)
    except subprocess.TimeoutExpired:
        return "lab runs hung for 60 s"
    dt = time.monotonic() - t0
    if r.returncode != 0:
        return f"exit {r.returncode}: {r.stderr.strip()[-200:]}"
    if must not in r.stdout:
        return f"{must!r} not listed: {r.stdout.strip()[-200:]}"
    if dt > within_s:
        return f"took {dt:.1f} s"
    return ""


def catalogue_cases(lab_main: LabMain, work: Path, quick: bool) -> list[Case]:
    cases: list[Case] = []

    def show(name: str, damage: Callable[[Path], None], names: str) -> Case:
        return Case(f"input-meaning/catalogue/runs show: {name}", f"exit 2, one line naming {names}",
                    lambda: _one_line(lab_main, ["runs", "show", "a", "--root",
                                                 str(_root_with(lab_main, work, name, damage))], names))

    cases.append(show("modules without names", _summary_edit(lambda s: [m.pop("name") for m in s["modules"]]),
                      "modules[0].name"))
    cases.append(show("summary not JSON", lambda run: (run / "summary.json").write_text('{"result": "comp'),
                      "not a readable JSON file"))
    if not quick:
        cases.append(show("a verdict that is text", _summary_edit(lambda s: s["modules"][0].update(verdict=5)),
                          "modules[0].verdict"))
        cases.append(show("a deviation that is NaN",
                          _summary_edit(lambda s: s["modules"][0].update(deviation_m=float("nan"))),
                          "modules[0].deviation_m"))

    def fifo(run: Path) -> None:
        sub = run.parent / "deep" / "er"
        sub.mkdir(parents=True)
        os.mkfifo(sub / "run.mcap")
    cases.append(Case("input-meaning/catalogue/lab runs with a FIFO named run.mcap", "the listing ends; the FIFO skipped",
                      lambda: _listing(_root_with(lab_main, work, "fifo", fifo), "completed", 20.0)))

    def padded(run: Path) -> None:
        data = (run / "run.mcap").read_bytes()
        pos = 8
        for _ in range(6):                       # a clean cut after the sixth record
            pos += 9 + int.from_bytes(data[pos + 1: pos + 9], "little")
        p = run.parent / "padded"
        p.mkdir()
        (p / "run.mcap").write_bytes(data[:pos] + bytes(32 * 2 ** 20))
    cases.append(Case("input-meaning/catalogue/lab runs with a run.mcap cut and padded with 32 MB of zeros",
                      "listed as killed within seconds",
                      lambda: _listing(_root_with(lab_main, work, "padded", padded), "killed", 8.0)))
    mcap = lambda: str(_reference_run(lab_main, work) / "run.mcap")          # noqa: E731
    cases.append(Case("input-meaning/catalogue/review --save DIR", "exit 2, one line naming --save",
                      lambda: _one_line(lab_main, ["review", mcap(), "--save", str(work)], "--save")))
    for url in (("http://[::1", "rerun+http://[bad/proxy", "host:99999") if not quick else ("http://[::1",)):
        cases.append(Case(f"input-meaning/catalogue/review --connect {url}", "exit 2, one line naming --connect",
                          lambda u=url: _one_line(lab_main, ["review", mcap(), "--connect", u], "--connect")))
    return cases


# ---- study journals ---------------------------------------------------------------------------------------


def _double(trial: Any) -> dict[str, Any]:          # a study's trial (module level: workers import it)
    return {"value": 2.0 * trial.spec, "none": None}


def _journal_case(work: Path, name: str, edit: Callable[[str], str], must: str) -> str:
    """An interrupted study's journal, edited, then the study run again as `lab bench` runs one."""
    import argparse

    from lab.core.errors import UserError
    from lab.core.executor import Journal, make_trials
    from lab.studies.bench_common import run_trial_study

    out = work / "journal" / name.replace(" ", "_")
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    j = Journal(out / "trials.jsonl", {"bench": "demo", "x": 1, "speedup": 1.0}, say=False)
    j.append("t/0", {"value": 2.0, "none": None})
    j.append("t/1", {"value": 4.0, "none": None})
    j.close()
    j.path.write_text(edit(j.path.read_text()))
    args = argparse.Namespace(out=str(out), json=True, workers=1, scheduler=None, speedup=1.0)
    try:
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            run_trial_study(args, "demo", make_trials(0, "t", [1, 2, 3]), _double, {"x": 1},
                            lambda ts: [{"sum": sum(t["value"] for t in ts)}], str, lambda r: "")
    except UserError as exc:
        text = str(exc)
        return "" if must in text and "trials.jsonl line 3 (trial t/1)" in text else f"refused, but: {text[:200]}"
    return "the edited journal was used"


def journal_cases(work: Path, quick: bool) -> list[Case]:
    def line_rewritten(text: str) -> str:
        from lab.core.executor.journal import _line

        lines = text.splitlines()
        lines[2] = _line("t/1", {"value": float("nan"), "none": None}).strip()
        return "\n".join(lines) + "\n"

    edits = {"NaN typed in": (lambda t: t.replace('"value": 4.0', '"value": NaN', 1), "not what the study wrote"),
             "a value changed": (lambda t: t.replace('"value": 4.0', '"value": 5.0', 1), "not what the study wrote"),
             "NaN with its checksum": (line_rewritten, "result.value is nan")}
    if quick:
        edits = {k: v for k, v in edits.items() if k == "NaN typed in"}
    return [Case(f"input-meaning/journal/{name}", "refused in one line naming the line and the trial",
                 lambda n=name, e=edit, m=must: _journal_case(work, n, e, m)) for name, (edit, must) in edits.items()]


# ---- a second Ctrl-C -----------------------------------------------------------------------------------------

# a process whose main thread is inside one long C call when Ctrl-C comes (also tests/test_double_ctrl_c.py)
CTRL_C_CHILD = r"""
import hashlib, os, signal, sys, threading, time
from procedures.pause import PauseControl
from procedures.runner import SignalShield

shield = SignalShield()
shield.install()
pause = PauseControl(shield, True, say=lambda text: None)
pause.install()
count = int(sys.argv[1])

def kick():
    time.sleep(0.2)
    for k in range(count):
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)

threading.Thread(target=kick).start()
try:
    hashlib.pbkdf2_hmac("sha256", b"x", b"y", 3_000_000)   # ~1 s in one C call, as an estimator update
    time.sleep(0.05)
    print("pause" if pause.requested else "nothing", len(shield.signals))
except KeyboardInterrupt:
    print("abort", len(shield.signals))
finally:
    pause.restore()
    shield.restore()
"""


def _ctrl_c(count: int, want: str) -> str:
    r = subprocess.run([sys.executable, "-c", CTRL_C_CHILD, str(count)], cwd=ROOT, capture_output=True, text=True,
                       timeout=60)
    got = r.stdout.split()     # what the child did, and how many signals its shield counted
    if r.returncode == 0 and got[:1] == [want]:
        return ""
    return f"exit {r.returncode}: {r.stdout.strip() or r.stderr.strip()[-200:]}"


def ctrl_c_cases(quick: bool) -> list[Case]:
    trials = 1 if quick else 5
    return ([Case(f"input-meaning/ctrl-c/two 50 ms apart inside a C call, trial {k + 1}", "abort",
                  lambda: _ctrl_c(2, "abort")) for k in range(trials)]
            + [Case("input-meaning/ctrl-c/one", "the pause is requested", lambda: _ctrl_c(1, "pause"))])


def cases(work: Path, quick: bool, lab_main: LabMain) -> list[Case]:
    """Every case of the section, in order (`lab_main`: the CLI's entry point, `lab.cli.main`)."""
    return (calibration_cases(lab_main, work, quick) + path_cases(lab_main, work, quick)
            + catalogue_cases(lab_main, work, quick)
            + journal_cases(work, quick) + ctrl_c_cases(quick))
