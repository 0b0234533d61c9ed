"""lab.core.executor: trials give the same results whichever executor runs them (in this process, local
worker processes, a Dask cluster), an interrupted study keeps its finished trials and resumes from
them, and bad --workers / --scheduler values are one-line errors."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from lab.core.errors import UserError
from lab.core.executor import (InProcess, Journal, LocalProcesses, Study, Trial, make_executor, make_trials, trial_seed,
                               without_executor_args)
from lab.core.executor.compare import differences, strip_timings

ROOT = Path(__file__).resolve().parents[1]


# Trial functions: module level, so that worker processes import them by name.

def noisy_square(trial: Trial) -> dict:
    """A seeded draw, a tuple (comes back a list: the JSON round trip), and later trials finishing
    first (the earlier ones sleep longer), so that order has to be restored."""
    import numpy as np

    x, sleep_s = trial.spec
    time.sleep(sleep_s)
    return {"x2": x * x, "draw": float(np.random.default_rng(trial.seed).normal()), "pair": (x, -x), "pid": os.getpid()}


def matmul_checksum(trial: Trial) -> str:
    # 400x400: big enough that OpenBLAS splits the product when it has two threads, which changes
    # the last bits (the executor runs every trial on one thread, wherever it runs)
    import numpy as np

    rng = np.random.default_rng(trial.seed)
    a, b = rng.normal(size=(400, 400)), rng.normal(size=(400, 400))
    return repr(float((a @ b).sum()))


def interrupt_at(trial: Trial) -> int:
    """spec (value, stop): a Ctrl-C arriving while this trial runs, when stop is set."""
    value, stop = trial.spec
    if stop:
        raise KeyboardInterrupt
    return value * 10


def not_json(trial: Trial) -> set:
    return {trial.spec}


# --------------------------------------------------------------------------------------------------


def test_trial_seed_is_a_function_of_study_seed_stream_and_index():
    assert trial_seed(0, "a", 3) == trial_seed(0, "a", 3)
    seeds = {trial_seed(s, st, i) for s in (0, 1) for st in ("a", "b") for i in range(5)}
    assert len(seeds) == 20
    assert [t.seed for t in make_trials(7, "x", "abc")] == [trial_seed(7, "x", i) for i in range(3)]
    assert [t.key for t in make_trials(7, "x", "abc", key_prefix="p")] == ["p/0", "p/1", "p/2"]
    with pytest.raises(ValueError):
        trial_seed(-1, "a", 0)


def test_results_in_trial_order_and_the_same_in_process_and_in_worker_processes():
    trials = make_trials(5, "squares", [(x, 0.05 * (6 - x)) for x in range(6)])
    arrived: list[str] = []
    with InProcess() as ex:
        here = ex.map(noisy_square, trials)
    with LocalProcesses(2) as ex:
        there = ex.map(noisy_square, trials, on_result=lambda t, r: arrived.append(t.key))
    assert [r["x2"] for r in there] == [x * x for x in range(6)]
    assert [r["pair"] for r in there] == [[x, -x] for x in range(6)]
    assert len({r["pid"] for r in there}) == 2 and os.getpid() not in {r["pid"] for r in there}
    assert arrived != [t.key for t in trials], "the later, shorter trials should have finished first"
    strip = [{k: v for k, v in r.items() if k != "pid"} for r in here], [{k: v for k, v in r.items() if k != "pid"}
                                                                           for r in there]
    assert strip[0] == strip[1]


def test_blas_threads_do_not_change_results():
    trials = make_trials(0, "matmul", range(3))
    with InProcess() as ex:
        here = ex.map(matmul_checksum, trials)
    with LocalProcesses(2) as ex:
        there = ex.map(matmul_checksum, trials)
    assert here == there


def test_batches_give_the_same_results_as_single_trials():
    trials = make_trials(1, "b", [(x, 0.0) for x in range(10)])
    with LocalProcesses(2) as ex:
        one = ex.map(noisy_square, trials)
        auto = ex.map(noisy_square, trials, batch_size="auto")
        four = ex.map(noisy_square, trials, batch_size=4)
    for a, b in ((one, auto), (one, four)):
        assert [r["draw"] for r in a] == [r["draw"] for r in b]


def test_results_must_be_json_and_keys_unique():
    with pytest.raises(TypeError, match="trial t/0"):
        InProcess().map(not_json, [Trial("t/0", 0, 1)])
    with pytest.raises(ValueError, match="unique"):
        InProcess().map(interrupt_at, [Trial("k", 0, (1, False)), Trial("k", 1, (2, False))])


def test_an_interrupted_study_keeps_its_finished_trials_and_resumes_from_them(tmp_path):
    path = tmp_path / "trials.jsonl"
    specs = [(v, False) for v in range(8)]
    stopped = [(v, v == 5) for v in range(8)]   # Ctrl-C during trial 5
    with pytest.raises(KeyboardInterrupt):
        with Study(InProcess(), Journal(path, {"study": "x"})) as study:
            study.map(interrupt_at, make_trials(0, "t", stopped))
    lines = path.read_text().splitlines()
    assert json.loads(lines[0]) == {"study": {"study": "x"}, "journal": 2}
    assert [json.loads(line)["key"] for line in lines[1:]] == [f"t/{i}" for i in range(5)]

    ran: list[str] = []
    with Study(InProcess(), Journal(path, {"study": "x"})) as study:
        assert study.journal.restored == 5
        resumed = study.map(interrupt_at, make_trials(0, "t", specs), on_result=lambda t, r: ran.append(t.key))
        study.finish()
    assert resumed == [v * 10 for v in range(8)]
    assert ran == [f"t/{i}" for i in range(8)]   # restored ones reported first, then the rest as run
    assert not path.exists(), "a finished study drops its journal"


def test_a_journal_cut_short_or_of_another_study(tmp_path, capsys):
    path = tmp_path / "trials.jsonl"
    j = Journal(path, {"seed": 1})
    for i in range(3):
        j.append(f"k/{i}", i)
    j.close()
    path.write_text(path.read_text() + '{"key": "k/3", "res')    # killed mid-line
    j = Journal(path, {"seed": 1})
    assert j.finished() == {"k/0": 0, "k/1": 1, "k/2": 2}
    j.append("k/3", 3)   # not glued onto the cut line
    j.close()
    assert Journal(path, {"seed": 1}).finished() == {"k/0": 0, "k/1": 1, "k/2": 2, "k/3": 3}
    capsys.readouterr()
    assert Journal(path, {"seed": 2}).finished() == {}   # another study: set aside, not mixed in
    assert "of another study" in capsys.readouterr().err
    assert (tmp_path / "trials.jsonl.old").exists() and not path.exists()


STUDY_SCRIPT = """
import sys
from lab.core.executor import Journal, LocalProcesses, Study, make_trials

