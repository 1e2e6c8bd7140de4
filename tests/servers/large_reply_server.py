"""A real srvwire server with a large reply, for measuring what a client that never reads costs.

Run as ``python large_reply_server.py [--reply-bytes N] [Server options as --name value]``.
It prints the port it listens on (on 127.0.0.1) as its first line, then logs srvwire's lines
to stderr. Its services:

* ``/large`` (``std_srvs/srv/Trigger``) answers at once with a ``message`` of
  ``--reply-bytes`` characters;
* ``/small`` answers at once with an empty message;
* ``/values`` takes ``int32[] values`` and answers ``ok``: a request that makes validation work.

Any other ``--name value`` is passed to :class:`srvwire.server.Server` as ``name=value``
(numbers as numbers, ``none`` as None), so the same script measures any setting of the limits.
"""

from __future__ import annotations

import asyncio
import logging
import sys
from typing import Any

from srvwire.loader import load_service
from srvwire.models import build_service
from srvwire.parser import parse_service
from srvwire.server import Server, serve


def parse_options(argv: list[str]) -> tuple[int, dict[str, Any]]:
    reply_bytes = 500_000
    options: dict[str, Any] = {}
    for name, text in zip(argv[::2], argv[1::2], strict=True):
        key = name.removeprefix("--").replace("-", "_")
        value: Any = None if text == "none" else float(text) if "." in text else int(text)
        if key == "reply_bytes":
            reply_bytes = int(value)
        else:
            options[key] = value
    return reply_bytes, options


async def main() -> None:
    reply_bytes, options = parse_options(sys.argv[1:])
    logging.basicConfig(stream=sys.stderr, level=logging.INFO, format="%(levelname)s %(message)s")
    server = Server(**options)
    trigger = load_service("std_srvs/srv/Trigger")
    large = trigger.Response(success=True, message="x" * reply_bytes)
    small = trigger.Response(success=True, message="")

    async def answer_large(request: Any) -> Any:
        return large

    async def answer_small(request: Any) -> Any:
        return small

    server.add_service("/large", trigger, answer_large)
    server.add_service("/small", trigger, answer_small)
    values = build_service(parse_service("int32[] values\n---\nbool ok\n", "limits", "Values"))

    async def answer_ok(request: Any) -> Any:
        return {"ok": True}

    server.add_service("/values", values, answer_ok)
    async with serve(server, "127.0.0.1", 0) as running:
        print(running.port, flush=True)
        await asyncio.Event().wait()


if __name__ == "__main__":
    asyncio.run(main())
