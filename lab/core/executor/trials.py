"""A study's unit of work and its seed.

A trial carries everything it needs, its seed included, so that whichever process or machine runs
it, and in whatever order, it draws the same numbers: a seed is derived from the study's seed, the
name of the random stream and the trial's index, never from the state of a worker."""

from __future__ import annotations

import zlib
from dataclasses import dataclass
from typing import Any, Iterable


@dataclass(frozen=True)
class Trial:
    key: str        # unique within the study and stable between runs: names the trial in the journal
    seed: int       # the trial's own seed (`trial_seed`), or a seed the study fixes itself
    spec: Any = None  # what to run: small and picklable (a module-level dataclass, tuple, dict)


def trial_seed(study_seed: int, stream: str, index: int) -> int:
    """The seed of trial `index` of `stream` in a study seeded `study_seed`.

    numpy's SeedSequence spawn keys give statistically independent streams per (stream, index);
    naming the stream (rather than numbering studies) keeps one study's seeds unchanged when
    another study is added or dropped.  Trials of different estimators compared on the same
    simulated assemblies share a stream (common random numbers)."""
    import numpy as np

    if study_seed < 0 or index < 0:
        raise ValueError(f"seeds and trial indices are non-negative, got {study_seed}, {index}")
    ss = np.random.SeedSequence(entropy=int(study_seed), spawn_key=(zlib.crc32(stream.encode()), int(index)))
    return int(ss.generate_state(1, np.uint64)[0])


def make_trials(study_seed: int, stream: str, specs: Iterable[Any], key_prefix: str | None = None) -> list[Trial]:
    """One trial per spec, keyed `PREFIX/INDEX` (prefix: the stream), seeded by `trial_seed`."""
    prefix = stream if key_prefix is None else key_prefix
    return [Trial(f"{prefix}/{i}", trial_seed(study_seed, stream, i), spec) for i, spec in enumerate(specs)]
