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

Run ``python benchmarks/topics.py`` (``--quick`` for a smoke run; ``--access-log`` turns the
server's access log on, written to a handler that discards it, to measure what it costs). Not
part of the test suite.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

MESSAGES = 3000
SERVER_CPU: list[float] = []  # srvwire's server: CPU seconds per message delivered, each run
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

    async def start(request: object) -> object:
        for n in range(count):
            pub.publish(message)
            if n % 100 == 99:
                await asyncio.sleep(0)
        return {"success": True}

    server.add_service("/start", Trigger, start)
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


def cpu_seconds(pid: int) -> float:
    """The CPU time the main thread of process ``pid`` (an event loop) has used, from
    ``/proc`` (Linux): its scheduler's count, in nanoseconds."""
    return int(Path(f"/proc/{pid}/schedstat").read_text().split()[0]) / 1e9


async def run_srvwire(port: int, subscribers: int, count: int, pid: int = 0) -> float:
    from srvwire import connect

    clients = [await connect(f"ws://127.0.0.1:{port}", timeout=60) for _ in range(subscribers + 1)]
    try:
        subscriptions = [await c.subscribe("/bench").start() for c in clients[1:]]

        async def receive(sub: object) -> None:
            for _ in range(count):
                await sub.receive()  # type: ignore[attr-defined]

        loop = asyncio.get_running_loop()
        cpu = cpu_seconds(pid) if pid else 0.0
        begin = loop.time()
        receiving = [asyncio.create_task(receive(sub)) for sub in subscriptions]
        await clients[0].call("/start", {})
        await asyncio.gather(*receiving)
        elapsed = loop.time() - begin
        if pid:
            SERVER_CPU.append((cpu_seconds(pid) - cpu) / (count * subscribers))
        assert all(sub.dropped == 0 for sub in subscriptions)
        return count / elapsed
    finally:
        for client in clients:
            await client.close()


async def run_raw(port: int, subscribers: int, count: int) -> float:
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

        loop = asyncio.get_running_loop()
        begin = loop.time()
        receiving = [asyncio.create_task(receive(ws)) for ws in sockets]
        await control.send("start")
        await asyncio.gather(*receiving)
        return count / (loop.time() - begin)
    finally:
        for ws in [control, *sockets]:
            await ws.close()


def measure(side: str, subscribers: int, count: int, access_log: bool = False) -> float:
    process = subprocess.Popen(
        [sys.executable, str(HERE), "--serve", side, "--messages", str(count)]
        + (["--access-log"] if access_log else []),
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert process.stdout is not None
        port = int(process.stdout.readline())
        if side == "srvwire":
            return asyncio.run(run_srvwire(port, subscribers, count, process.pid))
        return asyncio.run(run_raw(port, subscribers, count))
    finally:
        process.kill()
        process.wait()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--quick", action="store_true", help="a smoke run: 300 messages, once")
    parser.add_argument("--repeat", type=int, default=3, help="runs of each (default: 3)")
    parser.add_argument("--messages", type=int, default=MESSAGES)
    parser.add_argument("--access-log", action="store_true", help="the server's access log on")
    parser.add_argument("--serve", choices=("srvwire", "raw"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.serve == "srvwire":
        asyncio.run(srvwire_server(args.messages, args.access_log))
        return 0
    if args.serve == "raw":
        asyncio.run(raw_server(args.messages))
        return 0
    count = 300 if args.quick else args.messages
    repeat = 1 if args.quick else args.repeat
    print(f"{count} messages of about 1 KB; median of {repeat} runs; messages/s per subscriber")
    print(f"{'subscribers':>11}  {'raw websockets':>14}  {'srvwire':>10}  {'ratio':>6}")
    cpu = {}
    for subscribers in (1, 10):
        raw: list[float] = []
        ours: list[float] = []
        SERVER_CPU.clear()
        for _ in range(repeat):  # interleaved, so that a change in load hits both sides alike
            raw.append(measure("raw", subscribers, count))
            ours.append(measure("srvwire", subscribers, count, args.access_log))
        r, s = statistics.median(raw), statistics.median(ours)
        print(f"{subscribers:>11}  {r:>14,.0f}  {s:>10,.0f}  {s / r:>6.2f}", flush=True)
        cpu[subscribers] = statistics.median(SERVER_CPU) * 1e6
    print(
        "srvwire's server, CPU per message delivered: "
        + ", ".join(f"{us:.1f} µs to {n}" for n, us in cpu.items())
    )
    return 0


if __name__ == "__main__":
    started = time.monotonic()
    status = main()
    if "--serve" not in sys.argv:
        print(f"({time.monotonic() - started:.0f} s)")
    raise SystemExit(status)
