"""BORG structures larger than 3x3x3 on the default rig (issue 13): `--n` builds the simulated
structure the run asks for, the lift carries the camera to the heights the upper layers need, and
a rig that cannot see some modules says which before anything moves."""

from __future__ import annotations

import json
from pathlib import Path

import lab.core.config as config
from lab.core.recorder import topics
from lab.core.recorder.reader import iter_messages


def _rig_variant(tmp_path: Path, name: str, edit) -> str:
    """The default sim rig, edited (its camera file alongside)."""
    rig_dir = Path(config.default_rig_path()).parent
    (tmp_path / "sim_camera.json").write_bytes((rig_dir / "sim_camera.json").read_bytes())
    path = tmp_path / f"{name}.toml"
    path.write_text(edit((rig_dir / "sim.toml").read_text()))
    return str(path)


def _without_lift(text: str) -> str:
    text = text[:text.index("[lift]")] + text[text.index("[camera]"):]
    return text[:text.index("[sim.lift]")] + text[text.index("[sim.stewart]"):]


def test_a_4x4x4_run_on_the_default_rig_uses_the_lift(lab, run_dir):
    """`--n 4` on the default rig (its borg_n is 3): the simulated world is the 4x4x4, the survey
    looks from lift heights (the rim tags from below the home height), the graph calibrates the
    lift's axis with the rest, and every module is verified.  (4D was also seen from above until
    the plans knew the floor, stop 45: that view no longer shrinks its predicted 1-sigma by a tenth.)"""
    out = run_dir
    r = lab(["run", "borg", "--n", "4", "--auto", "--quiet", "--modules", "6", "--no-rig-survey", "--speedup", "40",
             "--out", str(out)])
    assert r.returncode == 0, r.stdout + r.stderr
    s = json.loads((out / "summary.json").read_text())
    assert s["result"] == "completed" and s["structure"] == "borg:4" and s["steps"] == 6
    assert [m["verdict"] for m in s["modules"]] == ["ok"] * 6, [(m["name"], m["reason"]) for m in s["modules"]]
    assert max(m["position_error_m"] for m in s["modules"]) < 0.003
    views = json.loads((out / "checkpoint.json").read_text())["state"]["views"]
    heights = {v["lift_m"] for v in views}
    assert 0.0 in heights and min(heights) < 0
    # the lift really moved there: MOVE commands on its serial line, each tagged
    sent = [m.message.data for m in iter_messages(out / "run.mcap")
            if m.topic == topics.COMMS and m.message.device == "lift" and m.message.direction == "tx"]
    moves = {b.split(b" ", 1)[1].strip() for b in sent if b" MOVE " in b}
    assert {f"MOVE {h * 1000:.3f}".encode() for h in heights if h} <= moves, moves


def test_modules_a_rig_without_the_lift_cannot_see_are_listed_before_anything_moves(lab, tmp_path, run_dir):
    """(A lift kept short is the same story: tests/test_survey_lift.py.)"""
    rig = _rig_variant(tmp_path, "rig", _without_lift)
    # the dry run lists them, one line each, and refuses
    r = lab(["run", "borg", "--n", "4", "--dry-run", "--rig", rig])
    assert r.returncode == 2, r.stdout + r.stderr
    listed = [line for line in r.stdout.splitlines() if "no candidate view of rig 'sim' sees tag" in line]
    assert listed and all(line.strip().startswith("REFUSED: module ") for line in listed)
    assert any("module 99S " in line for line in listed), r.stdout          # top layer, face 1, z 2.07 m
    # a run refuses before it starts: the same lines on stderr, exit 2, no run directory left
    out = run_dir
    r = lab(["run", "borg", "--n", "4", "--auto", "--rig", rig, "--out", str(out)])
    assert r.returncode == 2, r.stdout + r.stderr
    err = r.stderr.splitlines()
    assert [line for line in err if line.startswith("unobservable: module ")] == \
        [f"unobservable: {line.strip().removeprefix('REFUSED: ')}" for line in listed]
    assert err[-1].startswith("lab: error: rig 'sim' cannot observe") and "--allow-unobservable" in err[-1]
    assert not out.exists()
    # told to go on, the dry run warns instead
    r = lab(["run", "borg", "--n", "4", "--dry-run", "--allow-unobservable", "--rig", rig])
    assert r.returncode == 0, r.stdout + r.stderr
    assert sum("WARNING: module " in line for line in r.stdout.splitlines()) == len(listed)
