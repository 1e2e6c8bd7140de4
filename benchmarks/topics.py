"""Topic throughput: srvwire's topics against raw websockets notifications, in the same run.

Each side runs its server in a child process and its subscribers in this one. Once every
subscriber is connected, the server publishes MESSAGES messages of about 1 KB as fast as it
can; the time is from the start signal until every subscriber has received the last one, and
the result is messages a second *per subscriber*.

* srvwire: ``Server.topic`` (reliable, depth large enough that nothing is dropped) and
  ``pub.publish`` in a loop that yields to the event loop every 100 messages; subscribers use
  ``client.subscribe``, which validates each message into the typed ``std_msgs/msg/String``.
* raw: ``websockets.asyncio.server.serve``; each message is written to JSON once (the same
  ``$/message`` envelope srvwire sends) and ``await ws.send`` to each subscriber in turn;
  subscribers use ``websockets.asyncio.client.connect`` and ``json.loads`` each message.

Beside the rates, each side's CPU time during the timed window is read (the subscribers' in
this process, the server's in the child, which reports its own ``time.process_time()``), and
printed as microseconds per message delivered: on a shared machine the rates follow the load,
the CPU per message much less. With two CPUs or more the server and the subscribers run on one
each (``--no-pin`` to leave them free), and the CPU that other processes used meanwhile (from
``/proc/stat``) is printed, so that a reader can tell how loaded the machine was.

Run ``python benchmarks/topics.py`` (``--quick`` for a smoke run; ``--access-log`` turns the
server's access log on, written to a handler that discards it, to measure what it costs;
``--help`` for the options).
Not part of the test suite; ``tests/test_benchmarks.py`` makes a smoke run.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import NamedTuple

from common import pin_to_cpu
from run import machine_busy_seconds

MESSAGES = 3000
MAX_MESSAGES = 9990  # srvwire's side asks for a depth of MESSAGES + 10, and depth is at most 10 000
PAYLOAD = "x" * 1000
HERE = Path(__file__).resolve()


# --- the servers (child processes) ---------------------------------------------------------


async def srvwire_server(count: int, access_log: bool = False) -> None:
    import logging

    from srvwire import Server, load_message, load_service, serve

    String = load_message("std_msgs/msg/String")
    Trigger = load_service("std_srvs/srv/Trigger")
    if access_log:  # every line made into a record, then discarded
        logger = logging.getLogger("srvwire.access")
        logger.setLevel(logging.INFO)
        logger.propagate = False
        logger.addHandler(logging.NullHandler())
    server = Server(access_log=access_log)
    pub = server.topic("/bench", String, qos={"depth": count + 10})
    message = String(data=PAYLOAD)

    def cpu(request: object) -> object:
        return {"success": True, "message": repr(time.process_time())}

    async def start(request: object) -> object:
        for n in range(count):
            pub.publish(message)
            if n % 100 == 99:
                await asyncio.sleep(0)
        return {"success": True}

    server.add_service("/start", Trigger, start)
    server.add_service("/cpu", Trigger, cpu)
    async with serve(server, "127.0.0.1", 0) as running:
        print(running.port, flush=True)
        await asyncio.Event().wait()


async def raw_server(count: int) -> None:
    from websockets.asyncio.server import ServerConnection, serve

    subscribers: list[ServerConnection] = []

    async def handler(ws: ServerConnection) -> None:
        async for text in ws:
            if text == "subscribe":
                subscribers.append(ws)
                await ws.send("subscribed")
            elif text == "cpu":
                await ws.send(repr(time.process_time()))
            elif text == "start":
                for seq in range(1, count + 1):
                    data = json.dumps(
                        {
                            "jsonrpc": "2.0",
                            "method": "$/message",
                            "params": {
                                "subscription": 1,
                                "seq": seq,
                                "dropped": 0,
                                "message": {"data": PAYLOAD},
                            },
                        },
                        separators=(",", ":"),
                    )
                    for subscriber in subscribers:
                        await subscriber.send(data)

    async with serve(handler, "127.0.0.1", 0, compression=None) as server:
        port = next(iter(server.sockets)).getsockname()[1]
        print(port, flush=True)
        await asyncio.Event().wait()


# --- the subscribers (this process) --------------------------------------------------------


class Run(NamedTuple):
    """One run, over the timed window: from the start signal to the last message everywhere."""

    rate: float  # messages a second, per subscriber
    client_cpu: float  # CPU seconds of this process (the subscribers)
    server_cpu: float  # CPU seconds of the server's process
    other_load: float  # CPUs that other processes on the machine kept busy, on average


class Window:
    """Times the window: wall clock, this process's CPU, the machine's busy time."""

    def __init__(self) -> None:
        self.cpu = time.process_time()
        self.busy = machine_busy_seconds()
        self.begin = time.perf_counter()

    def end(self, count: int, server_cpu: float) -> Run:
        elapsed = time.perf_counter() - self.begin
        cpu = time.process_time() - self.cpu
        # CPU neither side of the benchmark used while it ran: other work on the machine.
        others = machine_busy_seconds() - self.busy - cpu - server_cpu
        return Run(count / elapsed, cpu, server_cpu, max(0.0, others) / elapsed)


async def run_srvwire(port: int, subscribers: int, count: int) -> Run:
    from srvwire import connect

    clients = [await connect(f"ws://127.0.0.1:{port}", timeout=60) for _ in range(subscribers + 1)]
    try:
        subscriptions = [await c.subscribe("/bench").start() for c in clients[1:]]

        async def receive(sub: object) -> None:
            for _ in range(count):
                await sub.receive()  # type: ignore[attr-defined]

        async def server_cpu() -> float:
            reply = await clients[0].call("/cpu", {})
            return float(reply.message)  # type: ignore[attr-defined]

        server_before = await server_cpu()
        window = Window()
        receiving = [asyncio.create_task(receive(sub)) for sub in subscriptions]
        await clients[0].call("/start", {})
        await asyncio.gather(*receiving)
        run = window.end(count, await server_cpu() - server_before)
        assert all(sub.dropped == 0 for sub in subscriptions)
        return run
    finally:
        for client in clients:
            await client.close()


async def run_raw(port: int, subscribers: int, count: int) -> Run:
    from websockets.asyncio.client import connect

    url = f"ws://127.0.0.1:{port}"
    control = await connect(url, compression=None, max_size=None)
    sockets = [await connect(url, compression=None, max_size=None) for _ in range(subscribers)]
    try:
        for ws in sockets:
            await ws.send("subscribe")
            assert await ws.recv() == "subscribed"

        async def receive(ws: object) -> None:
            for _ in range(count):
                json.loads(await ws.recv())  # type: ignore[attr-defined]

        async def server_cpu() -> float:
            await control.send("cpu")
            return float(await control.recv())

        server_before = await server_cpu()
        window = Window()
        receiving = [asyncio.create_task(receive(ws)) for ws in sockets]
        await control.send("start")
        await asyncio.gather(*receiving)
        return window.end(count, await server_cpu() - server_before)
    finally:
        for ws in [control, *sockets]:
            await ws.close()


def measure(
    side: str,
    subscribers: int,
    count: int,
    server_cpu: int | None = None,
    access_log: bool = False,
) -> Run:
    """One run of ``side``; its server runs pinned to ``server_cpu`` when that is given, with
    its access log on if ``access_log``."""
    pin = [] if server_cpu is None else ["--cpu", str(server_cpu)]
    logged = ["--access-log"] if access_log else []
    process = subprocess.Popen(
        [sys.executable, str(HERE), "--serve", side, "--messages", str(count), *pin, *logged],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert process.stdout is not None
        port = int(process.stdout.readline())
        run = run_srvwire if side == "srvwire" else run_raw
        return asyncio.run(run(port, subscribers, count))
    finally:
        process.kill()
        process.wait()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--quick", action="store_true", help="a smoke run: 300 messages, once")
    parser.add_argument("--repeat", type=int, default=3, help="runs of each (default: 3)")
    parser.add_argument(
        "--messages", type=int, default=MESSAGES, help=f"per run (default: {MESSAGES})"
    )
    parser.add_argument(
        "--subscribers",
        default="1,10",
        help="how many subscribers, comma-separated (default: 1,10)",
    )
    parser.add_argument(
        "--no-pin",
        action="store_true",
        help="run the server and the subscribers on any CPU (default: one CPU each, if two)",
    )
    parser.add_argument(
        "--access-log",
        action="store_true",
        help="srvwire's server with its access log on (lines made, then discarded)",
    )
    parser.add_argument("--serve", choices=("srvwire", "raw"), help=argparse.SUPPRESS)
    parser.add_argument("--cpu", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.serve is not None:
        pin_to_cpu(args.cpu)
        if args.serve == "srvwire":
            asyncio.run(srvwire_server(args.messages, args.access_log))
        else:
            asyncio.run(raw_server(args.messages))
        return 0
    count = 300 if args.quick else args.messages
    if not 1 <= count <= MAX_MESSAGES:
        parser.error(f"--messages must be from 1 to {MAX_MESSAGES}")
    repeat = 1 if args.quick else args.repeat
    try:
        counts = [int(n) for n in args.subscribers.split(",")]
    except ValueError:
        counts = []
    if not counts or min(counts) < 1:
        parser.error("--subscribers takes positive integers, such as 1,10")
    cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
    server_cpu = None
    if not args.no_pin and len(cpus) >= 2:
        server_cpu = cpus[0]
        pin_to_cpu(cpus[1])  # the subscribers; the server is started on the other
    print(f"{count} messages of about 1 KB; median of {repeat} runs; messages/s per subscriber")
    print(f"{'subscribers':>11}  {'raw websockets':>14}  {'srvwire':>10}  {'ratio':>6}  (each run)")
    cpu_rows: list[str] = []
    loads: list[float] = []
    for subscribers in counts:
        raw: list[Run] = []
        ours: list[Run] = []
        for _ in range(repeat):  # interleaved, so that a change in load hits both sides alike
            raw.append(measure("raw", subscribers, count, server_cpu))
            ours.append(measure("srvwire", subscribers, count, server_cpu, args.access_log))
        r = statistics.median(run.rate for run in raw)
        s = statistics.median(run.rate for run in ours)
        each = ", ".join(f"{o.rate / w.rate:.2f}" for w, o in zip(raw, ours, strict=True))
        print(f"{subscribers:>11}  {r:>14,.0f}  {s:>10,.0f}  {s / r:>6.2f}  ({each})", flush=True)
        delivered = count * subscribers / 1e6  # so that CPU seconds become µs per message
        cells = [
            statistics.median(cpu / delivered for cpu in seconds)
            for seconds in (
                [run.client_cpu for run in raw],
                [run.client_cpu for run in ours],
                [run.server_cpu for run in raw],
                [run.server_cpu for run in ours],
            )
        ]
        cpu_rows.append(
            f"{subscribers:>11}  {cells[0]:>8.1f} {cells[1]:>8.1f} {cells[1] / cells[0]:>6.2f}"
            f"  {cells[2]:>8.1f} {cells[3]:>8.1f} {cells[3] / cells[2]:>6.2f}"
        )
        loads += [run.other_load for run in raw + ours]
    print("\nCPU per message delivered, µs (median): the subscribers' process | the server's")
    columns = f"{'raw':>8} {'srvwire':>8} {'ratio':>6}"
    print(f"{'subscribers':>11}  {columns}  {columns}")
    for row in cpu_rows:
        print(row)
    pinned = "unpinned" if server_cpu is None else "server and subscribers on one CPU each"
    print(
        f"\n{pinned}; other processes kept {statistics.median(loads):.2f} CPUs busy "
        f"(median of the runs; {min(loads):.2f}-{max(loads):.2f}) of {os.cpu_count()}"
    )
    return 0


if __name__ == "__main__":
    started = time.monotonic()
    status = main()
    if "--serve" not in sys.argv:
        print(f"({time.monotonic() - started:.0f} s)")
    raise SystemExit(status)
