"""The runs catalogue: where runs go by default, and what each run under a root was, read from its
own files (`lab runs`, `lab runs show RUN`).

There is no database to fall out of step with the runs: a run directory is the record (its
`run.mcap` start/stop/step records first, `summary.json` for the counts), so a run copied from
another machine, or killed before it could write anything else, is listed like any other.

The default root, first found wins:
1. `$LAB_RUNS`;
2. `runs = "DIR"` in the user config file `$LAB_CONFIG`, else `$XDG_CONFIG_HOME/lab/config.toml`
   (`~/.config/lab/config.toml`); a relative DIR is relative to the config file;
3. `runs` in the current directory (as before the catalogue existed).
"""

from __future__ import annotations

import datetime as dt
import json
import math
import os
import stat
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from lab.core.errors import UserError
from lab.core.files import read_toml
from lab.core.verdicts import VERDICTS, tally

ENV_ROOT = "LAB_RUNS"
ENV_CONFIG = "LAB_CONFIG"
RUN_FILE = "run.mcap"
CONFIG_KEYS = {"runs"}


def config_path(env: dict[str, str] | None = None) -> Path:
    env = os.environ if env is None else env
    if env.get(ENV_CONFIG):
        return Path(env[ENV_CONFIG])
    base = Path(env["XDG_CONFIG_HOME"]) if env.get("XDG_CONFIG_HOME") else Path.home() / ".config"
    return base / "lab" / "config.toml"


def load_config(env: dict[str, str] | None = None) -> dict[str, Any]:
    """The user config file ({} if there is none); a bad one is refused in one line."""
    path = config_path(env)
    if not path.is_file():
        if (os.environ if env is None else env).get(ENV_CONFIG):
            raise UserError(f"{ENV_CONFIG}={path}: no such file")
        return {}
    data = read_toml(path, "user config")
    unknown = sorted(set(data) - CONFIG_KEYS)
    if unknown:
        raise UserError(f"{path}: unknown key {unknown[0]!r} (known: {', '.join(sorted(CONFIG_KEYS))})")
    if "runs" in data and (not isinstance(data["runs"], str) or not data["runs"].strip()):
        raise UserError(f"{path}: runs must be a directory path (a string), got {data['runs']!r}")
    return data


def runs_root(env: dict[str, str] | None = None) -> tuple[Path, str]:
    """(the default runs root, where that came from)."""
    env = os.environ if env is None else env
    if env.get(ENV_ROOT):
        return Path(env[ENV_ROOT]).expanduser(), f"${ENV_ROOT}"
    cfg = load_config(env)
    if "runs" in cfg:
        p = Path(cfg["runs"]).expanduser()
        path = config_path(env)
        return (p if p.is_absolute() else path.parent / p), str(path)
    return Path("runs"), "default"


