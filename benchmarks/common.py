"""What the benchmark's servers and clients share: the payloads, the event loop, the stdio protocol.

Every process the harness starts speaks one JSON object per line on stdout, and takes one-word
commands on stdin, so ``run.py`` can drive it without sockets of its own:

* a server prints ``{"event": "listening", "port": N}`` once it accepts connections, answers each
  ``stats`` line with ``{"event": "stats", ...}`` (its CPU time and memory so far), and exits when
  its stdin closes;
* a client connects, warms up, prints ``{"event": "ready"}``, waits for a ``go`` line, runs the
  measured part of its workload, prints ``{"event": "result", ...}`` and exits.

Both sides answer the same service with the same data: a small ``RobotStateQuery``-shaped reply
(five float64 readings and their five names), or, for the query type ``large``, a reply of
:data:`LARGE_VALUES` readings. The float lists are built once at start-up, so building a reply
costs the handler almost nothing and the measurements are of the stack, not of the handler.
"""

from __future__ import annotations

import argparse
import asyncio
import cProfile
import json
import os
import resource
import sys
import threading
from collections import Counter
from collections.abc import Awaitable, Callable, Coroutine
from pathlib import Path
from types import FrameType
from typing import Any, TypeVar

from websockets.asyncio.server import serve

T = TypeVar("T")

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent

SERVICE = "/get_robot_state"
SRV_TYPE = "advanced_communication_tutorials/srv/RobotStateQuery"
SMALL_REQUEST: dict[str, Any] = {"query_type": "position", "target_frame": ""}
LARGE_REQUEST: dict[str, Any] = {"query_type": "large", "target_frame": ""}
CALL_TIMEOUT = 30.0  # seconds; the deadline every call carries (never reached in a healthy run)
MAX_MESSAGE = 16 * 2**20  # bytes; W4's reply is about 1.7 MB and websockets' default cap is 1 MiB

SMALL_NAMES = ["x", "y", "z", "yaw", "battery"]
SMALL_VALUES = [1.0 / 3.0, -2.718281828459045, 0.001, 3.141592653589793, 98.5]
LARGE_VALUES_COUNT = 100_000
# Full-precision floats, so each one takes as many characters on the wire as real readings do.
LARGE_VALUES = [i / 7.0 + 0.1 for i in range(LARGE_VALUES_COUNT)]


def reply_fields(query_type: str) -> dict[str, Any]:
    """Return the reply's fields for ``query_type``, the same on every side of the benchmark."""
    if query_type == "large":
        return {"success": True, "message": "large", "values": LARGE_VALUES, "names": []}
    return {"success": True, "message": "position", "values": SMALL_VALUES, "names": SMALL_NAMES}


def large_reply_bytes() -> int:
    """Return the size of the large reply's ``result`` as compact JSON: W4's bytes per call."""
    return len(json.dumps(reply_fields("large"), separators=(",", ":")))


# -- process plumbing --------------------------------------------------------------------------

_stdout_lock = threading.Lock()


def python_steps(run: Callable[[int], int], calls: int) -> dict[str, float]:
    """The Python bytecode instructions each function runs per call, by ``module:function``,
    the most first (at least half a one): ``run(n)`` makes about ``n`` calls and returns how
    many it made; the steps of ``calls`` calls less those of a tenth as many (what a run costs
    besides its calls cancels out), divided by the difference. Counted with ``sys.settrace``'s
    opcode events: exact, and the machine's load does not move it."""

    def count(calls: int) -> tuple[Counter[str], int]:
        counted: Counter[str] = Counter()

        def trace(frame: FrameType, event: str, arg: Any) -> Any:
            frame.f_trace_opcodes = True
            frame.f_trace_lines = False
            if event == "opcode":
                code = frame.f_code
                counted[f"{code.co_filename.rsplit('/', 1)[-1]}:{code.co_name}"] += 1
            return trace

        # Python 3.12 turns opcode events on only for a frame that asks before tracing starts;
        # one set from the trace function alone gives none (3.11 takes either).
        sys._getframe().f_trace_opcodes = True
        sys.settrace(trace)
        try:
            made = run(calls)
        finally:
            sys.settrace(None)
        return counted, made

    (many, made), (few, fewer) = count(calls), count(max(1, calls // 10))
    per_call = {name: (many[name] - few[name]) / (made - fewer) for name in many}
    return {name: n for name, n in sorted(per_call.items(), key=lambda i: -i[1]) if n >= 0.5}


def print_steps(title: str, steps: dict[str, float]) -> None:
    """Print what :func:`python_steps` counted: the total per call, then each function's."""
    print(f"{title}: {sum(steps.values()):.0f} bytecode instructions per call")
    for name, n in steps.items():
        print(f"{n:8.1f}  {name}")


def emit(event: str, **fields: Any) -> None:
    """Print one JSON line to stdout for ``run.py`` and flush it at once."""
    line = json.dumps({"event": event, **fields})
    with _stdout_lock:
        sys.stdout.write(line + "\n")
        sys.stdout.flush()


def cpu_seconds() -> float:
    """Return this process's user + system CPU time, in seconds, over all its threads.

    ``getrusage`` rather than ``os.times``: it counts in microseconds, not 10 ms clock ticks.
    """
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def memory_kib() -> tuple[int, int]:
    """Return this process's peak resident memory (``ru_maxrss``) and current one, in KiB."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    with open("/proc/self/statm") as statm:
        resident_pages = int(statm.read().split()[1])
    return peak, resident_pages * os.sysconf("SC_PAGE_SIZE") // 1024


def raise_file_limit() -> None:
    """Lift the soft open-file limit to the hard one: the idle workload holds 1 000 sockets."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard == resource.RLIM_INFINITY or soft < hard:
        resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))


