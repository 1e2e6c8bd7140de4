"""What a deadline on one awaited reply costs on this Python, with nothing of srvwire around it.

One task awaits, ``--calls`` times, a future that a loop callback resolves at the next turn,
as a reader resolves a call's reply. Each way of waiting is measured in a child process of its
own:

* **await**: the future itself, with no deadline;
* **wait_for**: ``asyncio.wait_for(future, 30)``, as srvwire's client waits (the design's
  deadline);
* **timeout**: ``async with asyncio.timeout(30): await future``;
* **timer**: a bare ``loop.call_later(30, ...)`` armed before and cancelled after;
* **wait_for-done**: ``asyncio.wait_for`` on a future resolved already (does it look first?).

The figure is instructions per await counted by valgrind (the difference between a run of
``--calls`` and one of three times as many), which other processes cannot disturb; without
valgrind on the path, or with ``--cpu``, µs of CPU per await (the minimum of ``--repeat``).

    python benchmarks/deadline_cost.py
"""

from __future__ import annotations

import argparse
import asyncio
import json
import re
import shutil
import subprocess
import sys
import time

WAYS = ["await", "wait_for", "timeout", "timer", "wait_for-done"]
DEADLINE = 30.0


def measure(way: str, calls: int) -> float:
    """µs of CPU per await, waiting ``way``."""

    async def run() -> float:
        loop = asyncio.get_running_loop()
        started = time.process_time()
        for _ in range(calls):
            future: asyncio.Future[int] = loop.create_future()
            if way == "wait_for-done":
                future.set_result(1)
            else:
                loop.call_soon(future.set_result, 1)
            if way == "await":
                await future
            elif way in ("wait_for", "wait_for-done"):
                await asyncio.wait_for(future, DEADLINE)
            elif way == "timeout":
                async with asyncio.timeout(DEADLINE):
                    await future
            else:
                timer = loop.call_later(DEADLINE, future.cancel)
                await future
                timer.cancel()
        return (time.process_time() - started) / calls * 1e6

    return asyncio.run(run())


def child(way: str, calls: int, prefix: list[str]) -> tuple[float, str]:
    """Run :func:`measure` in a child process (under ``prefix``); its figure and stderr."""
    done = subprocess.run(
        [*prefix, sys.executable, __file__, "--child", way, "--calls", str(calls)],
        check=True,
        capture_output=True,
        text=True,
    )
    return float(json.loads(done.stdout.splitlines()[-1])), done.stderr


def instructions(way: str, calls: int) -> float:
    counted = []
    for n in (calls, 3 * calls):
        _, err = child(way, n, VALGRIND)
        found = re.search(r"I\s+refs:\s+([0-9,]+)", err)
        if found is None:
            raise SystemExit(f"valgrind did not count the instructions:\n{err}")
        counted.append(int(found[1].replace(",", "")))
    return (counted[1] - counted[0]) / (2 * calls)


VALGRIND = ["valgrind", "--tool=cachegrind", "--cache-sim=no", "--cachegrind-out-file=/dev/null"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    parser.add_argument("--calls", type=int, default=2_000)
    parser.add_argument("--repeat", type=int, default=5, help="runs of each (with --cpu)")
    parser.add_argument("--cpu", action="store_true", help="µs of CPU instead of instructions")
    parser.add_argument("--ways", default=",".join(WAYS))
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(measure(args.child, args.calls)))
        return
    ways = args.ways.split(",")
    counting = not args.cpu and shutil.which("valgrind") is not None
    unit = "instructions per await, valgrind" if counting else "µs of CPU per await"
    print(f"Python {sys.version.split()[0]}, {unit}; extra = more than awaiting the future alone")
    figures = {}
    for way in ways:
        if counting:
            figures[way] = instructions(way, args.calls)
        else:
            figures[way] = min(child(way, args.calls, [])[0] for _ in range(args.repeat))
    base = figures.get("await")
    for way in ways:
        extra = "" if base is None else f"  extra {figures[way] - base:9.1f}"
        print(f"  {way:14} {figures[way]:9.1f}{extra}")


if __name__ == "__main__":
    main()
