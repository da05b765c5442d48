"""`zenpilot sweep`: grids of whole-stack lockstep flights, flown as tasks on Dask.

A grid is missions x scenarios x swept parameters x seeds. Each point is one
`zenpilot fly --lockstep --no-plots` in its own process (its services as threads on an
in-process bus, deploy/one_process.py) and its own folder, <out>/<flight id>/, so flights
never meet. The flights are
tasks of a dask.distributed cluster: a LocalCluster of --workers processes (one
flight each at a time) by default, or the cluster whose scheduler --scheduler names
(its workers need this package installed and --out on a filesystem they share).

A task whose flight leaves no metrics.json (the stack failed) raises and Dask runs
it once more; a second failure is a row with status "failed" and the error. A flight
that flew but crashed or did not complete is a result, not a failure. Re-running the
same sweep into the same --out skips every flight whose folder holds metrics.json from
the same command (resume). Results: <out>/sweep.csv and sweep.parquet (one row per
flight: the grid values, status, wall time, attempts, metrics.json flattened with dots)
and <out>/sweep-<dimension>.png, the chosen metric against each swept dimension.

This module's grid expansion is pure (tests/unit/deploy/test_sweep.py); Dask, pyarrow and
matplotlib are imported only by the functions that need them.
"""
from __future__ import annotations

import csv
import hashlib
import json
import math
import os
import re
import shutil
import signal
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from services.params import Param
from services.params.reference import DECLARED
from services.stack import StackError, check_param, load_stack, parse_overrides

ROOT = Path(__file__).resolve().parents[1]

# Named sets of overrides (the robustness cases of 001's flip, bench/flip_stack.py's scenarios)
SCENARIOS: dict[str, tuple[str, ...]] = {
    "nominal": (),
    "mass+10%": ("sim.mass_scale=1.1",),             # the plant's mass only: the services keep the file's
    "wind-2m/s": ("sim.wind_m_s=[0.0,2.0,0.0]",),    # across the roll (world y)
    "camera-drop-20%": ("sim.camera_drop_rate=0.2",),
}
ROW_FILE = "sweep-row.json"      # in a flight's folder: how the sweep flew it (resume compares it)
ATTEMPTS_FILE = "sweep-attempts"
MAX_SEEDS = 100_000
DEFAULT_METRICS = ("flip.altitude_loss_m", "position_rms_m", "duration_s")
BASE_COLUMNS = ("flight", "status", "mission", "scenario", "seed")
TAIL_COLUMNS = ("wall_s", "attempts", "resumed", "worker", "error")


# ---------------------------------------------------------------- the grid (pure)
def parse_seeds(text: str) -> list[int]:
    """'0-99', '1,3,5', '0-4,10' -> seeds, in the order given, each once."""
    seeds: list[int] = []
    for part in str(text).split(","):
        part = part.strip()
        m = re.fullmatch(r"(\d+)(?:\s*-\s*(\d+))?", part)
        if not m:
            raise StackError(f"--seeds {text!r}: {part!r} is not a seed or a range (e.g. 0-99 or 1,3,5)")
        lo = int(m.group(1))
        hi = int(m.group(2)) if m.group(2) is not None else lo
        if hi < lo:
            raise StackError(f"--seeds {text!r}: range {part!r} runs backwards")
        if hi - lo >= MAX_SEEDS:
            raise StackError(f"--seeds {text!r}: more than {MAX_SEEDS} seeds in {part!r}")
        for s in range(lo, hi + 1):
            if s in seeds:
                raise StackError(f"--seeds {text!r}: seed {s} given twice")
            seeds.append(s)
    return seeds


def split_values(text: str) -> list[str]:
    """'8,12,16' -> ['8', '12', '16']; commas inside brackets or quotes stay:
    '[8,8,6],[12,12,6]' -> ['[8,8,6]', '[12,12,6]']."""
    out, depth, quote, cur = [], 0, None, ""
    for ch in text:
        if quote:
            quote = None if ch == quote else quote
        elif ch in "\"'":
            quote = ch
        elif ch in "[{":
            depth += 1
        elif ch in "]}":
            depth -= 1
        elif ch == "," and depth == 0:
            out.append(cur.strip())
            cur = ""
            continue
        cur += ch
    out.append(cur.strip())
    return out


