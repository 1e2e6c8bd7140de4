"""What a request held by its handler costs the server: left bare, or written out in full.

A server serves ``/bare`` (``float64[N] samples``, N its ``max_message_size``: the largest
fixed array the server serves) and ``/full`` (``float64[] samples``). A raw WebSocket client
sends ``--calls`` requests of ``/bare`` with no params (each field made bare by the server),
then as many of ``/full`` with a message of ``max_message_size`` bytes of one-digit numbers;
each handler holds its request until all of them arrived. Printed per kind: the size of one
message, and the growth of the process's RSS divided by the requests held.

    python benchmarks/bare_requests.py [--calls 16] [--size BYTES]
"""

from __future__ import annotations

import argparse
import asyncio
import json
from pathlib import Path
from typing import Any

from websockets.asyncio.client import connect as ws_connect

import srvwire
from srvwire.models import build_service
from srvwire.parser import parse_service


def rss_mib() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise LookupError("VmRSS")


def full_params(size: int) -> str:
    """``{"samples": [...]}`` of one-digit numbers, the most values a request of about ``size``
    bytes can hold; each becomes a float object of its own."""
    count = (size - 100) // 2
    return '{"samples":[' + ",".join(str(k % 10) for k in range(count)) + "]}"


class Holder:
    """The handler: holds each request until :attr:`release` is set, and says when
    :attr:`expected` requests are held."""

    def __init__(self) -> None:
        self.release = asyncio.Event()
        self.all_held = asyncio.Event()
        self.held = 0
        self.expected = 0

    async def __call__(self, request: Any) -> dict[str, bool]:
        self.held += 1
        if self.held == self.expected:
            self.all_held.set()
        await self.release.wait()
        return {"ok": len(request.samples) > 0}


async def held(url: str, method: str, params: str, calls: int, holder: Holder) -> float:
    """RSS growth per request, with ``calls`` requests of ``method`` held by the handler."""
    holder.held, holder.expected = 0, calls
    holder.release.clear()
    holder.all_held.clear()
    async with ws_connect(url, max_size=None) as ws:
        before = rss_mib()
        for id_ in range(calls):
            await ws.send(f'{{"jsonrpc":"2.0","id":{id_},"method":"{method}","params":{params}}}')
        await holder.all_held.wait()
        growth = (rss_mib() - before) / calls
        holder.release.set()
        answered = 0
        while answered < calls:
            answered += "id" in json.loads(await ws.recv())
        return growth


async def main(calls: int, size: int) -> None:
    bare = build_service(parse_service(f"float64[{size}] samples\n---\nbool ok\n", "b", "Bare"))
    full = build_service(parse_service("float64[] samples\n---\nbool ok\n", "b", "Full"))
    server = srvwire.Server(max_message_size=size, max_in_flight=max(256, calls))
    holder = Holder()
    server.add_service("/bare", bare, holder)
    server.add_service("/full", full, holder)
    params = full_params(size)
    async with srvwire.serve(server, "127.0.0.1", 0) as running:
        for kind, method, sent in (("bare", "/bare", "{}"), ("full", "/full", params)):
            growth = await held(running.url, method, sent, calls, holder)
            print(f"{kind:5} message {len(sent) + 50:>8} B  {growth:6.1f} MiB per request held")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=16)
    parser.add_argument("--size", type=int, default=2**20, help="max_message_size")
    args = parser.parse_args()
    asyncio.run(main(args.calls, args.size))