def slow(trial):
    import time
    time.sleep(0.25)
    return trial.spec * 2

if __name__ == "__main__":
    with Study(LocalProcesses(2), Journal(sys.argv[1], {"demo": 1})) as study:
        out = study.concurrently({"a": lambda: study.map(slow, make_trials(0, "a", range(16))),
                                  "b": lambda: study.map(slow, make_trials(0, "b", range(16)))})
        print(out["a"] + out["b"])
        study.finish()
"""


def test_ctrl_c_on_worker_processes_keeps_finished_trials(tmp_path):
    script = tmp_path / "study.py"
    script.write_text(textwrap.dedent(STUDY_SCRIPT))
    journal = tmp_path / "trials.jsonl"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    p = subprocess.Popen([sys.executable, str(script), str(journal)], env=env, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, start_new_session=True)
    deadline = time.time() + 60
    while time.time() < deadline and (not journal.exists() or len(journal.read_text().splitlines()) < 5):
        time.sleep(0.05)
    os.killpg(p.pid, signal.SIGINT)   # a Ctrl-C at a terminal: the whole process group
    t0 = time.time()
    out, err = p.communicate(timeout=30)
    assert p.returncode != 0 and time.time() - t0 < 10, (p.returncode, err)
    kept = [json.loads(line)["key"] for line in journal.read_text().splitlines()[1:]]
    assert 4 <= len(kept) < 32
    r = subprocess.run([sys.executable, str(script), str(journal)], env=env, capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0, r.stderr
    assert f"resuming: {len(kept)} finished trials" in r.stderr
    assert json.loads(r.stdout) == [2 * i for i in range(16)] * 2
    assert not journal.exists()


def test_mle_study_identical_in_process_on_workers_and_on_dask():
    """The issue's test: a small study under every executor, the same figures apart from timings."""
    distributed = pytest.importorskip("distributed", reason="Dask is the `distributed` extra")
    from lab.studies import bench_mle
    from lab.core.executor import DaskCluster

    def run(executor) -> dict:
        with Study(executor) as study:
            return strip_timings(bench_mle.study_tetrahelix20(trials=8, seed=3, study=study))

    here = run(InProcess())
    assert differences(here, run(LocalProcesses(2))) == []
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        assert differences(here, run(DaskCluster(cluster.scheduler_address))) == []
    assert here["ekf"]["trials"] == 8 and here["ekf"]["trace_total_m2"] > 0