def param_declarations(service: str) -> dict[str, Param]:
    """A service's declared parameters (services/params/): what the grid's values are checked against."""
    return DECLARED.get(service, {})


def check_setting(item: str, stack, option: str = "--param",
                  declared_of: Callable[[str], dict] = param_declarations) -> tuple[str, str]:
    """'service.key=value' checked against the stack's services and the service's declared
    parameters (name, type, bounds, choices) with the check the service makes at start
    (services/stack.py check_param), so no flight is flown to be refused; returns ('service.key',
    value as it goes to `fly --set`). A number for a list of numbers is every element:
    attitude.k=8 is [8.0,8.0,8.0]."""
    name, sep, raw = item.partition("=")
    service, dot, key = name.strip().partition(".")
    if not sep or not dot or not key or not raw.strip():
        raise StackError(f"{option} {item!r}: expected SERVICE.KEY=VALUE, e.g. attitude.k=[12,12,12]")
    if service not in stack.services:
        raise StackError(f"{option} {item!r}: no service {service!r} in {stack.path} "
                         f"(services: {', '.join(stack.services)})")
    declared = declared_of(service)
    value = parse_overrides([f"{key}={raw.strip()}"])[key]
    d = declared.get(key)
    default = d.default if isinstance(d, Param) else d
    if (isinstance(default, (list, tuple)) and default and all(isinstance(x, float) for x in default)
            and isinstance(value, (int, float)) and not isinstance(value, bool)):
        value = [float(value)] * len(default)
        raw = "[" + ",".join(repr(v) for v in value) + "]"
    check_param(declared, key, value, f"{option} {item!r}: {service}")
    return f"{service}.{key}", raw.strip()


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9.+_-]+", "_", text.replace("%", "pct").replace("/", "_")).strip("_") or "x"


@dataclass(frozen=True)
class Flight:
    """One point of the grid."""
    mission: str                                  # a name or a file (absolute)
    scenario: str
    seed: int
    params: tuple[tuple[str, str, str], ...] = ()  # (service.key, the value as given, as it goes to --set)
    settings: tuple[str, ...] = ()                # SERVICE.KEY=VALUE of the scenario and the fixed --set
    stack: str | None = None

    @property
    def id(self) -> str:
        parts = [_slug(Path(self.mission).stem), _slug(self.scenario)]
        parts += [f"{_slug(name)}={_slug(given)}" for name, given, _ in self.params]
        return "-".join(parts) + f"-seed{self.seed}"

    def set_items(self) -> list[str]:
        return [*self.settings, *(f"{name}={value}" for name, _, value in self.params)]

    def fly_argv(self) -> list[str]:
        """`zenpilot fly`'s arguments, less --out (the task's own)."""
        argv = ["fly", "--mission", self.mission, "--seed", str(self.seed), "--lockstep", "--no-plots"]
        if self.stack:
            argv += ["--stack", self.stack]
        for item in self.set_items():
            argv += ["--set", item]
        return argv

    def values(self) -> dict[str, Any]:
        return {"mission": self.mission, "scenario": self.scenario, "seed": self.seed,
                **{name: given for name, given, _ in self.params}}


@dataclass
class Grid:
    flights: list[Flight]
    dimensions: list[str]            # what varies, in the table's order: parameters, then scenario, mission
    param_names: list[str] = field(default_factory=list)


