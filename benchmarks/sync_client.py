"""What a blocking call costs against an ``await``: srvwire.sync against srvwire's async client.

One server process (the tutorial's ``RobotStateQuery`` shape, one async handler) and, in this
process, the measurements below, taken in turn in every round so that a change in the
machine's load falls on all of them alike; the table gives each one's median over the rounds.

* ``async``: sequential ``await client.call(...)`` on one connection;
* ``sync``: sequential ``client.call(...)`` from the main thread on one blocking client;
* ``async, 4 tasks``: four tasks calling at once on one connection;
* ``sync, 4 threads``: four threads calling at once on one blocking client;
* ``sync, a connection per call``: ``with srvwire.sync.connect(url)`` around every call, which
  is what a blocking client that opened a connection per call would cost.
* ``the hand-off alone``: what the blocking client adds to a call, without one: a coroutine
  that returns at once, run on a loop thread from this one and waited for.

Ratios are of time per call against the async client's, in the same run.

    python benchmarks/sync_client.py [--calls 3000] [--rounds 5] [--quick]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import srvwire

SERVICE = "/get_robot_state"
REQUEST = {"query_type": "position", "target_frame": ""}
THREADS = 4
WARMUP = 200


def serve() -> None:
    """The server process: print the URL once it listens, serve until stdin closes."""
    query = srvwire.load_service("advanced_communication_tutorials/srv/RobotStateQuery")

    async def get_robot_state(request: Any) -> Any:
        return query.Response(
            success=True,
            message="Current joint positions",
            values=[0.0, 0.5, 1.0, 1.5, 2.0],
            names=[f"joint_{i}" for i in range(5)],
        )

    server = srvwire.Server()
    server.add_service(SERVICE, query, get_robot_state)

    async def main() -> None:
        async with srvwire.serve(server, "127.0.0.1", 0) as running:
            print(running.url, flush=True)
            await asyncio.get_running_loop().run_in_executor(None, sys.stdin.read)

    asyncio.run(main())


# --- the measurements: each returns seconds per call -----------------------------------------


async def async_sequential(url: str, calls: int) -> float:
    async with srvwire.connect(url) as client:
        for _ in range(WARMUP):
            await client.call(SERVICE, REQUEST)
        start = time.perf_counter()
        for _ in range(calls):
            await client.call(SERVICE, REQUEST)
        return (time.perf_counter() - start) / calls


async def async_tasks(url: str, calls: int) -> float:
    async with srvwire.connect(url) as client:

        async def caller(count: int) -> None:
            for _ in range(count):
                await client.call(SERVICE, REQUEST)

        await caller(WARMUP)
        start = time.perf_counter()
        await asyncio.gather(*(caller(calls // THREADS) for _ in range(THREADS)))
        return (time.perf_counter() - start) / (calls // THREADS * THREADS)


def sync_sequential(url: str, calls: int) -> float:
    with srvwire.sync.connect(url) as client:
        for _ in range(WARMUP):
            client.call(SERVICE, REQUEST)
        start = time.perf_counter()
        for _ in range(calls):
            client.call(SERVICE, REQUEST)
        return (time.perf_counter() - start) / calls


def sync_threads(url: str, calls: int) -> float:
    with srvwire.sync.connect(url) as client, ThreadPoolExecutor(THREADS) as pool:

        def caller(count: int) -> None:
            for _ in range(count):
                client.call(SERVICE, REQUEST)

        caller(WARMUP)
        start = time.perf_counter()
        for future in [pool.submit(caller, calls // THREADS) for _ in range(THREADS)]:
            future.result()
        return (time.perf_counter() - start) / (calls // THREADS * THREADS)


def sync_connection_per_call(url: str, calls: int) -> float:
    calls = max(calls // 50, 5)  # each one opens a connection and a thread: far fewer
    start = time.perf_counter()
    for _ in range(calls):
        with srvwire.sync.connect(url) as client:
            client.call(SERVICE, REQUEST)
    return (time.perf_counter() - start) / calls


def handoff(url: str, calls: int) -> float:
    """A blocking client's hand-off alone: a coroutine that returns at once, on a loop thread."""

    async def nothing() -> None:
        pass

    thread = srvwire.sync.LoopThread("hand-off")
    try:
        for _ in range(WARMUP):
            thread.run(nothing(), 10.0)
        start = time.perf_counter()
        for _ in range(calls):
            thread.run(nothing(), 10.0)
        return (time.perf_counter() - start) / calls
    finally:
        thread.stop()


MEASUREMENTS: dict[str, Callable[[str, int], float]] = {
    "async": lambda url, calls: asyncio.run(async_sequential(url, calls)),
    "sync": sync_sequential,
    f"async, {THREADS} tasks": lambda url, calls: asyncio.run(async_tasks(url, calls)),
    f"sync, {THREADS} threads": sync_threads,
    "sync, a connection per call": sync_connection_per_call,
    "the hand-off alone, no call": handoff,
}


def measure(url: str, calls: int, rounds: int) -> dict[str, list[float]]:
    """Every measurement once per round, in turn: name -> seconds per call, one per round."""
    results: dict[str, list[float]] = {name: [] for name in MEASUREMENTS}
    for _ in range(rounds):
        for name, run in MEASUREMENTS.items():
            results[name].append(run(url, calls))
    return results


def report(results: dict[str, list[float]]) -> list[dict[str, Any]]:
    """The rows of the table: median time per call, calls per second, ratio to ``async``."""
    baseline = statistics.median(results["async"])
    rows = []
    for name, seconds in results.items():
        median = statistics.median(seconds)
        rows.append(
            {
                "measurement": name,
                "us_per_call": median * 1e6,
                "calls_per_second": 1 / median,
                "ratio_to_async": median / baseline,
                "rounds": len(seconds),
            }
        )
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--calls", type=int, default=3000, help="calls per measurement")
    parser.add_argument("--rounds", type=int, default=5, help="rounds; the median is reported")
    parser.add_argument("--quick", action="store_true", help="a smoke run: 300 calls, 1 round")
    parser.add_argument("--json", metavar="FILE", help="also write the rows as JSON to FILE")
    parser.add_argument("--serve", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.serve:
        serve()
        return 0
    calls, rounds = (300, 1) if args.quick else (args.calls, args.rounds)
    server = subprocess.Popen(
        [sys.executable, __file__, "--serve"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert server.stdout is not None
        url = server.stdout.readline().strip()
        rows = report(measure(url, calls, rounds))
    finally:
        assert server.stdin is not None
        server.stdin.close()  # the server's signal to stop
        server.wait()
    print(f"{calls} calls per measurement, median of {rounds} round(s), server at {url}")
    print(f"{'measurement':<30} {'µs per call':>12} {'calls/s':>10} {'/ async':>8}")
    for row in rows:
        print(
            f"{row['measurement']:<30} {row['us_per_call']:>12.1f} "
            f"{row['calls_per_second']:>10.0f} {row['ratio_to_async']:>8.2f}"
        )
    if args.json:
        with open(args.json, "w", encoding="utf-8") as file:
            json.dump(rows, file, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
