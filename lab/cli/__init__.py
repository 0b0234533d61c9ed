"""`lab` command line.  Each command group lives in its own module under `lab/cli/` and exposes
`register(subparsers)`; heavy imports happen inside the command functions so `lab --help` is fast
and the kernel never imports the layers above it at import time.

Errors a user can cause are one line and exit 2, argparse's own included: `LabParser` prints
`lab run borg: error: ...` with a suggestion for a mistyped command, choice or flag (difflib; Python
3.14's argparse `suggest_on_error` does the same, we run on 3.11) and a pointer to `--help`,
instead of the usage block."""

from __future__ import annotations

import argparse
import difflib
import importlib
import re
import sys

from lab.core.errors import UserError

DESCRIPTION = ("lab: hardware-in-the-loop control of the robotic-assembly lab: BORG truss assembly measured "
               "with SF-GraphSLAM, IPJR truss assembly, camera and rig calibration, on real or simulated devices; "
               "every run recorded to MCAP, reviewed in Rerun.")
EPILOG = ("Start with: lab run borg --auto --out runs/demo (a full simulated run), then lab review "
          "runs/demo/run.mcap. `lab COMMAND --help` for any command; docs/ has the details.")


class LabParser(argparse.ArgumentParser):
    """argparse, with one-line errors that suggest what was probably meant."""

    def error(self, message: str) -> "NoReturn":  # type: ignore[name-defined]
        self.exit(2, f"{self.prog}: error: {message}{self._suggest(message)}; see `{self.prog} --help`\n")

    def _suggest(self, message: str) -> str:
        m = re.search(r"invalid choice: '([^']*)' \(choose from (.*)\)", message)
        if m:
            choices = re.findall(r"'([^']*)'", m.group(2)) or [c.strip() for c in m.group(2).split(",")]
            close = difflib.get_close_matches(m.group(1), choices, n=1, cutoff=0.5)
            return f" (did you mean '{close[0]}'?)" if close else ""
        m = re.search(r"unrecognized arguments: (.*)", message)
        if m:
            known = [o for a in self._actions for o in a.option_strings]
            hints = []
            for arg in m.group(1).split():
                if arg.startswith("-"):
                    close = difflib.get_close_matches(arg.split("=", 1)[0], known, n=1, cutoff=0.6)
                    if close:
                        hints.append((arg, close[0]))
            if len(hints) == 1:
                return f" (did you mean {hints[0][1]}?)"
            return f" (did you mean {', '.join(f'{good} for {bad}' for bad, good in hints)}?)" if hints else ""
        return ""


def version_text() -> str:
    """`lab --version`: the installed distribution's version, else the source tree's pyproject."""
    from importlib import metadata
    from pathlib import Path

    try:
        return f"lab (truss-lab) {metadata.version('truss-lab')}"
    except metadata.PackageNotFoundError:
        import tomllib

        pyproject = Path(__file__).resolve().parents[2] / "pyproject.toml"
        try:
            return f"lab (truss-lab) {tomllib.loads(pyproject.read_text())['project']['version']} (source tree)"
        except (OSError, KeyError, tomllib.TOMLDecodeError):
            return "lab (truss-lab) unknown version"

# Command-group modules, in help order.  A module that fails to import is reported, not hidden.
COMMAND_MODULES = [
    "lab.cli.structure",   # lab structure borg|truss
    "lab.cli.recording",   # lab recover, lab review
    "lab.cli.devices",     # lab sim, lab devices check, lab stewart ik
    "lab.cli.rig",         # lab rig check
    "lab.cli.plan",        # lab plan truss
    "lab.cli.bench",       # lab bench slam|mle|...
    "lab.cli.run",         # lab run borg|truss, lab resume, lab calibrate
    "lab.cli.runs",        # lab runs, lab runs show
    "lab.cli.calibrate",   # lab calibrate camera|board
]


def build_parser() -> argparse.ArgumentParser:
    parser = LabParser(prog="lab", description=DESCRIPTION, epilog=EPILOG)
    parser.add_argument("--version", action="version", version=version_text())
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name == name:
                continue  # that command group has not been written yet
            raise
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if extra:
        # an unknown flag belongs to the subcommand it was typed for: say so there, with its options
        _deepest(parser, sys.argv[1:] if argv is None else argv).error(f"unrecognized arguments: {' '.join(extra)}")
    try:
        rc = args.func(args)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except UserError as exc:
        print(f"lab: error: {exc}", file=sys.stderr)
        return 2
    except EOFError:
        # stdin ended while a question waited for its answer (a closed pipe, Ctrl-D)
        print("lab: error: end of input while waiting for an answer; answer at a terminal, or use --auto "
              "where the command has it", file=sys.stderr)
        return 2
    except BrokenPipeError:
        # the reader went away (`lab ... | head`): not an error of ours; silence the final flush
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    return int(rc or 0)


def _deepest(parser: argparse.ArgumentParser, argv: list[str]) -> argparse.ArgumentParser:
    """The (sub)parser the command line reached: `lab run borg --atuo` -> the `run borg` parser."""
    p = parser
    for token in argv:
        subs = [a for a in p._actions if isinstance(a, argparse._SubParsersAction)]
        if subs and token in subs[0].choices:
            p = subs[0].choices[token]
    return p


if __name__ == "__main__":
    sys.exit(main())