@dataclass
class RunEntry:
    id: str                        # the run directory, relative to the root
    path: str
    procedure: str = ""
    rig: str = ""
    start: str = ""                # ISO 8601, UTC
    start_s: float = 0.0
    duration_s: float | None = None
    result: str = ""               # completed | aborted | failed | running | killed | unreadable
    reason: str = ""
    steps_completed: int = 0
    counts: dict[str, int] = field(default_factory=dict)   # verdicts (BORG) or nodes (truss)
    structure: str = ""
    argv: list[str] = field(default_factory=list)

    def counts_text(self) -> str:
        if not self.counts:
            return ""
        return ", ".join(f"{v} {k}" for k, v in self.counts.items())

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def read_run(run_dir: Path, root: Path | None = None) -> RunEntry:
    """What a run directory says about its run.  A killed run (no stop record) is `killed`."""
    from lab.core.recorder import topics
    from lab.core.recorder.reader import ScanState, iter_messages

    rid = str(run_dir.relative_to(root)) if root is not None and run_dir.is_relative_to(root) else str(run_dir)
    entry = RunEntry(rid, str(run_dir))
    start = stop = None
    last_ns = 0
    ended: set[int] = set()
    scan = ScanState()
    try:
        start, stop = _start_stop_indexed(run_dir / RUN_FILE)
    except Exception:   # no footer (killed) or no index: scan the file front to back below
        start = stop = None
    try:
        records = iter_messages(run_dir / RUN_FILE, (topics.RUN_START, topics.RUN_STOP, topics.RUN_STEP), scan,
                                max_bytes=SCAN_BUDGET_BYTES)
        for r in (records if stop is None else ()):
            last_ns = max(last_ns, r.log_time_ns)
            if r.topic == topics.RUN_START:
                start = r.message
            elif r.topic == topics.RUN_STOP:
                stop = r.message
            elif r.message.phase == "end":
                ended.add(r.message.index)
    except Exception as exc:   # a file that is not MCAP at all: listed, not fatal to the listing
        entry.result, entry.reason = "unreadable", f"{type(exc).__name__}: {exc}"
        return entry
    if start is not None:
        entry.procedure = start.procedure
        entry.structure = start.structure
        entry.argv = list(start.argv)
        entry.start_s = start.start_time.seconds + start.start_time.nanos * 1e-9
        entry.start = dt.datetime.fromtimestamp(entry.start_s, tz=dt.timezone.utc).isoformat(timespec="seconds")
        try:
            rig = json.loads(start.rig_json or "{}")
        except json.JSONDecodeError:
            rig = {}
        table = rig.get("rig") if isinstance(rig, dict) else None
        entry.rig = str(table.get("name", "")) if isinstance(table, dict) else ""
    entry.steps_completed = len(ended)
    if stop is not None:
        entry.result, entry.reason = stop.result, stop.reason
        entry.duration_s = float(stop.duration_s)
        entry.steps_completed = max(entry.steps_completed, int(stop.steps_completed))
    else:
        from lab.core.locks import read_holder

        # a run still going holds its directory's lock (a .lock that is no file holds nothing)
        holder = read_holder(run_dir / ".lock") if _regular(run_dir / ".lock") else None
        if holder:
            entry.result = "running"
            entry.reason = f"pid {holder.get('pid', '?')} holds the run directory"
            if start is not None:
                import time

                entry.duration_s = max(0.0, time.time() - entry.start_s)   # so far
        else:
            entry.result = "killed"
            entry.reason = f"no stop record ({scan.stop_reason or 'cut short'}); `lab recover` or `lab resume` it"
            if start is not None and last_ns:
                entry.duration_s = max(0.0, last_ns * 1e-9 - entry.start_s)
        if scan.budget_reached:
            # the steps past the budget: the checkpoint counts them (written after every step)
            ckpt = _json_file(run_dir / "checkpoint.json")
            done = ckpt.get("steps_completed") if isinstance(ckpt, dict) else None
            if isinstance(done, int) and not isinstance(done, bool) and done >= 0:
                entry.steps_completed = max(entry.steps_completed, done)
    summary = _json_file(run_dir / "summary.json")
    if summary_problem(summary) is not None:
        summary = None        # a damaged summary counts nothing (`lab runs show` says what is wrong)
    entry.counts = _counts(summary)
    if isinstance(summary, dict) and entry.procedure == "" and isinstance(summary.get("structure"), str):
        entry.structure = summary["structure"]
    return entry


# A killed run's file is scanned front to back for its steps; past this much (a long run's images)
# the checkpoint says how many steps were done, so listing many runs stays quick whatever their size
SCAN_BUDGET_BYTES = 64 * 2 ** 20


