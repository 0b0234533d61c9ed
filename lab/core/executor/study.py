"""A study's run: where its trials go (the executor), where finished ones are kept (the journal),
what the user sees (the progress bar).  Benches build one with `open_study` and hand it to their
study functions, which call `study.map(fn, trials)`."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Sequence, TypeVar

from lab.core.executor.backends import InProcess, TrialExecutor, TrialFn
from lab.core.executor.journal import Journal
from lab.core.executor.progress import Progress
from lab.core.executor.trials import Trial

T = TypeVar("T")


@dataclass
class Study:
    executor: TrialExecutor = field(default_factory=InProcess)
    journal: Journal | None = None
    progress: Progress | None = None

    def map(self, fn: TrialFn, trials: Sequence[Trial], *, batch_size: int | str = 1,
            on_result: Callable[[Trial, Any], None] | None = None) -> list[Any]:
        """fn(trial) for each trial, results in trial order (`TrialExecutor.map`)."""
        return self.executor.map(fn, trials, journal=self.journal, progress=self.progress, batch_size=batch_size,
                                 on_result=on_result)

    def concurrently(self, parts: dict[str, Callable[[], T]]) -> dict[str, T]:
        """Run a bench's independent parts at the same time, each mapping its trials onto the shared
        executor, so that one part's serial stretch (planning its trials, say) overlaps another's
        trials.  The parts' threads only wait on the workers.  One after another where the trials
        run in this thread (`InProcess`): there, threads would only interleave the timings."""
        if not self.executor.parallel or len(parts) < 2:
            return {name: part() for name, part in parts.items()}
        from concurrent.futures import FIRST_EXCEPTION, ThreadPoolExecutor, wait

        pool = ThreadPoolExecutor(len(parts), thread_name_prefix="study-part")
        futures = {name: pool.submit(part) for name, part in parts.items()}
        try:
            done, _ = wait(futures.values(), return_when=FIRST_EXCEPTION)
            for future in done:
                future.result()   # the first failure, raised here
            return {name: future.result() for name, future in futures.items()}
        except BaseException:
            # a failure or Ctrl-C: cancel every part's trials, so the other threads stop waiting
            self.executor.abort()
            raise
        finally:
            pool.shutdown(wait=True)

    def describe(self) -> str:
        return self.executor.describe()

    def say(self, text: str) -> None:
        """A line for the user on stdout (above the progress bar, if one is drawn)."""
        if self.progress is not None:
            self.progress.write(text)
        else:
            print(text, flush=True)

    def finish(self) -> None:
        """The study's output is written: drop the journal (a rerun measures afresh)."""
        if self.journal is not None:
            self.journal.finish()

    def __enter__(self) -> Study:
        return self

    def __exit__(self, exc_type: Any, *exc: Any) -> None:
        try:
            if self.progress is not None:
                self.progress.close()
        finally:
            try:
                self.executor.__exit__(exc_type, *exc)
            finally:
                if self.journal is not None:
                    self.journal.close()
