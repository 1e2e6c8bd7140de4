"""Measure srvwire against a baseline written directly on ``websockets``, in the same run.

Usage::

    python benchmarks/run.py [--quick] [--repeat 3] [--workloads W1,W2,W3,W4,MEM,CORPUS]
                             [--loop asyncio|uvloop|asyncio,uvloop] [--json out.json]
                             [--compare baseline,srvwire [--compare A,B ...]]

``--compare A,B`` picks two implementations of :data:`IMPLEMENTATIONS` to compare:
``baseline`` (raw ``websockets``, nothing typed), ``floor`` (the least a typed JSON-RPC
framework must do per call), ``srvwire``, and on the native transport ``picows`` (raw
``picows``, nothing typed: that transport's own floor) and ``srvwire-picows``; and ``peer``, a
JSON-RPC peer (an ``aiohttp-json-rpc`` server and a ``jsonrpc-websocket`` client);
``srvwire-heap`` and ``srvwire-picows-heap`` are srvwire with ``keep_freed_heap()`` called
first on both sides, as an application of large messages would; ``floor-picows`` is the
floor on the native transport (the floor's typed work on both ends, on raw ``picows``' shape,
each wait under ``asyncio.wait_for``) and ``floor-picows-bare`` the same with the futures
awaited bare, without a deadline; ``floor-picows-corked`` (and ``-corked-bare``) the same with
what one turn or one read makes written in one system call on both ends, as srvwire writes it;
``picows-corked`` is raw picows writing that way, nothing typed, and ``picows-corked-deadline``
the same with each wait under ``asyncio.wait_for``: the least any design that batches and keeps
the design's per-call deadline can cost on this transport. Given several times, every
implementation named is measured once per repeat, in the same alternation, and one table is
printed per pair.

Every measurement starts a fresh server process (on 127.0.0.1, port 0, its port read from its
stdout) and a fresh client process, pinned to different CPUs when there are two. The client
warms up, then ``run.py`` reads the server's CPU time, tells the client to go, reads the
client's result and the server's CPU time again, so each side's CPU per call covers exactly the
measured calls. The two implementations alternate (A first on even repeats, B first on odd ones)
so slow drift of the machine lands on both. The table shows medians over the repeats and the
ratio B / A, of the medians and of each repeat's pair of runs: with the default
``baseline,srvwire``, 0.85 for a rate metric (↑) means srvwire does 85 % of the baseline's work
per second, and above 1 for a cost metric (↓: latency, CPU, memory) means srvwire costs more.
CORPUS measures srvwire's loader alone, so it runs only when srvwire is one of the two.

``--profile DIR`` instead runs srvwire alone, once per workload, with cProfile in both processes,
and writes ``DIR/<loop>-<workload>-{server,client}.prof`` plus a text summary of each.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import importlib.metadata
import io
import json
import os
import platform
import pstats
import statistics
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

HERE = Path(__file__).resolve().parent
PYTHON = sys.executable

IMPLEMENTATIONS: dict[str, tuple[Path, Path, tuple[str, ...]]] = {
    "baseline": (HERE / "baseline_server.py", HERE / "baseline_client.py", ()),
    "floor": (HERE / "floor_server.py", HERE / "floor_client.py", ()),
    "srvwire": (HERE / "srvwire_server.py", HERE / "srvwire_client.py", ()),
    "picows": (HERE / "picows_server.py", HERE / "picows_client.py", ()),
    "srvwire-picows": (
        HERE / "srvwire_server.py",
        HERE / "srvwire_client.py",
        ("--transport", "picows"),
    ),
    "peer": (HERE / "peer_server.py", HERE / "peer_client.py", ()),
    "srvwire-heap": (HERE / "srvwire_server.py", HERE / "srvwire_client.py", ("--keep-heap",)),
    "srvwire-picows-heap": (
        HERE / "srvwire_server.py",
        HERE / "srvwire_client.py",
        ("--transport", "picows", "--keep-heap"),
    ),
    "floor-picows": (HERE / "floor_picows_server.py", HERE / "floor_picows_client.py", ()),
    "floor-picows-bare": (
        HERE / "floor_picows_server.py",
        HERE / "floor_picows_client.py",
        ("--no-deadline",),
    ),
    "floor-picows-corked": (
        HERE / "floor_picows_server.py",
        HERE / "floor_picows_client.py",
        ("--cork",),
    ),
    "floor-picows-corked-bare": (
        HERE / "floor_picows_server.py",
        HERE / "floor_picows_client.py",
        ("--cork", "--no-deadline"),
    ),
    "picows-corked": (HERE / "picows_server.py", HERE / "picows_client.py", ("--cork",)),
    "picows-corked-deadline": (
        HERE / "picows_server.py",
        HERE / "picows_client.py",
        ("--cork", "--deadline"),
    ),
}
"""Each implementation's server script, client script, and the options both take."""
NETWORK_WORKLOADS = ["W1", "W2", "W3", "W4", "MEM"]
ALL_WORKLOADS = [*NETWORK_WORKLOADS, "CORPUS"]