def expand_grid(missions: list[str], seeds: str, params: list[str] | None = None,
                scenarios: list[str] | None = None, sets: list[str] | None = None, stack_path: str | None = None,
                declared_of: Callable[[str], dict] = param_declarations,
                check_mission: Callable[[str], Any] | None = None,
                scenario_table: dict[str, tuple[str, ...]] = SCENARIOS) -> Grid:
    """Every flight of the grid, seed-major (a sweep cut short has every other point at its
    first seeds). Refuses before any flight, with what is wrong, an unknown service, parameter
    or scenario, a value of the wrong type, out of its bounds or not among its choices, a bad
    seed range and a dimension given twice."""
    stack = load_stack(stack_path)
    seed_list = parse_seeds(seeds)
    missions = [m for text in (missions or ["hover"]) for m in split_values(text) if m]
    resolved = []
    for m in missions:
        if check_mission is not None:
            check_mission(m)
        resolved.append(str(Path(m).resolve()) if (m.endswith(".toml") or os.sep in m) and Path(m).exists() else m)
    if len(set(resolved)) != len(resolved):
        raise StackError(f"--mission: a mission given twice ({', '.join(missions)})")
    names = [s for text in (scenarios or ["nominal"]) for s in split_values(text) if s]
    for s in names:
        if s not in scenario_table:
            raise StackError(f"--scenario {s!r}: unknown (scenarios: {', '.join(scenario_table)})")
    if len(set(names)) != len(names):
        raise StackError(f"--scenario: a scenario given twice ({', '.join(names)})")
    scen_sets = {s: [check_setting(i, stack, f"--scenario {s}", declared_of) for i in scenario_table[s]] for s in names}
    fixed = [check_setting(i, stack, "--set", declared_of) for i in sets or []]
    axes: list[tuple[str, list[tuple[str, str]]]] = []
    for item in params or []:
        name, sep, raw = item.partition("=")
        if not sep:
            raise StackError(f"--param {item!r}: expected SERVICE.KEY=V1,V2,... e.g. attitude.k=8,12,16")
        values = split_values(raw)
        if not all(values):
            raise StackError(f"--param {item!r}: an empty value")
        checked = [check_setting(f"{name.strip()}={v}", stack, "--param", declared_of) for v in values]
        key = checked[0][0]
        if key in [a for a, _ in axes]:
            raise StackError(f"--param {key}: given twice (give every value in one --param {key}=V1,V2,...)")
        if len(set(values)) != len(values):
            raise StackError(f"--param {item!r}: a value given twice")
        if any(key == k for k, _ in fixed):
            raise StackError(f"--param {key}: also fixed by --set")
        axes.append((key, [(v, c[1]) for v, c in zip(values, checked)]))
    combos: list[tuple[tuple[str, str, str], ...]] = [()]
    for key, values in axes:
        combos = [(*c, (key, given, value)) for c in combos for given, value in values]
    flights = []
    for seed in seed_list:
        for mission in resolved:
            for scen in names:
                settings = tuple(f"{k}={v}" for k, v in [*scen_sets[scen], *fixed])
                for combo in combos:
                    flights.append(Flight(mission, scen, seed, combo, settings,
                                          str(Path(stack_path).resolve()) if stack_path else None))
    ids = [f.id for f in flights]
    if len(set(ids)) != len(ids):   # values that differ only in characters a folder name cannot hold
        flights = [_with_hash(f) for f in flights]
    dims = [k for k, v in axes if len(v) > 1] + (["scenario"] if len(names) > 1 else []) \
        + (["mission"] if len(resolved) > 1 else [])
    return Grid(flights, dims, [k for k, _ in axes])


class _HashedFlight(Flight):
    @property
    def id(self) -> str:
        digest = hashlib.sha1(json.dumps(self.fly_argv()).encode()).hexdigest()[:8]
        return f"{Flight.id.fget(self)}-{digest}"


def _with_hash(f: Flight) -> Flight:
    return _HashedFlight(f.mission, f.scenario, f.seed, f.params, f.settings, f.stack)


# ---------------------------------------------------------------- one flight (a task)
class FlightFailed(RuntimeError):
    """The flight left no metrics.json: the stack failed (Dask retries the task once)."""


