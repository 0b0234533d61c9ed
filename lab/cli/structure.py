"""`lab structure borg|truss`: print a design model (text summary, or JSON with --json)."""

from __future__ import annotations

import argparse
import json


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("structure", help="print a structure's design model")
    ssub = p.add_subparsers(dest="kind", metavar="KIND")
    ssub.required = True

    b = ssub.add_parser("borg", help="the BORG N x N x N truss (N = 3 is the paper's, Table 1)")
    b.add_argument("--n", type=int, default=3, help="cells per side, >= 2 (default 3)")
    b.add_argument("--spacing", type=float, default=0.5, help="node spacing in metres (default 0.5)")
    b.add_argument("--json", action="store_true", help="print the full model as JSON")
    b.add_argument("--plot", metavar="PNG", help="also render the layout to this PNG file")
    b.set_defaults(func=_borg)

    t = ssub.add_parser("truss", help="a tetrahedral IPJR truss, e.g. tetrahelix:20, telescope:84")
    t.add_argument("name")
    t.add_argument("--json", action="store_true", help="print the full model as JSON")
    t.set_defaults(func=_truss)


def _borg(args: argparse.Namespace) -> int:
    from lab.core.errors import UserError
    from lab.core.structures.borg import build_borg, to_json

    try:
        model = build_borg(args.n, args.spacing)
    except ValueError as exc:
        raise UserError(str(exc)) from exc
    if args.plot:
        from pathlib import Path

        from lab.core.structures.borg_plot import plot_borg

        target = Path(args.plot)
        if not target.parent.is_dir():
            raise UserError(f"--plot {target}: no such directory {target.parent}")
        try:
            plot_borg(model, target)
        except OSError as exc:
            raise UserError(f"--plot {target}: cannot write it: {exc.strerror or exc}") from None
    if args.json:
        print(json.dumps(to_json(model), indent=1))
        return 0
    print(f"BORG {model.n}x{model.n}x{model.n}, {model.spacing_m} m cells: {len(model.nodes)} nodes, "
          f"{len(model.edges)} struts, {len(model.modules)} modules, {len(model.tags)} tags "
          f"({len(model.turntable.tag_ids)} on the turntable), {len(model.relations)} relations")
    print(f"{'#':>3} {'module':<7} {'type':<16} {'face':>4}  tags")
    for i, m in enumerate(model.modules, start=1):
        labels = ", ".join(f"{t} ({model.tags[t].label})" for t in m.tags)
        print(f"{i:>3} {m.name:<7} {m.kind:<16} {m.face:>4}  {labels}")
    return 0


def _truss(args: argparse.Namespace) -> int:
    from lab.core.structures.trusses import build_truss, to_json

    model = build_truss(args.name)
    if args.json:
        print(json.dumps(to_json(model), indent=1))
        return 0
    print(f"{model.name}: {len(model.nodes)} nodes, {len(model.edges)} struts")
    return 0
