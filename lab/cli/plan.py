"""`lab plan truss NAME`: an IPJR assembly sequence for a tetrahedral truss -- the steps (float
node on its ordered base triple), the parallel layers and the open-loop covariance trace."""

from __future__ import annotations

import argparse
import json
import math

METHODS = ("locally-optimal", "greedy", "random")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("plan", help="plan an assembly sequence")
    psub = p.add_subparsers(dest="plan_kind", metavar="KIND")
    psub.required = True
    t = psub.add_parser("truss", help="IPJR sequence for a tetrahedral truss, e.g. tetrahelix:20, telescope:84")
    t.add_argument("name", help="truss name: tetrahelix:N[:edge_m] or telescope:N")
    t.add_argument("--method", choices=METHODS, default="locally-optimal",
                   help="locally-optimal = central triangle + greedy + local search (default); greedy; random")
    t.add_argument("--sigma-l", type=float, default=math.sqrt(3.57e-7), metavar="M",
                   help="strut length standard deviation in metres for the trace (default sqrt(3.57e-7), the paper's)")
    t.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    t.add_argument("--json", action="store_true", help="print the plan as JSON")
    t.set_defaults(func=_plan_truss)


def _plan_truss(args: argparse.Namespace) -> int:
    import numpy as np

    from estimation.sequencing import Planner, all_central_triangles, random_sequence
    from estimation.truss_covariance import node_traces
    from lab.core.errors import UserError
    from lab.core.structures.trusses import build_truss

    if not (args.sigma_l > 0 and math.isfinite(args.sigma_l)):
        raise UserError(f"--sigma-l must be a positive length in metres, got {args.sigma_l}")
    model = build_truss(args.name)
    planner = Planner(model)
    rng = np.random.default_rng(args.seed)
    if args.method == "locally-optimal":
        plan = planner.locally_optimal(rng).plan
    else:
        central = all_central_triangles(model, rng, planner.geometry)
        if not central:
            raise UserError(f"{model.name} has no starting triangle from which it can be assembled")
        tri = central[int(rng.integers(len(central)))]
        if args.method == "greedy":
            result = planner.greedy(tri)
            plan = result.plan if result is not None else None
        else:
            plan = random_sequence(model, tri, "any", rng, planner.geometry)
        if plan is None:
            raise UserError(f"{model.name} cannot be completed from starting triangle {tri}")
    per_node = node_traces(model.nodes, plan, args.sigma_l, planner.sens)
    total = float(per_node.sum())
    if args.json:
        doc = {"truss": model.name, "method": args.method, "sigma_L_m": args.sigma_l, "trace_m2": total,
               "trace_per_sigma_L2": total / args.sigma_l ** 2, "n_layers": len(plan.layers), **plan.to_json()}
        for step in doc["steps"]:
            step["trace_m2"] = float(per_node[step["node"]])
        print(json.dumps(doc, indent=1))
        return 0
    a, b, c = plan.triangle
    print(f"{model.name}: {model.n_nodes} nodes, {len(model.edges)} struts; method {args.method}; "
          f"starting triangle ({a}, {b}, {c})")
    print(f"{'t':>3} {'node':>5}  {'base (ordered)':<16} {'node trace [m^2]':>16}")
    for s in plan.steps:
        base = ", ".join(str(v) for v in s.base)
        print(f"{plan.times[s.node]:>3} {s.node:>5}  ({base}){'':<{max(0, 14 - len(base))}} {per_node[s.node]:>16.4g}")
    print("layers: " + "  ".join(f"t={t}:{','.join(str(v) for v in layer)}" for t, layer in enumerate(plan.layers, 1)))
    print(f"{len(plan.layers)} parallel layers; open-loop trace {total:.4g} m^2 at sigma_L = {args.sigma_l:.4g} m "
          f"({total / args.sigma_l ** 2:.4g} sigma_L^2)")
    return 0