def test_strip_timings_and_differences():
    a = {"seconds": 1.0, "x": {"wall_s": 2, "update_ms_median": 3.0, "trace_m2": 1.5, "sigma_px_0.3": [1, 2]},
         "executor": "2 local processes", "find_locally_optimal_seconds_45": 9}
    assert strip_timings(a) == {"x": {"trace_m2": 1.5, "sigma_px_0.3": [1, 2]}}
    assert differences({"a": [1, float("nan")]}, {"a": [1, float("nan")]}) == []
    assert differences({"a": [1, 2]}, {"a": [1, 3], "b": 0}) == ["$.a[1]: 2 against 3", "$.b: only in second"]


def test_executor_choice_and_bad_values():
    assert isinstance(make_executor(1), InProcess)
    with pytest.raises(UserError, match="--workers"):
        make_executor(0)
    with pytest.raises(UserError, match="alternatives"):
        make_executor(2, "tcp://127.0.0.1:8786")
    for bad in ("foo://x:1", "tcp://:8786", "tcp://host", "tcp://host:99999", "tcp://h:1/path"):
        with pytest.raises(UserError, match="tcp://HOST:PORT"):
            make_executor(scheduler=bad)
    assert without_executor_args(["--quick", "--workers", "2", "--scheduler=tcp://h:1", "--seeds", "3"]) == \
        ["--quick", "--seeds", "3"]


def test_without_dask_the_error_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)   # import distributed -> ImportError
    with pytest.raises(UserError, match=r"pip install -e '\.\[distributed\]'"):
        make_executor(scheduler="tcp://127.0.0.1:8786")


def test_a_module_the_cluster_cannot_import_is_named():
    from lab.core.executor.backends import _missing_module

    try:
        try:
            import no_such_module_here  # noqa: F401
        except ModuleNotFoundError as exc:
            raise RuntimeError("Error during deserialization of the task graph") from exc
    except RuntimeError as exc:
        assert _missing_module(exc) == "no_such_module_here"
    assert _missing_module(RuntimeError("other")) is None


def test_no_scheduler_listening_is_one_line():
    pytest.importorskip("distributed")
    from lab.core.executor import DaskCluster

    with pytest.raises(UserError, match="no Dask scheduler answered"):
        DaskCluster("tcp://127.0.0.1:9", connect_timeout_s=1.0)


@pytest.mark.parametrize("argv, message", [
    (["--workers", "0"], "argument --workers: expected a whole number"),
    (["--workers", "two"], "argument --workers: expected a whole number"),
    (["--scheduler", "localhost"], "argument --scheduler: expected tcp://HOST:PORT"),
    (["--workers", "2", "--scheduler", "tcp://127.0.0.1:8786"], "not allowed with argument"),
])
def test_bench_flags_are_checked_in_one_line(lab, argv, message):
    r = lab(["bench", "mle", "--quick", *argv], timeout=60)
    assert r.returncode == 2
    assert len(r.stderr.strip().splitlines()) == 1 and message in r.stderr, r.stderr


def test_calibration_runs_side_by_side_give_the_figures_of_runs_one_after_another(lab, tmp_path):
    """Two `lab run borg` at once on one machine: each simulated bench on its own free ports, the
    same verdicts and errors as the same seeds run one after another."""
    out = {}
    for workers in (1, 2):
        d = tmp_path / f"w{workers}"
        r = lab(["bench", "calibration", "--seeds", "2", "--modules", "1", "--scales", "0", "--modes", "uncalibrated",
                 "--workers", str(workers), "--json", "--out", str(d)])
        assert r.returncode == 0, r.stderr
        out[workers] = json.loads((d / "calibration.json").read_text())
        assert not (d / "trials.jsonl").exists()
    assert out[2]["executor"] == "2 local processes" and out[2]["runs"] == 2
    assert [t["seed"] for t in out[2]["trials"]] == [0, 1]
    assert differences(strip_timings(out[1], frozenset({"command"})), strip_timings(out[2], frozenset({"command"}))) == []
