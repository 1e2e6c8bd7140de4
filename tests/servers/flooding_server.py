"""A real srvwire server that publishes 10 KB messages on ``/flood`` about a thousand times a
second, for tests that measure what a subscriber that never reads costs it.

Run as ``python flooding_server.py [--max-queued-bytes N]``. It prints the port it listens on
(on 127.0.0.1) as its first line. It also serves ``/add_two_ints``, so a test can call it while
the topic floods.
"""

from __future__ import annotations

import argparse
import asyncio

from srvwire.loader import load_message, load_service
from srvwire.server import Server, serve

PERIOD = 0.001  # seconds between two publications


async def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--max-queued-bytes", type=int, default=4 * 2**20)
    server = Server(max_queued_bytes=parser.parse_args().max_queued_bytes)
    AddTwoInts = load_service("example_interfaces/srv/AddTwoInts")
    String = load_message("std_msgs/msg/String")
    server.add_service("/add_two_ints", AddTwoInts, lambda r: {"sum": r.a + r.b})
    flood = server.topic("/flood", String, qos={"depth": 10, "reliability": "best_effort"})
    message = String(data="x" * 10_000)
    async with serve(server, "127.0.0.1", 0) as running:
        print(running.port, flush=True)
        while True:
            flood.publish(message)
            await asyncio.sleep(PERIOD)


if __name__ == "__main__":
    asyncio.run(main())
