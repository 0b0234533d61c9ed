"""`lab bench NAME`: benchmarks that print measured figures (speed and accuracy targets live here,
never in timed unit tests).  Each benchmark is a module exposing `add_arguments(parser)` and
`run(args) -> int`; it is imported only when its command runs."""

from __future__ import annotations

import argparse
import importlib

from lab.cli import LabParser

BENCHES: dict[str, tuple[str, str]] = {
    # name: (module, one-line help)
    "slam": ("lab.studies.bench_slam", "GraphSLAM vs SF-GraphSLAM vs the paper's Powell method (Monte Carlo)"),
    "fiducials": ("lab.studies.bench_fiducials", "AprilTag detection time and pose error on rendered images; image "
                                               "quality (edge spread, noise) of photographs vs the simulator"),
    "mle": ("lab.studies.bench_mle", "IPJR sequencing, MLE vs EKF vs open loop"),
    "run": ("lab.studies.bench_run", "end-to-end simulated procedure runs (BORG, tetrahelix)"),
    "calibration": ("lab.studies.bench_calibration", "BORG verdicts and accuracy against rig-error size, with and "
                                                   "without rig calibration"),
    "trust": ("lab.studies.bench_trust", "verdicts, accuracy and honest 1-sigma against rig-error size and "
                                             "camera quality"),
    "layers": ("lab.studies.bench_layers", "every BORG module verified, layer by layer, at N = 3..10: faults in every "
                                           "layer, unverified, false flags, error against truth and 1-sigma, cost"),
    "replay": ("lab.studies.bench_replay", "a BORG run's estimator again from its checkpoint: CPU per round and "
                                           "part (solve, marginals, verdict, release), verdicts against the run's; "
                                           "a simulated run's rig in the graph against the truth"),
    "faults": ("lab.studies.bench_faults", "the fault campaign: device faults, kills, signals, bad input, abuse"),
}


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="run a benchmark and print its figures")
    bench_sub = p.add_subparsers(dest="bench", metavar="NAME", parser_class=_StudyParser)
    bench_sub.required = True
    for name, (module_name, help_text) in BENCHES.items():
        bp = bench_sub.add_parser(name, help=help_text)
        bp.study = (name, module_name)
        bp.set_defaults(func=_runner(module_name), _bench_parser=bp, lab_main=_lab_main)


class _StudyParser(LabParser):
    """The parser of `lab bench NAME`: the study's own flags are added when this parser is first
    used (`lab bench NAME ...`), so the study is imported only when its command runs and `lab
    --help` imports no study."""

    study: tuple[str, str] | None = None

    def _load_study(self) -> None:
        if self.study is None:
            return
        name, module_name = self.study
        self.study = None
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            if exc.name != module_name:
                raise
            self.set_defaults(func=_missing(name))
            return
        module.add_arguments(self)

    def parse_known_args(self, args=None, namespace=None):  # type: ignore[override]
        self._load_study()
        return super().parse_known_args(args, namespace)

    def format_help(self) -> str:
        self._load_study()
        return super().format_help()

    def format_usage(self) -> str:
        self._load_study()
        return super().format_usage()


def _runner(module_name: str):
    def run(args: argparse.Namespace) -> int:
        return importlib.import_module(module_name).run(args)

    return run


def _lab_main(argv: list[str]) -> int:
    """`lab ARGV` in this process, for a study that runs commands (the fault campaign): the studies
    sit below the CLI and get it from here, as `args.lab_main`, instead of importing it."""
    from lab.cli import main

    return main(argv)


def _missing(name: str):
    def run(args: argparse.Namespace) -> int:
        from lab.core.errors import UserError

        raise UserError(f"benchmark {name!r} is not available in this build")

    return run
