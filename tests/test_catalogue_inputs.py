"""The catalogue and review take their files and flags as inputs (issue 22, items 5-7): `lab runs`
skips a run.mcap that is not a regular file (a FIFO would hang it) and bounds its work per run (a
file cut short and padded with zeros, a killed run larger than its scan budget); `lab runs show`
says what is wrong with a damaged summary.json, naming the key, instead of a traceback or "the run
stopped before its first step ended"; `lab review --save DIR` and a malformed `--connect` URL are
one line.

Every case is built from one short simulated run (module fixture)."""

from __future__ import annotations

import json
import os
import shutil
import struct
import time
from pathlib import Path

import pytest

from lab.core import runs as catalogue


@pytest.fixture(scope="module")
def run_dir(lab, tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("one") / "run"
    rc, _, err = lab.main("run", "borg", "--auto", "--quiet", "--speedup", "100", "--modules", "2", "--no-rig-survey",
                          "--out", str(d))
    assert rc == 0, err
    return d


@pytest.fixture
def root(tmp_path, run_dir) -> Path:
    r = tmp_path / "root"
    shutil.copytree(run_dir, r / "a")
    return r


def _records_end(path: Path, n: int) -> int:
    """The offset just after the file's n-th record (a clean cut)."""
    data = path.read_bytes()
    pos = 8
    for _ in range(n):
        _, length = struct.unpack_from("<BQ", data, pos)
        pos += 9 + length
    return pos


# ---- lab runs show: the summary ------------------------------------------------------------------

@pytest.mark.parametrize("case, damage, names", [
    ("modules without names", lambda s: [m.pop("name") for m in s["modules"]], "modules[0].name: missing"),
    ("a verdict that is no verdict", lambda s: s["modules"][1].update(verdict="great"), "modules[1].verdict"),
    ("a deviation that is text", lambda s: s["modules"][0].update(deviation_m="far"), "modules[0].deviation_m"),
    ("a NaN deviation", lambda s: s["modules"][0].update(deviation_m=float("nan")), "modules[0].deviation_m"),
    ("modules not a list", lambda s: s.update(modules={"1P": "ok"}), "modules: expected a list"),
    ("rejected tags not a list", lambda s: s.update(rejected_tags=3), "rejected_tags"),
])
def test_runs_show_names_what_is_wrong_with_a_summary(lab, root, case, damage, names):
    p = root / "a" / "summary.json"
    s = json.loads(p.read_text())
    damage(s)
    p.write_text(json.dumps(s))
    for extra in ([], ["--json"]):
        rc, out, err = lab.main("runs", "show", "a", "--root", str(root), *extra)
        assert rc == 2 and "Traceback" not in err, (case, err)
        assert len(err.strip().splitlines()) == 1 and "summary.json" in err and names in err, (case, err)
    # the listing still lists it, counting nothing from the damaged file
    rc, out, err = lab.main("runs", "--root", str(root))
    assert rc == 0 and "a " in out and "completed" in out


def test_a_completed_run_whose_summary_is_not_json(lab, root):
    (root / "a" / "summary.json").write_text('{"result": "comp')
    rc, out, err = lab.main("runs", "show", "a", "--root", str(root))
    assert rc == 2 and "not a readable JSON file" in err and "damaged" in err
    assert "before its first step" not in out + err
    assert "result completed" in out               # what run.mcap says stands


def test_a_completed_run_whose_summary_was_deleted(lab, root):
    (root / "a" / "summary.json").unlink()
    rc, out, err = lab.main("runs", "show", "a", "--root", str(root))
    assert rc == 0 and "deleted or moved" in out and "before its first step" not in out


def test_the_good_summary_still_shows_its_table(lab, root):
    rc, out, err = lab.main("runs", "show", "a", "--root", str(root))
    assert rc == 0 and "1P " in out and "2D " in out, err


# ---- lab runs: what is not a regular file, and work per run ---------------------------------------

@pytest.mark.parametrize("what", ["run.mcap", "summary.json", "checkpoint.json", ".lock"])
def test_a_fifo_anywhere_does_not_hang_the_listing(lab, root, run_dir, what):
    d = root / "deep" / "er"
    d.mkdir(parents=True)
    if what != "run.mcap":
        shutil.copy(run_dir / "run.mcap", d / "run.mcap")
    os.mkfifo(d / what)
    t0 = time.monotonic()
    rc, out, err = lab.main("runs", "--root", str(root))
    assert rc == 0, err
    assert time.monotonic() - t0 < 10
    assert ("deep/er" in out) == (what != "run.mcap")        # a FIFO is no run: skipped
    if what != "run.mcap":
        rc, out, err = lab.main("runs", "show", "deep/er", "--root", str(root))
        assert rc in (0, 2) and "Traceback" not in err


def test_a_file_cut_short_and_padded_with_zeros_is_read_quickly(lab, root, run_dir):
    src = run_dir / "run.mcap"
    cut = _records_end(src, 6)
    d = root / "padded"
    d.mkdir()
    (d / "run.mcap").write_bytes(src.read_bytes()[:cut] + bytes(32 * 2 ** 20))
    t0 = time.monotonic()
    rc, out, err = lab.main("runs", "--root", str(root))
    dt = time.monotonic() - t0
    assert rc == 0 and "padded" in out and "killed" in out, err
    assert dt < 3.0, f"{dt:.1f} s for 32 MB of zeros (9 bytes a step took ~9 s)"
    rc, out, err = lab.main("runs", "show", "padded", "--root", str(root))
    assert "zero bytes where a record should start" in out


def test_a_killed_run_is_read_within_its_budget(root, run_dir, monkeypatch):
    """Past the budget the checkpoint counts the steps: listing a long killed run stays quick."""
    src = run_dir / "run.mcap"
    d = root / "killed"
    d.mkdir()
    data = src.read_bytes()
    (d / "run.mcap").write_bytes(data[: len(data) - 200])       # no footer: scanned front to back
    (d / "checkpoint.json").write_text(json.dumps({"steps_completed": 2}))
    monkeypatch.setattr(catalogue, "SCAN_BUDGET_BYTES", 4096)
    entry = catalogue.read_run(d, root)
    assert entry.result == "killed" and entry.steps_completed == 2
    assert "read the first" in entry.reason


# ---- lab review -------------------------------------------------------------------------------------

def test_review_save_to_a_directory_is_one_line(lab, run_dir, tmp_path):
    rc, out, err = lab.main("review", str(run_dir / "run.mcap"), "--save", str(tmp_path))
    assert rc == 2 and "--save" in err and "directory" in err and "Traceback" not in err


@pytest.mark.parametrize("url", ["http://[::1", "rerun+http://[bad/proxy", "host:99999", "rerun+http://h:x/proxy"])
def test_review_connect_with_a_malformed_url_is_one_line(lab, run_dir, url):
    rc, out, err = lab.main("review", str(run_dir / "run.mcap"), "--connect", url)
    assert rc == 2 and "--connect" in err and len(err.strip().splitlines()) == 1, err
