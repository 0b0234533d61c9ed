"""A procedure built from a run's parameters (the CLI's, as run.json keeps them): `lab run` builds
a run with it, `lab resume` builds it again, `lab bench replay` builds a finished run's offline."""

from __future__ import annotations

from typing import Any

from procedures.setup import Bench, check_borg_n, open_bench


def build_procedure(procedure: str, params: dict[str, Any], offline: bool = False) -> tuple[Any, Bench, str]:
    """(procedure object, bench, structure name); `offline`: no simulator and no device claimed
    (`open_bench`), for replaying a run's estimator."""
    n = check_borg_n(params.get("n")) if procedure == "borg" else None
    bench = open_bench(params.get("rig"), params.get("scenario"), speedup=params.get("speedup"), borg_n=n,
                       offline=offline)
    try:
        if procedure == "truss":
            from procedures.truss import TrussProcedure

            proc = TrussProcedure(bench, params["name"], params.get("estimator", "mle"), params.get("plan"),
                                  params.get("plan_seed", 0))
            return proc, bench, params["name"]
        from procedures.borg import BorgProcedure

        proc = BorgProcedure(bench, on_flag=params.get("on_flag", "stop"), n=params.get("n"),
                             max_modules=params.get("modules"), calibration=params.get("calibration"),
                             rig_survey=False if params.get("no_rig_survey") else None,
                             observation=params.get("observation"), uncalibrated=bool(params.get("uncalibrated")),
                             tolerances=params.get("tolerance"), sigma_target_mm=params.get("sigma_target_mm"),
                             max_views=params.get("max_views"),
                             allow_unobservable=bool(params.get("allow_unobservable")))
        return proc, bench, f"borg:{proc.model.n}"
    except BaseException:
        bench.close()
        raise
