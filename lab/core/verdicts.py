"""A module's verdict, the one record of it from the estimator to the operator: the verdict names,
their tally, and the record the console's row, summary.json, the run's log (and so `lab review`)
and a checkpoint are all written from.

The estimator makes the record (`estimation.verification.verify_module`: what it measured and the
tolerance it judged by); the BORG procedure adds what only it knows with `dataclasses.replace`
before anyone reads it (views, attempts, the plan's predicted 1-sigma, and in simulation the error
against the truth and the Cramér-Rao bound).  What each verdict means: estimation/verification.py.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Iterable, Mapping

import numpy as np

from lab.core.geometry import Pose3

OK = "ok"
FLAGGED = "flagged"
UNCERTAIN = "uncertain"
UNVERIFIED = "unverified"
# in the order a tally is printed
VERDICTS = (OK, FLAGGED, UNCERTAIN, UNVERIFIED)


def tally(verdicts: Iterable[str]) -> dict[str, int]:
    """How many of each verdict, every name present (0 where none), in VERDICTS order."""
    seen = list(verdicts)
    return {v: seen.count(v) for v in VERDICTS}


@dataclass(frozen=True)
class Bound:
    """Simulation: the best 1-sigma any estimator could give the module from the same views."""

    position_m: float
    rotation_rad: float
    position_rms_m: float        # sqrt(trace): the expected RMS of the 3-D position error


@dataclass(frozen=True)
class TruthError:
    """Simulation: the module's estimate against the simulated truth."""

    position_m: float
    rotation_rad: float
    position_vector_m: tuple[float, ...] | None   # estimate - truth, structure frame
    nees: float | None = None               # error' covariance^-1 error (dimension 3), given a covariance


@dataclass(frozen=True)
class Verdict:
    """A module's verdict with everything a reader of it needs, SI units (see the module's docstring)."""

    module: str
    verdict: str                         # one of VERDICTS
    reason: str
    estimate: Pose3 | None               # structure_T_module
    deviation_m: float | None            # against the design
    deviation_rad: float | None
    sigma_m: float | None                # 1-sigma position uncertainty of the module (worst direction)
    tags_used: tuple[int, ...]           # its usable tags; the estimate is read from the first
    sigma_rad: float | None = None       # 1-sigma rotation uncertainty
    position_covariance: np.ndarray | None = None   # 3x3, structure frame, of the module's position
    tolerance_m: float | None = None     # the tolerance it was judged by
    tolerance_rad: float | None = None
    tags_seen: tuple[int, ...] = ()      # the module's tags that were measured, rejected ones too
    # the procedure's
    views: int = 0                       # views taken for this verdict (all rounds)
    attempts: int = 1                    # 2 and more: measured again after the operator re-deployed it
    predicted_sigma_m: float | None = None   # what the plan expected of its views
    bound: Bound | None = None
    truth: TruthError | None = None

    def summary_row(self) -> dict[str, Any]:
        """The module's entry in summary.json, which the console's table row is printed from."""
        t, b = self.truth, self.bound
        return {"name": self.module, "verdict": self.verdict, "reason": self.reason,
                "position_error_m": t.position_m if t else None, "rotation_error_rad": t.rotation_rad if t else None,
                "deviation_m": self.deviation_m, "deviation_rad": self.deviation_rad,
                "sigma_position_m": self.sigma_m, "tolerance_m": self.tolerance_m,
                "tolerance_rad": self.tolerance_rad, "tags_seen": list(self.tags_seen), "attempts": self.attempts,
                "sigma_rotation_rad": self.sigma_rad, "views": self.views, "predicted_sigma_m": self.predicted_sigma_m,
                "bound_position_m": b.position_m if b else None, "bound_rotation_rad": b.rotation_rad if b else None,
                "bound_position_rms_m": b.position_rms_m if b else None,
                "position_covariance_m2": (None if self.position_covariance is None
                                           else self.position_covariance.tolist()),
                "position_error_vector_m": (list(t.position_vector_m) if t and t.position_vector_m is not None
                                            else None),
                "position_nees": t.nees if t else None}

    def checkpoint_json(self) -> dict[str, Any]:
        """What a checkpoint keeps: the summary's entry without the tolerance (a resumed run judges
        by its own)."""
        return {k: v for k, v in self.summary_row().items() if k not in _NOT_CHECKPOINTED}

    @classmethod
    def from_checkpoint(cls, d: Mapping[str, Any], tolerance_m: float | None,
                        tolerance_rad: float | None) -> Verdict:
        """A verdict of a completed step, for a resumed run's summary; the estimate and the tag it was
        read from stay with the run that measured it (a resumed run's estimator has them again)."""
        unknown = sorted(set(d) - set(_CHECKPOINT_DEFAULTS))
        if unknown:
            raise TypeError(f"unexpected key {unknown[0]!r} in a module's result")
        f = {**_CHECKPOINT_DEFAULTS, **d}
        cov, vector = f["position_covariance_m2"], f["position_error_vector_m"]
        truth = (None if f["position_error_m"] is None else
                 TruthError(f["position_error_m"], f["rotation_error_rad"],
                            None if vector is None else tuple(vector), f["position_nees"]))
        bound = (None if f["bound_position_m"] is None else
                 Bound(f["bound_position_m"], f["bound_rotation_rad"], f["bound_position_rms_m"]))
        return cls(d["name"], f["verdict"], f["reason"], None, f["deviation_m"], f["deviation_rad"],
                   f["sigma_position_m"], (), f["sigma_rotation_rad"], None if cov is None else np.asarray(cov),
                   tolerance_m, tolerance_rad, tuple(f["tags_seen"]), f["views"], f["attempts"],
                   f["predicted_sigma_m"], bound, truth)


_NOT_CHECKPOINTED = ("tolerance_m", "tolerance_rad")
# a checkpoint's module result: its keys, and what one missing (a checkpoint older than the key) reads as
_CHECKPOINT_DEFAULTS: dict[str, Any] = {
    "name": None, "verdict": UNVERIFIED, "reason": "", "position_error_m": None, "rotation_error_rad": None,
    "deviation_m": None, "deviation_rad": None, "sigma_position_m": None, "tags_seen": [], "attempts": 1,
    "sigma_rotation_rad": None, "views": 0, "predicted_sigma_m": None, "bound_position_m": None,
    "bound_rotation_rad": None, "bound_position_rms_m": None, "position_covariance_m2": None,
    "position_error_vector_m": None, "position_nees": None}
