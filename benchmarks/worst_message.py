"""How long the worst single message stalls the server, and what it costs in memory and reply.

Starts ``tests/servers/large_reply_server.py`` in a subprocess. A srvwire client calls
``/small`` in a loop, one call at a time, the whole run. Meanwhile a raw WebSocket client
sends each message below ``--repeat`` times, waiting for its reply (when it has one) each
time. Printed per message: its size, the server's time to answer it (seen by its sender),
the size of its reply (and its ratio to the request), the other client's slowest call while
that message was being handled, as a ratio of its median call with nothing else going on
(measured first, in the same run), and the server's peak RSS growth (VmHWM).

Messages, each ``--size`` bytes (1 MiB, the default ``max_message_size``):

* ``invalid elements``: one request whose ``int32[]`` array holds ~350 000 ``{}`` elements;
* ``invalid strings``: the same with ``"x"`` elements;
* ``unknown methods batch``: a batch of ~21 000 calls of a method that does not exist, refused
  whole because it is longer than ``max_batch``;
* ``batch at max_batch``: a batch of ``max_batch`` (100) calls, each with ~10 KB of invalid
  elements.

    python benchmarks/worst_message.py [--repeat 5] [--size BYTES] [-- SERVER OPTIONS]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import sys
import time
from pathlib import Path

from websockets.asyncio.client import connect as ws_connect

from srvwire.client import connect

from slow_reader import ServerProcess, status_kib

SIZE = 2**20


def array_request(element: str, size: int, id: int = 1) -> str:
    """One ``/values`` request of about ``size`` bytes whose array holds copies of ``element``."""
    head = f'{{"jsonrpc":"2.0","id":{id},"method":"/values","params":{{"values":['
    count = (size - len(head) - 3) // (len(element) + 1)
    return head + ",".join([element] * count) + "]}}"


def messages(max_batch: int, size: int) -> dict[str, str]:
    unknown = '{"jsonrpc":"2.0","id":1,"method":"/nope"}'
    per_item = size // max_batch
    return {
        "invalid elements": array_request("{}", size),
        "invalid strings": array_request('"x"', size),
        "unknown methods batch": "[" + ",".join([unknown] * (size // (len(unknown) + 1))) + "]",
        "batch at max_batch": "["
        + ",".join(array_request("{}", per_item - 2, id=i) for i in range(max_batch))
        + "]",
    }


def reset_peak(pid: int) -> None:
    """Start VmHWM again from the current RSS (Linux: 5 to ``clear_refs``), so that each
    message's peak is its own."""
    Path(f"/proc/{pid}/clear_refs").write_text("5")


class Caller:
    """Calls ``/small`` in a loop and records when each call started and how long it took."""

    def __init__(self, url: str) -> None:
        self.url = url
        self.calls: list[tuple[float, float]] = []
        self.stop = asyncio.Event()

    async def run(self) -> None:
        async with connect(self.url) as client:
            while not self.stop.is_set():
                start = time.perf_counter()
                await client.call("/small", {}, srv_type="std_srvs/srv/Trigger")
                self.calls.append((start, time.perf_counter() - start))

    def slowest_since(self, since: float) -> float:
        return max((took for start, took in self.calls if start + took >= since), default=0.0)


async def measure_one(name: str, message: str, args: argparse.Namespace) -> dict[str, object]:
    """Measure one message on a fresh server, so that no other message's memory is reused."""
    server = ServerProcess(args.server_options)
    url = f"ws://127.0.0.1:{server.port}"
    try:
        caller = Caller(url)
        calling = asyncio.create_task(caller.run())
        await asyncio.sleep(2.0)  # the other client alone: its baseline, same run
        alone = statistics.median(took for _, took in caller.calls)
        async with ws_connect(url, max_size=None) as ws:
            await ws.recv()  # $/services
            reset_peak(server.proc.pid)
            before = status_kib(server.proc.pid, "VmRSS")
            times, slowest = [], 0.0
            reply = ""
            for _ in range(args.repeat):
                start = time.perf_counter()
                await ws.send(message)
                reply = str(await ws.recv())
                times.append(time.perf_counter() - start)
                await asyncio.sleep(0.2)  # let the other client's held call finish
                slowest = max(slowest, caller.slowest_since(start))
            peak = status_kib(server.proc.pid, "VmHWM")
        caller.stop.set()
        await calling
    finally:
        server.stop()
    return {
        "message": name,
        "request_bytes": len(message),
        "median_answer_s": round(statistics.median(times), 3),
        "reply_bytes": len(reply),
        "reply_over_request": round(len(reply) / len(message), 4),
        "other_client_slowest_ms": round(slowest * 1000, 1),
        "other_client_median_alone_ms": round(alone * 1000, 3),
        "slowest_over_median_alone": round(slowest / alone, 1),
        "server_peak_growth_mib": round((peak - before) / 1024, 1),
    }


async def measure(args: argparse.Namespace) -> list[dict[str, object]]:
    return [
        await measure_one(name, message, args)
        for name, message in messages(args.max_batch, args.size).items()
    ]


def main() -> None:
    argv = sys.argv[1:]
    own = argv[: argv.index("--")] if "--" in argv else argv
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--max-batch", type=int, default=100, help="the server's max_batch")
    parser.add_argument("--size", type=int, default=SIZE, help="bytes per message (1 MiB)")
    args = parser.parse_args(own)
    args.server_options = argv[argv.index("--") + 1 :] if "--" in argv else []
    for result in asyncio.run(measure(args)):
        print(json.dumps(result))


if __name__ == "__main__":
    main()
