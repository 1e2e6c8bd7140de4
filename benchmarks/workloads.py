"""The client side of every workload, written once over a small adapter per implementation.

``baseline_client.py`` and ``srvwire_client.py`` each describe how to open a connection, how to
build a request and how to read a reply (an :class:`Adapter`); everything else — warm-up, the
ready/go handshake with ``run.py``, timing, CPU accounting — is here, so both sides are measured
by exactly the same loop.

Workloads (counts come from ``run.py``):

* ``W1`` sequential: one connection, one call at a time; calls/s and per-call latency.
* ``W2`` pipelined: one connection, ``--inflight`` calls outstanding at all times; calls/s.
* ``W3`` fan-in: ``--connections`` connections, each calling sequentially for ``--duration`` s.
* ``W4`` large: one connection, one call at a time, each reply carrying 100 000 float64 values.
* ``IDLE``: open ``--connections`` connections and hold them, so ``run.py`` can read the
  server's memory; nothing is called.
"""

from __future__ import annotations

import argparse
import asyncio
import math
import sys
import time
from collections.abc import Awaitable, Callable
from contextlib import AsyncExitStack
from dataclasses import dataclass
from typing import Any

from common import (
    LARGE_REQUEST,
    LARGE_VALUES_COUNT,
    SMALL_REQUEST,
    add_process_options,
    cpu_seconds,
    emit,
    large_reply_bytes,
    run,
)

Call = Callable[[Any], Awaitable[Any]]
"""Call the benchmark's service with one request and return its reply."""

CONNECT_BATCH = 50  # connections opened concurrently at a time (below the listen backlog)


@dataclass(frozen=True)
class Adapter:
    """How one implementation opens a connection, builds a request and reads a reply."""

    open: Callable[[str, AsyncExitStack], Awaitable[Call]]
    """Connect to the url; register the connection's cleanup on the stack; return its call."""
    make_request: Callable[[dict[str, Any]], Any]
    """Build the request object a caller of this implementation would pass."""
    values_of: Callable[[Any], int]
    """Return how many ``values`` a reply holds (checked once, before measuring)."""


@dataclass
class Measure:
    """The measured part of a workload: wall time, this process's CPU time, calls, latencies."""

    calls: int = 0
    elapsed_s: float = 0.0
    cpu_s: float = 0.0
    latencies_ns: list[int] | None = None

    def result(self, **extra: Any) -> dict[str, Any]:
        fields: dict[str, Any] = {
            "calls": self.calls,
            "elapsed_s": self.elapsed_s,
            "client_cpu_s": self.cpu_s,
            **extra,
        }
        if self.latencies_ns:
            ordered = sorted(self.latencies_ns)
            fields["p50_us"] = percentile(ordered, 0.50) / 1000
            fields["p99_us"] = percentile(ordered, 0.99) / 1000
        return fields


def percentile(ordered: list[int], fraction: float) -> float:
    """Return the nearest-rank percentile of an already sorted list."""
    rank = max(1, math.ceil(fraction * len(ordered)))
    return float(ordered[rank - 1])


async def ready_then_wait_for_go() -> None:
    """Tell ``run.py`` the warm-up is over and wait until it says to start measuring."""
    emit("ready")
    line = await asyncio.to_thread(sys.stdin.readline)
    if line.strip() != "go":
        raise SystemExit(f"expected 'go' on stdin, got {line!r}")


async def check_reply(adapter: Adapter, call: Call, request: Any, expected: int) -> int:
    """Call once and return how many values the reply holds; exit unless ``expected``."""
    got = adapter.values_of(await call(request))
    if got != expected:
        raise SystemExit(f"the reply holds {got} values, expected {expected}")
    return got


async def sequential(adapter: Adapter, url: str, request: Any, warmup: int, calls: int) -> Measure:
    """One connection, one call at a time: the loop of W1 and W4."""
    async with AsyncExitStack() as stack:
        call = await adapter.open(url, stack)
        for _ in range(warmup):
            await call(request)
        await ready_then_wait_for_go()
        latencies = [0] * calls
        clock = time.perf_counter_ns
        cpu_start = cpu_seconds()
        start = clock()
        for index in range(calls):
            before = clock()
            await call(request)
            latencies[index] = clock() - before
        elapsed = clock() - start
        cpu = cpu_seconds() - cpu_start
    return Measure(calls, elapsed / 1e9, cpu, latencies)