def flatten(d: dict, prefix: str = "") -> dict[str, Any]:
    """metrics.json as columns: nested objects with dots, lists as JSON."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        name = f"{prefix}{k}"
        if isinstance(v, dict):
            if v:
                out.update(flatten(v, name + "."))
            else:
                out[name] = None
        elif isinstance(v, (list, tuple)):
            out[name] = json.dumps(v)
        else:
            out[name] = v
    return out


def flight_status(metrics: dict) -> str:
    if metrics.get("crashed"):
        return "crashed"
    return "ok" if metrics.get("completed") else "incomplete"


def done_row(folder: Path, argv: list[str]) -> dict | None:
    """The row of a flight already flown into `folder` with the same command, else None."""
    try:
        row = json.loads((folder / ROW_FILE).read_text())
        metrics = json.loads((folder / "metrics.json").read_text())
    except (OSError, ValueError):
        return None
    if row.get("argv") != argv:
        return None
    return {**row, "metrics": metrics}


def fly_task(task: dict) -> dict:
    """Fly one grid point: `python -m deploy.cli fly ... --out <out>/<id>` (lockstep: one process, no router).
    Returns {"id", "wall_s", "attempts", "metrics", "worker", "resumed"}; raises FlightFailed
    when the flight left no metrics.json (the folder keeps its logs)."""
    folder = Path(task["folder"])
    argv = list(task["argv"])
    done = done_row(folder, argv)
    if done is not None:   # flown by an earlier attempt or run
        return {**done, "resumed": True}
    attempts = 1
    try:
        attempts += int((folder / ATTEMPTS_FILE).read_text())
    except (OSError, ValueError):
        pass
    if folder.exists():   # what an earlier attempt left: its logs would mix with this one's
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    (folder / ATTEMPTS_FILE).write_text(str(attempts))
    cmd = [sys.executable, "-m", "deploy.cli", *argv, "--out", str(folder)]
    t0 = time.monotonic()
    with open(folder / "fly.log", "w") as log:
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT,
                                cwd=task["cwd"] if os.path.isdir(task.get("cwd") or "") else None)
        try:
            proc.wait(timeout=task.get("timeout_s"))
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGTERM)   # `fly` stops its services and the recorder closes the log
            try:
                proc.wait(timeout=90)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            raise FlightFailed(f"{task['id']}: no end within {task['timeout_s']:.0f} s (see {folder / 'fly.log'})")
    wall = time.monotonic() - t0
    try:
        metrics = json.loads((folder / "metrics.json").read_text())
    except (OSError, ValueError):
        raise FlightFailed(f"exit status {proc.returncode}: {_why(folder)}") from None
    row = {"id": task["id"], "argv": argv, "wall_s": round(wall, 2), "attempts": attempts,
           "worker": os.uname().nodename + f":{os.getpid()}", "exit_status": proc.returncode}
    (folder / ROW_FILE).write_text(json.dumps(row, indent=1) + "\n")
    return {**row, "metrics": metrics, "resumed": False}


def _last_error(path: Path) -> str | None:
    try:
        lines = [ln.strip() for ln in path.read_text(errors="replace").splitlines() if ln.strip()]
    except OSError:
        return None
    errors = [ln for ln in lines if "error" in ln.lower()]
    return (errors or lines or [None])[-1]


def _why(folder: Path) -> str:
    """fly's error line, and the error line of the service's log it points at (what was refused)."""
    said = _last_error(folder / "fly.log") or "no output"
    service_log = re.search(r"see (\S+/logs/\w+\.log)", said)
    cause = _last_error(Path(service_log.group(1))) if service_log else None
    return (said[:300] + (f" <- {cause[:300]}" if cause else "") + f" (see {folder / 'fly.log'})")


# ---------------------------------------------------------------- the table
def make_row(flight: Flight, result: dict | None, error: str | None, folder: Path) -> dict[str, Any]:
    row: dict[str, Any] = {"flight": flight.id}
    if result is None:
        row["status"] = "failed"
    else:
        row["status"] = flight_status(result["metrics"])
    row.update(flight.values())
    attempts = None
    if result is None:
        try:
            attempts = int((folder / ATTEMPTS_FILE).read_text())
        except (OSError, ValueError):
            pass
    row.update({"wall_s": (result or {}).get("wall_s"), "attempts": (result or {}).get("attempts", attempts),
                "resumed": (result or {}).get("resumed", False), "worker": (result or {}).get("worker"),
                "error": error})
    if result is not None:
        metrics = flatten(result["metrics"])
        for k in ("mission", "seed", "mode"):   # the grid's own columns say these
            metrics.pop(k, None)
        row.update({k: v for k, v in metrics.items() if k not in row})
    return row


def write_tables(rows: list[dict], out: Path, grid_columns: list[str]) -> tuple[Path, Path]:
    cols = list(BASE_COLUMNS) + [c for c in grid_columns if c not in BASE_COLUMNS] + list(TAIL_COLUMNS)
    for r in rows:
        cols += [k for k in r if k not in cols]
    csv_path, pq_path = out / "sweep.csv", out / "sweep.parquet"
    with open(csv_path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=cols, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in cols})
    import pyarrow as pa
    import pyarrow.parquet as pq

    arrays = []
    for c in cols:
        values = [r.get(c) for r in rows]
        try:
            arr = pa.array(values)
            if pa.types.is_null(arr.type):
                arr = pa.array(values, type=pa.string())
        except (pa.ArrowInvalid, pa.ArrowTypeError, TypeError, OverflowError):
            arr = pa.array([None if v is None else (v if isinstance(v, str) else json.dumps(v)) for v in values],
                           type=pa.string())
        arrays.append(arr)
    pq.write_table(pa.Table.from_arrays(arrays, names=cols), pq_path)
    return csv_path, pq_path


def choose_metric(rows: list[dict], wanted: str | None) -> str | None:
    numeric = {k for r in rows for k, v in r.items()
               if isinstance(v, (int, float)) and not isinstance(v, bool) and k not in ("seed", "wall_s", "attempts")}
    if wanted:
        if wanted not in numeric and any(r["status"] != "failed" for r in rows):
            raise StackError(f"--metric {wanted!r}: no numeric column of that name in the table "
                             f"(some: {', '.join(sorted(numeric)[:12])}, ...)")
        return wanted
    return next((m for m in DEFAULT_METRICS if m in numeric), None)


def _number(text: Any) -> float | None:
    try:
        v = float(text)
        return v if math.isfinite(v) else None
    except (TypeError, ValueError):
        return None


def make_plots(rows: list[dict], out: Path, dimensions: list[str], metric: str | None) -> list[Path]:
    """One PNG per swept dimension: the metric of every flight (dots) and its median over the
    other dimensions' flights (line), failed flights left out."""
    if not metric or not dimensions:
        return []
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    flown = [r for r in rows if r["status"] != "failed" and _number(r.get(metric)) is not None]
    paths = []
    for dim in dimensions:
        order: list[str] = []
        for r in rows:
            if str(r.get(dim)) not in order:
                order.append(str(r.get(dim)))
        numeric = all(_number(v) is not None for v in order)
        xs = {v: (_number(v) if numeric else i) for i, v in enumerate(order)}
        fig, ax = plt.subplots(figsize=(6, 4))
        by: dict[str, list[float]] = {v: [] for v in order}
        for r in flown:
            by[str(r.get(dim))].append(float(r[metric]))
        for v in order:
            ax.plot([xs[v]] * len(by[v]), by[v], "o", color="tab:blue", alpha=0.4, ms=4)
        med = [(xs[v], statistics.median(by[v])) for v in order if by[v]]
        if med:
            ax.plot([m[0] for m in med], [m[1] for m in med], "-", color="tab:red", label="median")
            ax.legend()
        if not numeric:
            ax.set_xticks(range(len(order)), order, rotation=20)
        ax.set_xlabel(dim)
        ax.set_ylabel(metric)
        failed = sum(1 for r in rows if r["status"] == "failed")
        ax.set_title(f"{metric} vs {dim} ({len(flown)} flights" + (f", {failed} failed" if failed else "") + ")")
        ax.grid(True, alpha=0.3)
        fig.tight_layout()
        path = out / f"sweep-{_slug(dim)}.png"
        fig.savefig(path, dpi=100)
        plt.close(fig)
        paths.append(path)
    return paths