# Client options per workload for a full run; --quick divides them (see quick_options).
FULL: dict[str, dict[str, float]] = {
    "W1": {"warmup": 1000, "calls": 20_000},
    "W2": {"warmup": 1000, "calls": 100_000, "inflight": 64},
    "W3": {"warmup": 10, "connections": 100, "duration": 5.0},
    "W4": {"warmup": 3, "calls": 60},
    "MEM": {"connections": 1000},
}
QUICK_DIVISOR = 20

STARTUP_TIMEOUT = 60.0  # seconds for a server to listen
STEP_TIMEOUT = 600.0  # seconds for a client to warm up, or to finish its measured part
RETRIES = 2  # extra tries of a measurement during which other processes kept a CPU busy
QUIET_WINDOW = 0.5  # seconds over which the machine's load is sampled before a measurement
QUIET_PATIENCE = 60.0  # seconds to wait for the machine to go quiet before measuring anyway
MEMORY_SETTLE = 1.0  # seconds to let the server finish 1 000 handshakes before reading its memory


def quick_options(options: dict[str, float]) -> dict[str, float]:
    """Shrink a workload for a smoke run: counts and durations divided, connections kept small."""
    quick = dict(options)
    for name in ("warmup", "calls"):
        if name in quick:
            quick[name] = max(2, int(quick[name]) // QUICK_DIVISOR)
    if "duration" in quick:
        quick["duration"] = quick["duration"] / QUICK_DIVISOR
    if "connections" in quick:
        quick["connections"] = max(5, int(quick["connections"]) // QUICK_DIVISOR)
    return quick


# -- processes ---------------------------------------------------------------------------------


class BenchError(Exception):
    """Raised when a server or client process misbehaves; carries the end of its stderr."""


@dataclass
class Process:
    """A child speaking the line protocol of ``common.py``, with its stderr kept in a file."""

    name: str
    process: asyncio.subprocess.Process
    stderr: IO[bytes]

    @classmethod
    async def start(cls, name: str, *argv: str | Path) -> Process:
        stderr = tempfile.TemporaryFile()
        process = await asyncio.create_subprocess_exec(
            PYTHON,
            *map(str, argv),
            stdin=asyncio.subprocess.PIPE,
            stdout=asyncio.subprocess.PIPE,
            stderr=stderr,
        )
        return cls(name, process, stderr)

    async def send(self, line: str) -> None:
        assert self.process.stdin is not None
        self.process.stdin.write(line.encode() + b"\n")
        await self.process.stdin.drain()

    async def expect(self, event: str, limit: float) -> dict[str, Any]:
        """Return the next line's JSON object, which must be ``event``, within ``limit`` s."""
        assert self.process.stdout is not None
        try:
            line = await asyncio.wait_for(self.process.stdout.readline(), limit)
        except TimeoutError:
            raise self.failure(f"no {event!r} within {limit:g} s") from None
        if not line:
            await self.process.wait()
            raise self.failure(f"exited with {self.process.returncode} before {event!r}")
        message: dict[str, Any] = json.loads(line)
        if message.get("event") != event:
            raise self.failure(f"expected {event!r}, got {message}")
        return message

    async def finish(self, limit: float = 30.0) -> None:
        """Close stdin (a server's cue to stop), then wait ``limit`` s for the exit, or kill."""
        if self.process.stdin is not None and not self.process.stdin.is_closing():
            self.process.stdin.close()
        try:
            await asyncio.wait_for(self.process.wait(), limit)
        except TimeoutError:
            self.process.kill()
            await self.process.wait()
            raise self.failure(f"did not exit within {limit:g} s") from None
        finally:
            self.stderr.close()

    def failure(self, what: str) -> BenchError:
        self.stderr.seek(0)
        tail = self.stderr.read()[-4000:].decode(errors="replace")
        return BenchError(f"{self.name} {what}\n--- its stderr ---\n{tail}")


def process_options(loop: str, cpu: int | None, profile: Path | None) -> list[str]:
    argv = ["--loop", loop]
    if cpu is not None:
        argv += ["--cpu", str(cpu)]
    if profile is not None:
        argv += ["--profile", str(profile)]
    return argv


@dataclass
class Config:
    loop: str
    quick: bool
    pin: bool
    max_other_load: float
    profile_dir: Path | None = None

    def cpus(self) -> tuple[int | None, int | None]:
        """Return the CPUs for the server and the client, or no pinning."""
        available = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
        if self.pin and len(available) >= 2:
            return available[0], available[1]
        return None, None

    def options(self, workload: str) -> dict[str, float]:
        return quick_options(FULL[workload]) if self.quick else FULL[workload]

    def profile(self, workload: str, side: str) -> Path | None:
        if self.profile_dir is None:
            return None
        return self.profile_dir / f"{self.loop}-{workload}-{side}.prof"


async def measure(impl: str, workload: str, config: Config) -> dict[str, Any]:
    """Run one workload once against one implementation; return the client's result, enriched."""
    server_script, client_script, extra = IMPLEMENTATIONS[impl]
    server_cpu, client_cpu = config.cpus()
    options = config.options(workload)
    server = await Process.start(
        f"{impl} server",
        server_script,
        *process_options(config.loop, server_cpu, config.profile(workload, "server")),
        *extra,
    )
    try:
        port = (await server.expect("listening", STARTUP_TIMEOUT))["port"]
        await server.send("stats")
        at_start = await server.expect("stats", STARTUP_TIMEOUT)
        client_argv: list[str | Path] = [
            client_script,
            "--url",
            f"ws://127.0.0.1:{port}",
            "--workload",
            "IDLE" if workload == "MEM" else workload,
            *process_options(config.loop, client_cpu, config.profile(workload, "client")),
            *extra,
        ]
        for name, value in options.items():
            client_argv += [f"--{name}", str(value)]
        client = await Process.start(f"{impl} {workload} client", *client_argv)
        try:
            await client.expect("ready", STEP_TIMEOUT)
            if workload == "MEM":
                await asyncio.sleep(MEMORY_SETTLE)
            await server.send("stats")
            before = await server.expect("stats", STARTUP_TIMEOUT)
            busy_before = machine_busy_seconds()
            await client.send("go")
            result = await client.expect("result", STEP_TIMEOUT)
            busy = machine_busy_seconds() - busy_before
            await server.send("stats")
            after = await server.expect("stats", STARTUP_TIMEOUT)
        finally:
            await client.finish()
    finally:
        await server.finish()
    result["server_cpu_s"] = after["cpu_s"] - before["cpu_s"]
    if result.get("elapsed_s"):
        # CPU that neither side of the benchmark used while it ran: other work on the machine.
        others = busy - result["server_cpu_s"] - result["client_cpu_s"]
        result["other_load_cpus"] = max(0.0, others) / result["elapsed_s"]
    result["server_rss_start_kib"] = at_start["rss_kib"]
    result["server_rss_kib"] = before["rss_kib"]
    result["server_maxrss_kib"] = before["maxrss_kib"]
    return result


def machine_busy_seconds() -> float:
    """Return the CPU time the whole machine has been busy (or stolen by its host), from /proc/stat.

    Counted in clock ticks (usually 10 ms), so only runs of a second or more are judged by it.
    """
    try:
        with open("/proc/stat") as stat:
            ticks = [int(value) for value in stat.readline().split()[1:9]]
    except (OSError, ValueError):
        return 0.0
    user, nice, system, _idle, _iowait, irq, softirq, steal = ticks
    return (user + nice + system + irq + softirq + steal) / os.sysconf("SC_CLK_TCK")


async def wait_for_quiet(limit: float, where: str) -> None:
    """Wait until other processes use at most ``limit`` CPUs, for :data:`QUIET_PATIENCE` s at most.

    The benchmark's own processes have all exited when this runs, so whatever keeps the machine
    busy is someone else's (a test suite, a build): numbers measured beside it are not comparable.
    A limit above the number of CPUs cannot be exceeded, so it is not sampled (the test suite's
    smoke runs, ``--max-other-load 64``, would only wait a window per measurement).
    """
    if limit > (os.cpu_count() or 1):
        return
    started = time.perf_counter()
    while True:
        before = machine_busy_seconds()
        await asyncio.sleep(QUIET_WINDOW)
        load = (machine_busy_seconds() - before) / QUIET_WINDOW
        if load <= limit:
            return
        if time.perf_counter() - started > QUIET_PATIENCE:
            log(f"{where}: other processes kept {load:.2f} CPUs busy; measuring anyway")
            return


async def measure_quietly(impl: str, workload: str, config: Config, where: str) -> dict[str, Any]:
    """Measure when the machine is quiet; measure again (:data:`RETRIES` times) if it was not."""
    for attempt in range(RETRIES + 1):
        await wait_for_quiet(config.max_other_load, where)
        result = await measure(impl, workload, config)
        other = result.get("other_load_cpus", 0.0)
        if other <= config.max_other_load or result["elapsed_s"] < 1.0:
            break
        kept = "keeping it" if attempt == RETRIES else "measuring again"
        log(f"{where}: other processes used {other:.2f} CPUs meanwhile; {kept}")
    return result


async def measure_corpus() -> dict[str, Any]:
    """Time loading every interface type in a fresh process (srvwire only)."""
    corpus = await Process.start("corpus loader", HERE / "corpus.py")
    try:
        return await corpus.expect("result", STEP_TIMEOUT)
    finally:
        await corpus.finish()


# -- metrics -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Metric:
    workload: str
    name: str
    higher_is_better: bool

    @property
    def label(self) -> str:
        return f"{self.name} {'↑' if self.higher_is_better else '↓'}"


def metrics_of(workload: str, result: dict[str, Any]) -> dict[str, float]:
    """Turn one measured run into the numbers the table shows."""
    calls = result.get("calls", 0)
    if workload == "CORPUS":
        return {"load ms": result["load_s"] * 1e3, "import ms": result["import_s"] * 1e3}
    if workload == "MEM":
        connections = result["connections"]
        grown = result["server_rss_kib"] - result["server_rss_start_kib"]
        return {
            "server ru_maxrss MiB": result["server_maxrss_kib"] / 1024,
            "server KiB per idle connection": grown / connections,
        }
    rate = calls / result["elapsed_s"]
    client_cpu = result["client_cpu_s"] / calls
    server_cpu = result["server_cpu_s"] / calls
    if workload == "W4":
        return {
            "round trips/s": rate,
            "MB/s": rate * result["reply_bytes"] / 1e6,
            "p50 ms": result["p50_us"] / 1e3,
            "client CPU ms/call": client_cpu * 1e3,
            "server CPU ms/call": server_cpu * 1e3,
        }
    numbers = {"calls/s": rate}
    if "p50_us" in result:
        numbers["p50 µs"] = result["p50_us"]
        numbers["p99 µs"] = result["p99_us"]
    numbers["client CPU µs/call"] = client_cpu * 1e6
    numbers["server CPU µs/call"] = server_cpu * 1e6
    return numbers


HIGHER_IS_BETTER = {"calls/s", "round trips/s", "MB/s"}


@dataclass(frozen=True)
class Row:
    """One line of the table: medians, their ratio, and the lowest and highest per-run ratio."""

    metric: Metric
    base: float | None
    candidate: float | None
    ratio: float | None
    spread: tuple[float, float] | None


@dataclass
class Table:
    """Every run's numbers, by metric and implementation, in the order they were first seen."""

    impls: list[str]
    values: dict[Metric, dict[str, list[float]]] = field(default_factory=dict)

    def add(self, impl: str, workload: str, numbers: dict[str, float]) -> None:
        for name, value in numbers.items():
            metric = Metric(workload, name, name in HIGHER_IS_BETTER)
            self.values.setdefault(metric, {}).setdefault(impl, []).append(value)

    def rows(self) -> Iterator[Row]:
        base_name, candidate_name = self.impls
        for metric, by_impl in self.values.items():
            base_runs = by_impl.get(base_name, [])
            candidate_runs = by_impl.get(candidate_name, [])
            base = median_or_none(base_runs)
            candidate = median_or_none(candidate_runs)
            ratio = candidate / base if base and candidate is not None else None
            # Both sides ran in the same repeat, side by side: the spread of their ratio repeat by
            # repeat shows how far one run can be trusted.
            paired = [c / b for b, c in zip(base_runs, candidate_runs, strict=False) if b]
            spread = (min(paired), max(paired)) if len(paired) > 1 else None
            yield Row(metric, base, candidate, ratio, spread)

    def render(self, title: str) -> str:
        base_name, candidate_name = self.impls
        header = ("workload", "metric", f"{base_name} (median)", f"{candidate_name} (median)")
        lines = [
            title,
            f"ratio = {candidate_name} / {base_name}: of the medians, and lowest..highest per run",
            f"{header[0]:<8} {header[1]:<32} {header[2]:>18} {header[3]:>18} {'ratio':>7}"
            f" {'per-run ratios':>15}",
        ]
        for row in self.rows():
            ratio = "—" if row.ratio is None else f"{row.ratio:.2f}"
            spread = "" if row.spread is None else f"{row.spread[0]:.2f}..{row.spread[1]:.2f}"
            lines.append(
                f"{row.metric.workload:<8} {row.metric.label:<32} {fmt(row.base):>18}"
                f" {fmt(row.candidate):>18} {ratio:>7} {spread:>15}"
            )
        return "\n".join(lines)

    def summary(self) -> list[dict[str, Any]]:
        base_name, candidate_name = self.impls
        return [
            {
                "workload": row.metric.workload,
                "metric": row.metric.name,
                "higher_is_better": row.metric.higher_is_better,
                base_name: row.base,
                candidate_name: row.candidate,
                "ratio": row.ratio,
                "ratio_range": row.spread,
                "runs": self.values[row.metric],
            }
            for row in self.rows()
        ]


def median_or_none(values: list[float]) -> float | None:
    return statistics.median(values) if values else None


def fmt(value: float | None) -> str:
    if value is None:
        return "—"
    if abs(value) >= 1000:
        return f"{value:,.0f}"
    if abs(value) >= 10:
        return f"{value:.1f}"
    return f"{value:.3f}"


# -- the run -----------------------------------------------------------------------------------


def machine() -> dict[str, Any]:
    """Describe what the numbers were measured on."""
    model = "unknown"
    with contextlib.suppress(OSError), open("/proc/cpuinfo") as cpuinfo:
        for line in cpuinfo:
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    versions: dict[str, str | None] = {}
    for package in (
        *("srvwire", "websockets", "picows", "pydantic", "pydantic-core", "orjson", "uvloop"),
        *("aiohttp", "aiohttp-json-rpc", "jsonrpc-websocket"),
    ):
        try:
            versions[package] = importlib.metadata.version(package)
        except importlib.metadata.PackageNotFoundError:
            versions[package] = None
    return {
        "cpus": os.cpu_count(),
        "cpu_model": model,
        "python": platform.python_version(),
        "implementation": platform.python_implementation(),
        "platform": platform.platform(),
        "versions": versions,
    }


def log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def pair_labels(pair: list[str]) -> list[str]:
    """The two column names of a pair: comparing an implementation with itself (the harness's
    own check) needs two."""
    return pair if pair[0] != pair[1] else [pair[0], f"{pair[1]}#2"]


async def bench_loop(
    config: Config, workloads: list[str], repeat: int, pairs: list[list[str]]
) -> tuple[list[Table], list[dict[str, Any]]]:
    tables = [Table(pair_labels(pair)) for pair in pairs]
    measured: list[tuple[str, str]] = []  # (implementation, label), each once
    for pair in pairs:
        for impl, label in zip(pair, pair_labels(pair), strict=True):
            if (impl, label) not in measured:
                measured.append((impl, label))
    runs: list[dict[str, Any]] = []
    for index in range(repeat):
        # Rotate who goes first, and reverse on odd repeats, so drift lands on every one.
        shift = index % len(measured)
        order = measured[shift:] + measured[:shift]
        if index % 2:
            order.reverse()
        for workload in workloads:
            if workload == "CORPUS":
                if not any("srvwire" in table.impls for table in tables):
                    continue
                result = await measure_corpus()
                for table in tables:
                    if "srvwire" in table.impls:
                        table.add("srvwire", workload, metrics_of(workload, result))
                runs.append({"impl": "srvwire", "workload": workload, "repeat": index, **result})
                log(f"[{config.loop} {index + 1}/{repeat}] CORPUS srvwire: {result}")
                continue
            for impl, label in order:
                started = time.perf_counter()
                where = f"[{config.loop} {index + 1}/{repeat}] {workload} {label}"
                result = await measure_quietly(impl, workload, config, where)
                numbers = metrics_of(workload, result)
                for table in tables:
                    if label in table.impls:
                        table.add(label, workload, numbers)
                runs.append({"impl": label, "workload": workload, "repeat": index, **result})
                shown = ", ".join(f"{name} {fmt(value)}" for name, value in numbers.items())
                took = time.perf_counter() - started
                other = result.get("other_load_cpus", 0.0)
                log(f"{where}: {shown} (other load {other:.2f} CPUs; {took:.1f} s)")
    return tables, runs


async def profile_loop(config: Config, workloads: list[str], impl: str = "srvwire") -> None:
    assert config.profile_dir is not None
    config.profile_dir.mkdir(parents=True, exist_ok=True)
    for workload in workloads:
        if workload in {"CORPUS", "MEM"}:
            continue
        await measure(impl, workload, config)
        for side in ("server", "client"):
            path = config.profile(workload, side)
            assert path is not None
            summary = io.StringIO()
            stats = pstats.Stats(str(path), stream=summary)
            stats.sort_stats("tottime").print_stats(40)
            stats.sort_stats("cumulative").print_stats(60)
            path.with_suffix(".txt").write_text(summary.getvalue())
            log(f"profile: {path} and {path.with_suffix('.txt')}")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description="Measure two implementations side by side: by default, srvwire against a"
        " raw-websockets baseline."
    )
    parser.add_argument("--quick", action="store_true", help=f"1/{QUICK_DIVISOR} of every workload")
    parser.add_argument("--repeat", type=int, default=None, help="runs of each (3; quick: 1)")
    parser.add_argument("--workloads", default=",".join(ALL_WORKLOADS))
    parser.add_argument("--loop", default="asyncio", help="asyncio, uvloop or asyncio,uvloop")
    parser.add_argument("--json", type=Path, default=None, help="write every run and the medians")
    parser.add_argument("--no-pin", action="store_true", help="leave both processes unpinned")
    parser.add_argument(
        "--compare",
        action="append",
        default=None,
        help=f"two of {', '.join(IMPLEMENTATIONS)}; the ratios are the second / the first"
        " (baseline,baseline checks the harness itself); repeat it for more tables from the"
        " same runs (default: baseline,srvwire)",
    )
    parser.add_argument("--profile", type=Path, default=None, help="profile srvwire into DIR")
    parser.add_argument(
        "--max-other-load",
        type=float,
        default=0.25,
        help="measure again when other processes used more CPUs than this meanwhile (0.25)",
    )
    args = parser.parse_args(argv)
    args.workloads = [name.strip().upper() for name in args.workloads.split(",") if name.strip()]
    args.loops = [name.strip() for name in args.loop.split(",") if name.strip()]
    args.pairs = [
        [name.strip() for name in pair.split(",")] for pair in args.compare or ["baseline,srvwire"]
    ]
    for name in args.workloads:
        if name not in ALL_WORKLOADS:
            parser.error(f"unknown workload {name!r}; choose from {', '.join(ALL_WORKLOADS)}")
    for name in args.loops:
        if name not in {"asyncio", "uvloop"}:
            parser.error(f"unknown loop {name!r}; choose asyncio or uvloop")
    for pair in args.pairs:
        if len(pair) != 2 or not set(pair) <= set(IMPLEMENTATIONS):
            parser.error("--compare takes two of: " + ", ".join(IMPLEMENTATIONS))
    if args.repeat is None:
        args.repeat = 1 if args.quick else 3
    return args


async def amain(args: argparse.Namespace) -> int:
    info = machine()
    log(f"machine: {json.dumps(info)}")
    report: dict[str, Any] = {"machine": info, "quick": args.quick, "repeat": args.repeat}
    started = time.perf_counter()
    for loop in args.loops:
        config = Config(loop, args.quick, not args.no_pin, args.max_other_load, args.profile)
        if args.profile is not None:
            candidate = args.pairs[0][1]
            await profile_loop(
                config, args.workloads, candidate if candidate.startswith("srvwire") else "srvwire"
            )
            continue
        tables, runs = await bench_loop(config, args.workloads, args.repeat, args.pairs)
        scale = "quick, 1/20 size" if args.quick else "full size"
        for table in tables:
            title = f"\n== {loop} event loop: medians of {args.repeat} run(s), {scale} =="
            print(table.render(title), flush=True)
        # The first pair's table stays "summary"; every pair's is in "summaries".
        report[loop] = {
            "summary": tables[0].summary(),
            "summaries": {",".join(table.impls): table.summary() for table in tables},
            "runs": runs,
        }
    log(f"total time {time.perf_counter() - started:.0f} s")
    if args.json is not None:
        args.json.write_text(json.dumps(report, indent=2) + "\n")
    return 0


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        return asyncio.run(amain(args))
    except BenchError as exc:
        log(f"benchmark failed: {exc}")
        return 1


if __name__ == "__main__":
    sys.exit(main())