def _start_stop_indexed(path: Path) -> tuple[Any, Any]:
    """Start and stop records of a complete file through its chunk index: only the chunks that hold
    them are read (a full scan of a 30 MB run takes ~0.4 s, this ~10 ms)."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    from lab.core.recorder import topics

    start = stop = None
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, _, decoded in reader.iter_decoded_messages(topics=[topics.RUN_START, topics.RUN_STOP]):
            if channel.topic == topics.RUN_START:
                start = decoded
            else:
                stop = decoded
    if start is None or stop is None:
        raise ValueError("no start or stop record in the index")
    return start, stop


# the numbers a summary's tables print: each a finite number or null
_MODULE_NUMBERS = ("deviation_m", "deviation_rad", "sigma_position_m", "position_error_m", "rotation_error_rad",
                   "tolerance_m", "tolerance_rad")
_NODE_NUMBERS = ("error_m", "estimate_error_m")


@dataclass(frozen=True)
class SummaryFile:
    """A run's summary.json as read: its content, or what is wrong with it (`problem`: "missing",
    else the key and value that make it unusable)."""

    summary: dict[str, Any] | None
    problem: str = ""


def read_summary_file(run_dir: Path) -> SummaryFile:
    """summary.json, checked like any input: the tables `lab runs show` prints from it need each
    row's name and verdict (or node id) and numbers where numbers go."""
    path = run_dir / "summary.json"
    if path.exists() and not _regular(path):
        return SummaryFile(None, "not a regular file")
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        return SummaryFile(None, "missing")
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        return SummaryFile(None, f"not a readable JSON file ({type(exc).__name__}: {exc})")
    problem = summary_problem(data)
    return SummaryFile(data if problem is None else None, problem or "")


def summary_problem(data: Any) -> str | None:
    """What makes a summary unusable for its tables, naming the key; None if nothing."""
    def number(v: Any) -> bool:
        return v is None or (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v))

    if not isinstance(data, dict):
        return f"expected a JSON object, got {type(data).__name__}"
    mods = data.get("modules")
    if mods is not None:
        if not isinstance(mods, list):
            return f"modules: expected a list, got {type(mods).__name__}"
        for k, m in enumerate(mods):
            if not isinstance(m, dict):
                return f"modules[{k}]: expected an object, got {m!r:.40}"
            if "name" not in m:
                return f"modules[{k}].name: missing"
            if not isinstance(m["name"], str) or not m["name"]:
                return f"modules[{k}].name: expected a module name, got {m['name']!r:.40}"
            if m.get("verdict") not in VERDICTS:
                return f"modules[{k}].verdict: expected one of {', '.join(VERDICTS)}, got {m.get('verdict')!r:.40}"
            for key in _MODULE_NUMBERS:
                if not number(m.get(key)):
                    return f"modules[{k}].{key}: expected a finite number or null, got {m[key]!r:.40}"
            if not isinstance(m.get("reason", ""), str):
                return f"modules[{k}].reason: expected text, got {m['reason']!r:.40}"
    tags = data.get("rejected_tags")
    if tags is not None and not (isinstance(tags, list) and all(isinstance(t, int) and not isinstance(t, bool)
                                                                for t in tags)):
        return f"rejected_tags: expected a list of tag ids, got {tags!r:.40}"
    nodes = data.get("nodes")
    if nodes is not None:
        if not isinstance(nodes, list):
            return f"nodes: expected a list, got {type(nodes).__name__}"
        for k, n in enumerate(nodes):
            if not isinstance(n, dict) or "id" not in n:
                return f"nodes[{k}].id: missing"
            for key in _NODE_NUMBERS:
                if not number(n.get(key)):
                    return f"nodes[{k}].{key}: expected a finite number or null, got {n[key]!r:.40}"
        if not number(data.get("rms_node_error_m")):
            return f"rms_node_error_m: expected a finite number or null, got {data['rms_node_error_m']!r:.40}"
    return None


def _json_file(path: Path) -> Any:
    if not _regular(path):
        return None
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _counts(summary: Any) -> dict[str, int]:
    if not isinstance(summary, dict):
        return {}
    mods = summary.get("modules")
    if isinstance(mods, list):
        out: dict[str, int] = tally(m.get("verdict") for m in mods if isinstance(m, dict))
        if summary.get("rejected_tags"):
            out["rejected tags"] = len(summary["rejected_tags"])
        return out
    nodes = summary.get("nodes")
    if isinstance(nodes, list):
        return {"nodes": len(nodes)}
    return {}


def _regular(path: Path) -> bool:
    """A regular file (through symlinks): never opened to find out, so a FIFO cannot block us."""
    try:
        return stat.S_ISREG(os.stat(path).st_mode)
    except OSError:
        return False


