"""`lab` command line.  Each command group lives in its own module under `lab/cli/` and exposes
`register(subparsers)`; heavy imports happen inside the command functions so `lab --help` is fast
and the kernel never imports the layers above it at import time."""

from __future__ import annotations

import argparse
import importlib
import sys

from lab.errors import UserError

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
    parser = argparse.ArgumentParser(prog="lab", description=__doc__.splitlines()[0])
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
    args = parser.parse_args(argv)
    try:
        rc = args.func(args)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except UserError as exc:
        print(f"lab: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        # the reader went away (`lab ... | head`): not an error of ours; silence the final flush
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    return int(rc or 0)


if __name__ == "__main__":
    sys.exit(main())
