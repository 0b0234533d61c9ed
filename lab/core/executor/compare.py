"""Compare two studies' JSON apart from timings: the check that an executor changed nothing.

    python -m lab.core.executor.compare bench_out/mle-local/mle.json bench_out/mle-dask/mle.json

prints `identical apart from timings` (exit 0) or the paths that differ (exit 1).  A timing is a
key one of whose underscore-separated words is seconds, s, ms or wall (`seconds`, `wall_s`,
`update_ms_median`, `find_locally_optimal_seconds_45`), plus `executor` (how the trials ran).
`--ignore KEY` leaves out more keys, e.g. a `command` that names two different --out directories."""

from __future__ import annotations

import json
import sys
from typing import Any

TIMING_WORDS = frozenset({"seconds", "s", "ms", "wall"})
IGNORED_KEYS = frozenset({"executor"})


def is_timing(key: str) -> bool:
    return key in IGNORED_KEYS or bool(TIMING_WORDS & set(key.split("_")))


def strip_timings(value: Any, ignore: frozenset[str] = frozenset()) -> Any:
    """The value without its timing keys (and `ignore`), at any depth."""
    if isinstance(value, dict):
        return {k: strip_timings(v, ignore) for k, v in value.items() if not is_timing(str(k)) and k not in ignore}
    if isinstance(value, list):
        return [strip_timings(v, ignore) for v in value]
    return value


def differences(a: Any, b: Any, path: str = "$", limit: int = 20) -> list[str]:
    """Where two JSON values differ (first `limit`), timings included: strip them first."""
    out: list[str] = []

    def walk(x: Any, y: Any, p: str) -> None:
        if len(out) >= limit:
            return
        if isinstance(x, dict) and isinstance(y, dict):
            for k in sorted(set(x) | set(y), key=str):
                if k not in x or k not in y:
                    out.append(f"{p}.{k}: only in {'second' if k in y else 'first'}")
                else:
                    walk(x[k], y[k], f"{p}.{k}")
        elif isinstance(x, list) and isinstance(y, list):
            if len(x) != len(y):
                out.append(f"{p}: {len(x)} items against {len(y)}")
            for i, (u, v) in enumerate(zip(x, y)):
                walk(u, v, f"{p}[{i}]")
        elif x != y and not (x != x and y != y):   # NaN equals NaN here: the same result
            out.append(f"{p}: {x!r} against {y!r}")

    walk(a, b, path)
    return out


def main(argv: list[str] | None = None) -> int:
    import argparse

    parser = argparse.ArgumentParser(prog="python -m lab.core.executor.compare",
                                     description="two studies' JSON, identical apart from timings?")
    parser.add_argument("first")
    parser.add_argument("second")
    parser.add_argument("--ignore", action="append", default=[], metavar="KEY", help="leave this key out too")
    args = parser.parse_args(argv)
    try:
        a, b = (strip_timings(json.loads(open(p).read()), frozenset(args.ignore)) for p in (args.first, args.second))
    except (OSError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    diff = differences(a, b)
    if diff:
        print(f"{args.first} and {args.second} differ apart from timings:")
        for line in diff:
            print(f"  {line}")
        return 1
    print(f"{args.first} and {args.second}: identical apart from timings")
    return 0


if __name__ == "__main__":
    sys.exit(main())