async def pipelined(
    adapter: Adapter, url: str, request: Any, warmup: int, calls: int, inflight: int
) -> Measure:
    """One connection, ``inflight`` calls outstanding until ``calls`` are done: W2."""
    async with AsyncExitStack() as stack:
        call = await adapter.open(url, stack)
        remaining = 0

        async def worker() -> None:
            nonlocal remaining
            while remaining > 0:
                remaining -= 1
                await call(request)

        remaining = warmup
        await asyncio.gather(*(worker() for _ in range(inflight)))
        await ready_then_wait_for_go()
        remaining = calls
        cpu_start = cpu_seconds()
        start = time.perf_counter()
        await asyncio.gather(*(worker() for _ in range(inflight)))
        elapsed = time.perf_counter() - start
        cpu = cpu_seconds() - cpu_start
    return Measure(calls, elapsed, cpu)


async def open_many(adapter: Adapter, url: str, stack: AsyncExitStack, count: int) -> list[Call]:
    """Open ``count`` connections, :data:`CONNECT_BATCH` at a time."""
    calls: list[Call] = []
    while len(calls) < count:
        batch = min(CONNECT_BATCH, count - len(calls))
        calls += await asyncio.gather(*(adapter.open(url, stack) for _ in range(batch)))
    return calls


async def fan_in(
    adapter: Adapter, url: str, request: Any, warmup: int, connections: int, duration: float
) -> Measure:
    """``connections`` connections, each calling sequentially for ``duration`` seconds: W3."""
    async with AsyncExitStack() as stack:
        calls = await open_many(adapter, url, stack, connections)
        latencies: list[int] = []
        clock = time.perf_counter_ns

        async def warm(call: Call) -> None:
            for _ in range(warmup):
                await call(request)

        async def worker(call: Call, deadline: int) -> None:
            mine: list[int] = []
            while clock() < deadline:
                before = clock()
                await call(request)
                mine.append(clock() - before)
            latencies.extend(mine)

        await asyncio.gather(*(warm(call) for call in calls))
        await ready_then_wait_for_go()
        cpu_start = cpu_seconds()
        start = clock()
        deadline = start + int(duration * 1e9)
        await asyncio.gather(*(worker(call, deadline) for call in calls))
        elapsed = clock() - start
        cpu = cpu_seconds() - cpu_start
    return Measure(len(latencies), elapsed / 1e9, cpu, latencies)


async def idle(adapter: Adapter, url: str, connections: int) -> Measure:
    """Open ``connections`` connections and hold them until ``run.py`` has read the server."""
    async with AsyncExitStack() as stack:
        await open_many(adapter, url, stack, connections)
        await ready_then_wait_for_go()
    return Measure()


def main(adapter: Adapter, description: str) -> None:
    """Parse the command line, run one workload against ``--url`` and print its result."""
    parser = argparse.ArgumentParser(description=description)
    add_process_options(parser)
    parser.add_argument("--url", required=True)
    parser.add_argument("--workload", choices=["W1", "W2", "W3", "W4", "IDLE"], required=True)
    parser.add_argument("--warmup", type=int, default=1000)
    parser.add_argument("--calls", type=int, default=20_000)
    parser.add_argument("--inflight", type=int, default=64)
    parser.add_argument("--connections", type=int, default=100)
    parser.add_argument("--duration", type=float, default=5.0)
    args = parser.parse_args()

    async def workload() -> dict[str, Any]:
        small = adapter.make_request(SMALL_REQUEST)
        large = adapter.make_request(LARGE_REQUEST)
        url: str = args.url
        if args.workload in {"W1", "W2", "W3"}:
            async with AsyncExitStack() as stack:
                await check_reply(adapter, await adapter.open(url, stack), small, 5)
        match args.workload:
            case "W1":
                measure = await sequential(adapter, url, small, args.warmup, args.calls)
            case "W2":
                measure = await pipelined(
                    adapter, url, small, args.warmup, args.calls, args.inflight
                )
            case "W3":
                measure = await fan_in(
                    adapter, url, small, args.warmup, args.connections, args.duration
                )
            case "W4":
                async with AsyncExitStack() as stack:
                    call = await adapter.open(url, stack)
                    values = await check_reply(adapter, call, large, LARGE_VALUES_COUNT)
                measure = await sequential(adapter, url, large, args.warmup, args.calls)
                return measure.result(reply_bytes=large_reply_bytes(), reply_values=values)
            case _:
                measure = await idle(adapter, url, args.connections)
                return measure.result(connections=args.connections)
        return measure.result()

    emit("result", **run(workload, args))
