"""Where a study's trials run: in this process, in local worker processes, or on a Dask cluster.

Every executor gives the same results for the same trials: a trial carries its own seed, results
come back in trial order whatever finished first, and every result makes the same JSON round trip
(the journal's) whether it was computed now or read back from an interrupted run.  Trials are
handed over in batches (`batch_size`): one task per trial costs about a millisecond on local
processes and several on Dask, which matters for trials of a few milliseconds only."""

from __future__ import annotations

import contextlib
import json
import math
import os
import signal
import threading
from abc import ABC, abstractmethod
from typing import TYPE_CHECKING, Any, Callable, Iterator, Sequence

from lab.core.errors import UserError
from lab.core.executor.trials import Trial

if TYPE_CHECKING:
    from lab.core.executor.journal import Journal
    from lab.core.executor.progress import Progress

TrialFn = Callable[[Trial], Any]

# Each worker is one of N busy processes on N cores: a BLAS or OpenMP pool of its own would only
# oversubscribe the cores.  Set before numpy loads in the worker (this module imports no numpy),
# inherited by what a trial starts (a `lab run` subprocess); a value the user set is kept.
THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS",
                    "VECLIB_MAXIMUM_THREADS")
MAX_WORKERS = 512


def default_workers() -> int:
    """All cores this process may use (the affinity mask, where the OS has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


def _run_batch(fn: TrialFn, batch: Sequence[Trial]) -> list[Any]:
    """Run trials with BLAS and OpenMP at one thread wherever they run (module level: executors
    pickle it by reference).  Not only for speed: OpenBLAS splits a product differently on 2 threads
    than on 1, and the last bits of an EKF's figures with it; one thread everywhere keeps the same
    seed giving the same JSON.  (The limit covers the libraries loaded so far; in a worker the
    THREAD_VARIABLES cover the rest.)"""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1):
        return [fn(t) for t in batch]


def _as_json(key: str, value: Any) -> Any:
    try:
        return json.loads(json.dumps(value))
    except (TypeError, ValueError) as exc:
        raise TypeError(f"trial {key}: a result must be JSON (lists, dicts, numbers, strings): {exc}") from None


class TrialExecutor(ABC):
    workers: int = 1
    parallel: bool = True   # False: trials run in the calling thread, one at a time

    def map(self, fn: TrialFn, trials: Sequence[Trial], *, journal: Journal | None = None,
            progress: Progress | None = None, batch_size: int | str = 1,
            on_result: Callable[[Trial, Any], None] | None = None) -> list[Any]:
        """fn(trial) for every trial; the results in trial order.

        fn: a module-level function (pickled by reference) returning JSON values.  Trials already in
        the journal are not run again; every new result is journaled as it arrives.
        batch_size: trials per task, or "auto" (about 8 tasks per worker) for cheap, even trials.
        on_result(trial, result): called as each result arrives (completion order), restored ones
        first."""
        trials = list(trials)
        keys = [t.key for t in trials]
        if len(set(keys)) != len(keys):
            raise ValueError(f"trial keys must be unique; repeated: {sorted({k for k in keys if keys.count(k) > 1})[:5]}")
        finished = journal.finished() if journal is not None else {}
        results: list[Any] = [None] * len(trials)
        todo = []
        for i, t in enumerate(trials):
            if t.key in finished:
                results[i] = finished[t.key]
                if on_result is not None:
                    on_result(t, results[i])
            else:
                todo.append(i)
        if progress is not None:
            progress.add(len(trials), len(trials) - len(todo))
        size = self._batch(len(todo), batch_size)
        index_batches = [todo[k:k + size] for k in range(0, len(todo), size)]
        batches = [[trials[i] for i in ib] for ib in index_batches]
        with contextlib.closing(self._completed(fn, batches)) as completed:
            for b, out in completed:
                for i, value in zip(index_batches[b], out):
                    results[i] = value = _as_json(trials[i].key, value)
                    if journal is not None:
                        journal.append(trials[i].key, value)
                    if on_result is not None:
                        on_result(trials[i], value)
                if progress is not None:
                    progress.update(len(out))
        return results

    def _batch(self, n: int, batch_size: int | str) -> int:
        if batch_size == "auto":
            return max(1, math.ceil(n / (8 * max(self.workers, 1))))
        if not isinstance(batch_size, int) or batch_size < 1:
            raise ValueError(f"batch_size must be a positive integer or 'auto', got {batch_size!r}")
        return batch_size

    @abstractmethod
    def _completed(self, fn: TrialFn, batches: list[list[Trial]]) -> Iterator[tuple[int, list[Any]]]:
        """(batch index, its results) as batches finish; closing it cancels what has not started."""

    @abstractmethod
    def describe(self) -> str:
        """How the trials run, for the study's JSON and the user (not a result: it is a timing's context)."""

    def close(self) -> None:
        """The study is done: release the workers."""

    def abort(self) -> None:
        """Interrupted: drop queued trials and stop running ones where the backend can."""
        self.close()

    def __enter__(self) -> TrialExecutor:
        return self

    def __exit__(self, exc_type: Any, *exc: Any) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


class InProcess(TrialExecutor):
    """Trials one after another in this process (--workers 1): no start-up cost, nothing else on
    the cores while a trial is timed."""

    workers = 1
    parallel = False

    def _completed(self, fn: TrialFn, batches: list[list[Trial]]) -> Iterator[tuple[int, list[Any]]]:
        for b, batch in enumerate(batches):
            yield b, _run_batch(fn, batch)

    def describe(self) -> str:
        return "in-process"


def _init_worker() -> None:
    for var in THREAD_VARIABLES:
        os.environ.setdefault(var, "1")
    # Ctrl-C at a terminal reaches the whole process group: the parent decides (keep what finished,
    # stop the rest), so a worker neither dies mid-result nor prints a traceback of its own.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # terminate() from the parent: unwind, so that a trial's own subprocess (subprocess.run kills
    # it on the way out) does not outlive its worker.
    signal.signal(signal.SIGTERM, _exit_on_sigterm)


def _exit_on_sigterm(signum: int, frame: Any) -> None:
    raise SystemExit(128 + signum)


class LocalProcesses(TrialExecutor):
    """Trials in N worker processes on this machine (concurrent.futures.ProcessPoolExecutor).

    Started with `spawn`: the parent has threads (GTSAM's TBB pool, OpenCV's, a study's own), and a
    forked child inherits their locks in whatever state they were."""

    def __init__(self, workers: int) -> None:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        self.workers = workers
        self._pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                                         initializer=_init_worker)
        self._lock = threading.Lock()
        self._pending: set[Any] = set()
        self._aborted = threading.Event()

    def _completed(self, fn: TrialFn, batches: list[list[Trial]]) -> Iterator[tuple[int, list[Any]]]:
        from concurrent.futures import FIRST_COMPLETED, CancelledError, wait

        futures = {self._pool.submit(_run_batch, fn, batch): b for b, batch in enumerate(batches)}
        with self._lock:
            self._pending.update(futures)
        try:
            pending = set(futures)
            while pending:
                # not as_completed: a future cancelled by abort() never wakes its waiters (only the
                # pool's own cancellations do), so the wait polls the abort flag
                done, pending = wait(pending, timeout=0.2, return_when=FIRST_COMPLETED)
                for future in done:
                    yield futures[future], future.result()
                if self._aborted.is_set():
                    raise CancelledError("the study was interrupted")
        finally:
            for future in futures:
                future.cancel()   # no-op for the finished and the running
            with self._lock:
                self._pending.difference_update(futures)

    def describe(self) -> str:
        return f"{self.workers} local processes"

    def close(self) -> None:
        self._pool.shutdown(wait=True)

    def abort(self) -> None:
        self._aborted.set()
        with self._lock:
            pending = list(self._pending)
        for future in pending:
            future.cancel()
        # Python 3.14 has terminate_workers(); before it the pool keeps its processes in _processes.
        processes = list((getattr(self._pool, "_processes", None) or {}).values())
        self._pool.shutdown(wait=False, cancel_futures=True)
        for p in processes:
            if p.is_alive():
                p.terminate()
        for p in processes:
            p.join(timeout=5.0)
            if p.is_alive():
                p.kill()


class DaskCluster(TrialExecutor):
    """Trials on a Dask distributed cluster (`--scheduler tcp://HOST:PORT`).

    The scheduler and the workers import the trial functions by name: they must run this project's
    code (the same checkout, or the same installed version), see docs/benchmarks.md.  Paths in a trial (a study's
    --out) are the workers' paths: on several machines, a shared file system."""

    def __init__(self, address: str, *, connect_timeout_s: float = 10.0, wait_for_workers_s: float = 30.0) -> None:
        distributed = import_distributed()
        self.address = address
        try:
            self._client = distributed.Client(address, timeout=connect_timeout_s, set_as_default=False)
        except (OSError, TimeoutError) as exc:
            raise UserError(f"--scheduler {address}: no Dask scheduler answered ({exc}); "
                            "start one with `dask scheduler` (docs/benchmarks.md)") from None
        try:
            self._client.wait_for_workers(1, timeout=wait_for_workers_s)
        except (OSError, TimeoutError):
            self._client.close()
            raise UserError(f"--scheduler {address}: the scheduler has no workers after {wait_for_workers_s:g} s; "
                            f"start some with `dask worker {address}`") from None
        self.workers = sum(self._client.nthreads().values())
        self._lock = threading.Lock()
        self._pending: set[Any] = set()

    def _completed(self, fn: TrialFn, batches: list[list[Trial]]) -> Iterator[tuple[int, list[Any]]]:
        import distributed

        futures = [self._client.submit(_run_batch, fn, batch, pure=False) for batch in batches]
        index = {f.key: b for b, f in enumerate(futures)}
        with self._lock:
            self._pending.update(futures)
        try:
            for future, out in distributed.as_completed(futures, loop=self._client.loop, with_results=True):
                yield index[future.key], out
        except Exception as exc:
            missing = _missing_module(exc)
            if missing is None:
                raise
            # the scheduler unpickles the tasks too (it reports it as a RuntimeError caused by this)
            raise UserError(f"the Dask cluster cannot import {missing!r}: start its scheduler and workers from this "
                            "project's environment (the same checkout on PYTHONPATH, or pip install -e "
                            "'.[distributed]'), see docs/benchmarks.md") from None
        finally:
            left = [f for f in futures if not f.done()]
            if left:
                self._client.cancel(left)
            with self._lock:
                self._pending.difference_update(futures)

    def describe(self) -> str:
        return f"Dask at {self.address} ({self.workers} worker threads)"

    def close(self) -> None:
        self._client.close()

    def abort(self) -> None:
        # Dask cannot stop a task that has started: queued trials are dropped, running ones finish
        # on their workers and are forgotten.
        with self._lock:
            pending = list(self._pending)
        if pending:
            self._client.cancel(pending)
        self._client.close()


def _missing_module(exc: BaseException | None) -> str | None:
    """The module a ModuleNotFoundError in `exc` or its causes names, if there is one."""
    seen = 0
    while exc is not None and seen < 10:
        if isinstance(exc, ModuleNotFoundError):
            return exc.name or str(exc)
        exc, seen = exc.__cause__ or exc.__context__, seen + 1
    return None


def import_distributed() -> Any:
    try:
        import distributed
    except ImportError:
        raise UserError("--scheduler runs trials on Dask, which is not installed: "
                        "pip install -e '.[distributed]'") from None
    return distributed


def check_workers(workers: int) -> int:
    if isinstance(workers, bool) or not isinstance(workers, int) or not 1 <= workers <= MAX_WORKERS:
        raise UserError(f"--workers must be a whole number from 1 to {MAX_WORKERS}, got {workers!r}")
    return workers


def check_scheduler(address: str) -> str:
    """tcp://HOST:PORT (or tls://), normalised; HOST:PORT alone means tcp, as Dask reads it."""
    import urllib.parse

    text = address.strip()
    if "://" not in text:
        text = "tcp://" + text
    parts = urllib.parse.urlsplit(text)
    try:
        port = parts.port
    except ValueError:
        port = None
    if parts.scheme not in ("tcp", "tls") or not parts.hostname or port is None or not 0 < port < 65536 \
            or parts.path not in ("", "/") or parts.query or parts.fragment:
        raise UserError(f"--scheduler must be tcp://HOST:PORT (a Dask scheduler's address), got {address!r}")
    return f"{parts.scheme}://{parts.netloc}"


def make_executor(workers: int | None = None, scheduler: str | None = None) -> TrialExecutor:
    """--scheduler: a Dask cluster; else --workers N local processes (default: all cores; 1: this
    process)."""
    if scheduler is not None:
        if workers is not None:
            raise UserError("--workers and --scheduler are alternatives: the cluster's workers run the trials")
        return DaskCluster(check_scheduler(scheduler))
    n = check_workers(workers) if workers is not None else default_workers()
    return InProcess() if n == 1 else LocalProcesses(n)