def find_runs(root: Path, max_depth: int = 3) -> list[Path]:
    """Run directories (holding a run.mcap that is a regular file: a FIFO or a device of that name
    is no run, and opening one would hang) under `root`, at most `max_depth` levels down."""
    if not root.is_dir():
        raise UserError(f"runs root {root}: no such directory")
    out = []
    for dirpath, dirnames, filenames in os.walk(root):
        depth = len(Path(dirpath).relative_to(root).parts)
        if RUN_FILE in filenames and _regular(Path(dirpath) / RUN_FILE):
            out.append(Path(dirpath))
            dirnames[:] = []          # a run directory holds no other runs
        elif depth >= max_depth:
            dirnames[:] = []
        dirnames.sort()
    return out


def list_runs(root: Path) -> list[RunEntry]:
    entries = [read_run(d, root) for d in find_runs(root)]
    return sorted(entries, key=lambda e: (e.start_s, e.id))


def resolve_run(spec: str, root: Path) -> Path:
    """RUN as the user gives it: an id under the root, a run directory, or its run.mcap."""
    for cand in (root / spec, Path(spec)):
        if cand.is_file() and cand.name.endswith(".mcap"):
            return cand.parent
        if (cand / RUN_FILE).is_file():
            return cand
    raise UserError(f"{spec}: no run with that id under {root}, and no run directory at that path")


def format_duration(seconds: float | None) -> str:
    if seconds is None:
        return "?"
    s = int(round(seconds))
    return f"{s // 3600}h{s % 3600 // 60:02d}m" if s >= 3600 else f"{s // 60}m{s % 60:02d}s"


def format_list(entries: list[RunEntry]) -> str:
    rows = [("id", "procedure", "rig", "start (UTC)", "duration", "result", "steps", "counts")]
    for e in entries:
        rows.append((e.id, e.procedure or "?", e.rig or "?", e.start[:19].replace("T", " ") or "?",
                     format_duration(e.duration_s), e.result, str(e.steps_completed), e.counts_text()))
    widths = [max(len(r[k]) for r in rows) for k in range(len(rows[0]) - 1)]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(r[:-1], widths)) + "  " + r[-1] for r in rows).rstrip()


@dataclass(frozen=True)
class MetricStats:
    """One metric of a run (`/metrics`, e.g. `slam/update_s`, the BORG step's estimator time)."""

    name: str
    unit: str
    count: int
    median: float
    p90: float
    max: float
    total: float = 0.0


def run_metrics(path: Path) -> dict[str, tuple[str, list[float]]]:
    """Every metric a run logged: name -> (unit, values in log order).  Reads only the metrics
    topic (a few hundred records of a file that is mostly images)."""
    from lab.core.recorder import topics
    from lab.core.recorder.reader import iter_messages

    out: dict[str, tuple[str, list[float]]] = {}
    for msg in iter_messages(path, topics.METRICS):
        out.setdefault(msg.message.name, (msg.message.unit, []))[1].append(float(msg.message.value))
    return out


def metric_stats(metrics: dict[str, tuple[str, list[float]]]) -> list[MetricStats]:
    import numpy as np

    return [MetricStats(name, unit, len(v), float(np.median(v)), float(np.percentile(v, 90)), float(max(v)),
                        float(np.sum(v)))
            for name, (unit, v) in sorted(metrics.items()) if v]


def format_metrics(stats: list[MetricStats]) -> str:
    """A line per metric; seconds shown in ms, their total in s (where a run's time went)."""
    def show(x: float, unit: str) -> str:
        return f"{x * 1000:.1f} ms" if unit == "s" else f"{x:.4g} {unit}".rstrip()

    def total(m: MetricStats) -> str:
        return f"{m.total:.1f} s" if m.unit == "s" else ""

    rows = [("metric", "count", "median", "90th pct", "max", "total")]
    rows += [(m.name, str(m.count), show(m.median, m.unit), show(m.p90, m.unit), show(m.max, m.unit), total(m))
             for m in stats]
    widths = [max(len(r[k]) for r in rows) for k in range(len(rows[0]))]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows)


__all__ = ["runs_root", "load_config", "config_path", "RunEntry", "read_run", "find_runs", "list_runs",
           "SummaryFile", "read_summary_file", "summary_problem",
           "resolve_run", "format_list", "format_duration", "MetricStats", "run_metrics", "metric_stats",
           "format_metrics", "ENV_ROOT", "ENV_CONFIG"]