# ---------------------------------------------------------------- the sweep
def open_client(workers: int, scheduler: str | None):
    """A Dask client: on the scheduler given, else on a LocalCluster of `workers` processes of
    one thread (a flight is a process tree of its own; one per worker at a time)."""
    from distributed import Client, LocalCluster

    if scheduler:
        return Client(scheduler), None
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None,
                           memory_limit=0)
    return Client(cluster), cluster


def run_sweep(grid: Grid, out: Path, workers: int = 2, scheduler: str | None = None, metric: str | None = None,
              timeout_s: float | None = None, rerun: bool = False, say: Callable[[str], None] = print) -> list[dict]:
    out = out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    tasks, rows_by_id = [], {}
    for f in grid.flights:
        folder = out / f.id
        if rerun and folder.exists():
            shutil.rmtree(folder)
        task = {"id": f.id, "folder": str(folder), "argv": f.fly_argv(), "timeout_s": timeout_s,
                "cwd": str(ROOT)}
        done = done_row(folder, task["argv"])
        if done is not None:
            rows_by_id[f.id] = make_row(f, {**done, "resumed": True}, None, folder)
        else:
            (folder / ATTEMPTS_FILE).unlink(missing_ok=True)   # attempts count within this run
            tasks.append(task)
    skipped = len(rows_by_id)
    say(f"zenpilot sweep: {len(grid.flights)} flights ({skipped} done already, {len(tasks)} to fly) -> {out}")
    by_id = {f.id: f for f in grid.flights}
    failed = 0
    t0 = time.monotonic()
    if tasks:
        from distributed import as_completed

        client, cluster = open_client(workers, scheduler)
        try:
            n_workers = len(client.nthreads())
            say(f"zenpilot sweep: Dask {'scheduler ' + scheduler if scheduler else 'LocalCluster'}, "
                f"{n_workers} worker(s)" + ("" if n_workers else "; the flights wait for a worker to join"))
            futures = client.map(fly_task, tasks, key=[f"fly-{t['id']}" for t in tasks], retries=1, pure=False)
            ids = {fut.key: t["id"] for fut, t in zip(futures, tasks)}
            for i, fut in enumerate(as_completed(futures), 1):
                fid = ids[fut.key]
                flight = by_id[fid]
                if fut.status == "error":
                    exc = fut.exception()
                    error = f"{type(exc).__name__}: {exc}" if not isinstance(exc, FlightFailed) else str(exc)
                    row = make_row(flight, None, error, out / fid)
                    failed += 1
                else:
                    row = make_row(flight, fut.result(), None, out / fid)
                rows_by_id[fid] = row
                elapsed = time.monotonic() - t0
                eta = elapsed / i * (len(tasks) - i)
                say(f"[{i}/{len(tasks)}] {fid}: {row['status']}"
                    + (f" in {row['wall_s']:.1f} s" if row.get("wall_s") else "")
                    + (f" ({row['error']})" if row.get("error") else "")
                    + f"; {elapsed:.0f} s elapsed, ~{eta:.0f} s to go")
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
    wall = time.monotonic() - t0
    rows = [rows_by_id[f.id] for f in grid.flights]
    grid_cols = grid.param_names
    csv_path, pq_path = write_tables(rows, out, grid_cols)
    chosen = choose_metric(rows, metric)
    plots = make_plots(rows, out, grid.dimensions, chosen)
    counts: dict[str, int] = {}
    for r in rows:
        counts[r["status"]] = counts.get(r["status"], 0) + 1
    say(f"zenpilot sweep: {len(tasks)} flown in {wall:.1f} s of wall time, {skipped} skipped (done already); "
        + ", ".join(f"{n} {s}" for s, n in sorted(counts.items())))
    say(f"zenpilot sweep: {csv_path}, {pq_path.name}" + (f", plots of {chosen}: " + ", ".join(p.name for p in plots)
                                                           if plots else ""))
    for r in rows:
        if r["status"] == "failed":
            say(f"zenpilot sweep: FAILED {r['flight']} after {r.get('attempts') or '?'} attempt(s): {r['error']}")
    return rows