def pin_to_cpu(cpu: int | None) -> None:
    """Run this process on one CPU only, when asked (``run.py`` gives each side its own)."""
    if cpu is not None and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {cpu})


def add_process_options(parser: argparse.ArgumentParser) -> None:
    """Add the options every server and client script takes."""
    parser.add_argument("--loop", choices=["asyncio", "uvloop"], default="asyncio")
    parser.add_argument("--cpu", type=int, default=None, help="pin this process to one CPU")
    parser.add_argument("--profile", type=Path, default=None, help="write cProfile stats here")
    parser.add_argument(
        "--transport",
        choices=["websockets", "picows"],
        default="websockets",
        help="srvwire's transport (the srvwire scripts only)",
    )
    parser.add_argument(
        "--keep-heap",
        action="store_true",
        help="call srvwire.keep_freed_heap() first, as a user would (the srvwire scripts only)",
    )
    parser.add_argument(
        "--no-deadline",
        action="store_true",
        help="await each reply bare, without asyncio.wait_for (floor_picows_client.py only)",
    )
    parser.add_argument(
        "--cork",
        action="store_true",
        help="write what one turn makes in one system call (the picows scripts only)",
    )
    parser.add_argument(
        "--deadline",
        action="store_true",
        help="await each reply under asyncio.wait_for (picows_client.py only)",
    )


def run(main: Callable[[], Coroutine[Any, Any, T]], args: argparse.Namespace) -> T:
    """Run ``main()`` on the event loop ``args.loop`` names, under cProfile if ``args.profile``."""
    pin_to_cpu(args.cpu)
    raise_file_limit()
    profile_path: Path | None = args.profile
    if profile_path is None:
        return _run_loop(main(), args.loop)
    profiler = cProfile.Profile()
    profiler.enable()
    try:
        return _run_loop(main(), args.loop)
    finally:
        profiler.disable()
        profiler.dump_stats(profile_path)


def _run_loop(coroutine: Coroutine[Any, Any, T], loop: str) -> T:
    if loop == "uvloop":
        import uvloop

        return uvloop.run(coroutine)
    return asyncio.run(coroutine)


# -- the server side ---------------------------------------------------------------------------


class ServerControl:
    """Answer ``run.py``'s commands on stdin from a thread, and say when the server should stop.

    The thread blocks in ``readline`` and does nothing while a workload runs, so it costs the
    measured server nothing. ``os.times`` and ``getrusage`` cover every thread of the process.
    """

    def __init__(self) -> None:
        self._loop = asyncio.get_running_loop()
        self.stopped = asyncio.Event()
        threading.Thread(target=self._serve, name="bench-control", daemon=True).start()

    def _serve(self) -> None:
        for line in sys.stdin:
            if line.strip() == "stats":
                peak, current = memory_kib()
                emit("stats", cpu_s=cpu_seconds(), maxrss_kib=peak, rss_kib=current)
        self._loop.call_soon_threadsafe(self.stopped.set)


async def serve_websockets(respond: Callable[[Any], Awaitable[None]], host: str) -> None:
    """Serve ``respond`` per connection on ``websockets``' own server, as the baseline and the
    floor do (compression off, :data:`MAX_MESSAGE`); print the port; stop when stdin closes.
    """
    control = ServerControl()
    async with serve(respond, host, 0, compression=None, max_size=MAX_MESSAGE) as server:
        port = next(iter(server.sockets)).getsockname()[1]
        emit("listening", port=port)
        await control.stopped.wait()


def server_parser(description: str) -> argparse.ArgumentParser:
    """Return the argument parser of a benchmark server script."""
    parser = argparse.ArgumentParser(description=description)
    add_process_options(parser)
    parser.add_argument("--host", default="127.0.0.1")
    return parser
