"""`lab runs` lists past runs from their own files (a killed one included), `lab runs show RUN`
prints one, and `lab run` without --out writes under the default runs root ($LAB_RUNS or the user
config file)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from pathlib import Path

import pytest

from lab.cli import main as lab_main
from lab.core.runs import runs_root



def _env(lab, **extra: str) -> dict[str, str]:
    # where a run goes without --out is what this file tests: not the runs root of whoever runs it
    return lab.env(drop=("LAB_RUNS", "LAB_CONFIG"), **extra)


@pytest.fixture(scope="module")
def root(lab, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three runs under one root: a truss run written there by $LAB_RUNS (no --out), a short BORG
    run, and a BORG run killed (SIGKILL) after its first step."""
    base = tmp_path_factory.mktemp("catalogue")
    root = base / "runs"
    env = _env(lab, LAB_RUNS=str(root))
    r = lab(["run", "truss", "tetrahelix:6", "--auto", "--quiet", "--speedup", "40"], env=env, cwd=base, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    # the ideal camera and a 1 mm target: one estimator update per step (on the realistic camera
    # without a survey the first modules are `uncertain`, and at the default 0.25 mm target an `ok`
    # read at the rig file's 1-sigma of 0.7-1.2 mm is confirmed: further rounds, each an update)
    ideal = Path(__file__).resolve().parents[1] / "docs" / "scenarios" / "ideal_camera.toml"
    r = lab(["run", "borg", "--auto", "--quiet", "--no-rig-survey", "--modules", "2", "--speedup", "40",
             "--sigma-target-mm", "1",
             "--scenario", str(ideal), "--out", str(root / "borg-short")], env=env, cwd=base, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    killed = root / "bench" / "borg-killed"          # one level deeper: found too
    p = lab.popen(["run", "borg", "--auto", "--quiet", "--no-rig-survey", "--speedup", "40", "--out", str(killed)],
                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env, cwd=base)
    ckpt = killed / "checkpoint.json"
    deadline = time.time() + 120
    while time.time() < deadline and not (ckpt.exists() and json.loads(ckpt.read_text())["steps_completed"] >= 1):
        time.sleep(0.02)
    os.kill(p.pid, signal.SIGKILL)
    p.wait(timeout=10)
    return root


def test_the_catalogue_lists_every_run_with_what_it_was(lab, root: Path) -> None:
    r = lab(["runs", "--root", str(root), "--json"], env=_env(lab), cwd=root)
    assert r.returncode == 0, r.stderr
    runs = {e["id"]: e for e in json.loads(r.stdout)["runs"]}
    assert len(runs) == 3, sorted(runs)
    truss = next(e for i, e in runs.items() if i.startswith("truss-"))   # the default name under $LAB_RUNS
    assert truss["procedure"] == "truss" and truss["result"] == "completed" and truss["counts"] == {"nodes": 6}
    short = runs["borg-short"]
    assert short["procedure"] == "borg" and short["rig"] == "sim" and short["result"] == "completed"
    assert sum(short["counts"][k] for k in ("ok", "flagged", "unverified")) == 2 and short["steps_completed"] == 2
    killed = runs[os.path.join("bench", "borg-killed")]
    assert killed["result"] == "killed" and "no stop record" in killed["reason"]
    assert killed["steps_completed"] >= 1 and killed["duration_s"] is not None and killed["duration_s"] > 0
    for e in runs.values():
        assert e["start"].startswith("20") and e["duration_s"] is not None
    # the plain listing: a header, one line per run (oldest first), a count
    text = lab(["runs", "--root", str(root)], env=_env(lab), cwd=root).stdout.splitlines()
    assert text[0].split()[:4] == ["id", "procedure", "rig", "start"]
    assert [ln.split()[0] for ln in text[1:4]] == [truss["id"], "borg-short", os.path.join("bench", "borg-killed")]
    assert "killed" in text[3] and text[4].startswith("3 runs under ")


def test_a_run_still_going_is_running_not_killed(root: Path, tmp_path: Path) -> None:
    """A run without a stop record whose directory lock is held (flock) is in progress."""
    import shutil

    from lab.core.locks import FileLock
    from lab.core.runs import read_run

    going = tmp_path / "going"
    shutil.copytree(root / "bench" / "borg-killed", going)
    with FileLock(going / ".lock", "run directory"):
        assert read_run(going).result == "running"
    assert read_run(going).result == "killed"


def test_show_prints_the_summary_and_the_verdict_table(lab, root: Path) -> None:
    r = lab(["runs", "show", "borg-short", "--root", str(root)], env=_env(lab), cwd=root)
    assert r.returncode == 0, r.stderr
    out = r.stdout
    assert "procedure borg" in out and "result completed" in out and "command: lab run borg" in out
    assert "dev mm" in out and "tol mm/deg" in out and out.rstrip().splitlines()[-1].startswith("dev: ")
    r = lab(["runs", "show", str(root / "bench" / "borg-killed" / "run.mcap")], env=_env(lab), cwd=root)  # by path
    assert r.returncode == 0 and "result killed" in r.stdout and "1P " in r.stdout
    # the default root from $LAB_RUNS
    r = lab(["runs", "show", "borg-short"], env=_env(lab, LAB_RUNS=str(root)), cwd=root.parent)
    assert r.returncode == 0 and "result completed" in r.stdout


def test_show_timings_reads_the_runs_metrics(lab, root: Path) -> None:
    """`--timings`: each metric of run.mcap once, the BORG step's estimator time a value per step."""
    r = lab(["runs", "show", "borg-short", "--root", str(root), "--timings"], env=_env(lab), cwd=root)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    head = lines.index(next(line for line in lines if line.startswith("metric ")))
    rows = {line.split()[0]: line.split() for line in lines[head + 1:]}
    assert rows["slam/update_s"][1] == "2" and rows["slam/update_s"][3] == "ms"
    r = lab(["runs", "show", "borg-short", "--root", str(root), "--timings", "--json"], env=_env(lab), cwd=root)
    t = {m["name"]: m for m in json.loads(r.stdout)["timings"]}
    step = t["slam/update_s"]
    assert step["unit"] == "s" and step["count"] == 2 and 0 < step["median"] <= step["p90"] <= step["max"]
    assert abs(float(rows["slam/update_s"][2]) - step["median"] * 1000) <= 0.05
    # where the run's time went: the devices' moves and the camera's grabs, each with its total
    for name in ("motion/move_s", "camera/grab_s"):
        m = t[name]
        assert m["count"] >= 2 and m["unit"] == "s"
        assert m["max"] <= m["total"] <= m["count"] * m["max"] + 1e-12
        assert rows[name][-1] == "s" and abs(float(rows[name][-2]) - m["total"]) <= 0.05


def test_the_default_root_comes_from_the_environment_or_the_user_config(tmp_path: Path) -> None:
    assert runs_root({"HOME": str(tmp_path)}) == (Path("runs"), "default")
    assert runs_root({"LAB_RUNS": "/data/runs"})[0] == Path("/data/runs")
    cfg = tmp_path / "xdg" / "lab" / "config.toml"
    cfg.parent.mkdir(parents=True)
    cfg.write_text('runs = "lab-runs"\n')
    assert runs_root({"XDG_CONFIG_HOME": str(tmp_path / "xdg")}) == (cfg.parent / "lab-runs", str(cfg))
    assert runs_root({"XDG_CONFIG_HOME": str(tmp_path / "xdg"), "LAB_RUNS": "/x"})[0] == Path("/x")   # env first


def test_bad_catalogue_input_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                         monkeypatch: pytest.MonkeyPatch) -> None:
    assert lab_main(["runs", "--root", str(tmp_path / "none")]) == 2
    assert lab_main(["runs", "show", "nope", "--root", str(tmp_path)]) == 2
    cfg = tmp_path / "config.toml"
    cfg.write_text('run = "typo"\n')
    monkeypatch.delenv("LAB_RUNS", raising=False)
    monkeypatch.setenv("LAB_CONFIG", str(cfg))
    assert lab_main(["runs"]) == 2
    cfg.write_text("runs = 3\n")
    assert lab_main(["runs"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 4 and all(e.startswith("lab: error: ") for e in err), err
    assert "'run'" in err[2] and str(cfg) in err[2] and "3" in err[3]