def cmd_sweep(args) -> int:
    from services.stack import load_mission

    if args.workers < 1:
        raise StackError(f"--workers {args.workers}: at least 1")
    grid = expand_grid(args.mission or ["hover"], args.seeds, args.param, args.scenario, args.set, args.stack,
                       check_mission=load_mission)
    if args.dry_run:
        for f in grid.flights:
            print(f"{f.id}: zenpilot {' '.join(f.fly_argv())}")
        print(f"{len(grid.flights)} flights")
        return 0
    out = Path(args.out or "runs/sweep")
    rows = run_sweep(grid, out, args.workers, args.scheduler, args.metric, args.timeout, args.rerun)
    return 1 if any(r["status"] == "failed" for r in rows) else 0


SWEEP_HELP = """\
Fly a grid of whole-stack lockstep flights as tasks on Dask (dask.distributed): every
combination of --mission, --scenario and each --param's values, at every seed of --seeds.
Each flight is `zenpilot fly --lockstep --no-plots` with its own router (a free port), its own
services and its own folder OUT/<flight id>/; a flight that leaves no metrics.json is retried
once, then reported as failed. Re-running into the same --out skips the flights done already.
Results: OUT/sweep.csv and OUT/sweep.parquet (one row per flight: grid values, status, wall
time, attempts, every metric of metrics.json) and OUT/sweep-<dimension>.png per swept dimension.
Exit status 1 when a flight failed (the table has it, with the error), 2 for a bad grid.

Cluster: by default a LocalCluster of --workers processes, one flight each at a time (a
short lockstep flight keeps 1-1.4 cores busy; on 2 cores 2 workers flew 40 flights 1.45x
faster than 1: docs/sweep.md).
With --scheduler tcp://HOST:8786 the flights run on that cluster's workers (started with
`dask scheduler` and `dask worker tcp://HOST:8786 --nthreads 1`): each needs zenpilot
installed, and --out on a filesystem every worker shares.

examples:
  zenpilot sweep --param attitude.k=8,12,16 --seeds 0-99 --scenario wind-2m/s
  zenpilot sweep --mission flip --param planner.flip_method=ilqr-project,baseline --seeds 0-9 --workers 4
  zenpilot sweep --seeds 0-39 --scheduler tcp://10.0.0.5:8786 --out /shared/runs/sweep
"""


def add_parser(sub) -> None:
    import argparse

    sp = sub.add_parser("sweep", help="fly a grid (seeds x scenarios x parameters) as Dask tasks; one table",
                        description=SWEEP_HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    sp.add_argument("--mission", action="append", metavar="M[,M2,...]",
                    help="mission name(s) or file(s) (default: hover; repeatable)")
    sp.add_argument("--seeds", default="0", help="seeds: a range 0-99, a list 1,3,5, or both 0-4,10 (default 0)")
    sp.add_argument("--param", action="append", metavar="SERVICE.KEY=V1,V2,...",
                    help="a swept parameter and its values, checked against the service's declared parameters "
                         "(name, type, bounds, choices) before any flight "
                         "(a number for a list of numbers sets every element: attitude.k=8 is [8,8,8]; "
                         "list values in brackets: attitude.k=[8,8,6],[12,12,6]); repeatable, one per parameter")
    sp.add_argument("--scenario", action="append", metavar="NAME[,NAME2,...]",
                    help=f"scenario(s): {', '.join(SCENARIOS)} (default: nominal; repeatable)".replace("%", "%%"))
    sp.add_argument("--set", action="append", metavar="SERVICE.KEY=VALUE",
                    help="a parameter fixed for every flight (repeatable)")
    sp.add_argument("--stack", help="stack file (default: deploy/stacks/default.toml)")
    sp.add_argument("--workers", type=int, default=2,
                    help="LocalCluster worker processes, flights at a time (default 2; ignored with --scheduler)")
    sp.add_argument("--scheduler", metavar="tcp://HOST:PORT",
                    help="address of a running Dask scheduler: fly on its cluster instead of a LocalCluster")
    sp.add_argument("--out", help="sweep folder: a folder per flight, sweep.csv, sweep.parquet, plots "
                                  "(default runs/sweep)")
    sp.add_argument("--metric", help=f"the metrics.json figure plotted, dotted (default: the first of "
                                     f"{', '.join(DEFAULT_METRICS)} there)")
    sp.add_argument("--timeout", type=float, default=1800.0, help="a flight's wall-time limit in s (default 1800)")
    sp.add_argument("--rerun", action="store_true", help="fly every flight again, even those done already")
    sp.add_argument("--dry-run", action="store_true", help="list the flights and their commands; fly nothing")
    sp.set_defaults(func=cmd_sweep)
