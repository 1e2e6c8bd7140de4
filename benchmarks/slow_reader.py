"""What one client that never reads costs the server, and the other clients.

Starts ``tests/servers/large_reply_server.py`` (a server whose ``/large`` answers 500 KB) in a
subprocess, then:

1. times ``--calls-timed`` sequential calls of ``/small`` from a srvwire client (no stuck peer);
2. opens a raw connection with a small receive buffer that never reads, and pipelines
   ``--stuck-calls`` calls of ``/large`` on it (``--batches``: each as a batch of one call);
3. times the same sequential calls again while that connection is stuck;
4. waits up to ``--wait`` seconds for the server to log that it closed the stuck connection.

It prints the server's RSS growth (the peak, VmHWM, less VmRSS before the stuck client came),
whether and when the stuck connection was closed (and whether the server's end of it was still
open when the wait ended), and the other client's median and slowest call times with the stuck
peer, as ratios of its median without, measured in the same run. Linux only
(``/proc``). Options after ``--`` go to the server (``-- --max-queued-bytes 1048576``).

    python benchmarks/slow_reader.py [--batches] [--stuck-calls N] [-- SERVER OPTIONS]
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import json
import os
import socket
import statistics
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

from srvwire.client import connect

SERVER = Path(__file__).resolve().parents[1] / "tests" / "servers" / "large_reply_server.py"
MIB = 2**20
MEMORY_GUARD_KIB = 3 * 2**20  # stop the server past 3 GiB: the machine is shared


def status_kib(pid: int, field: str) -> int:
    """Return a ``/proc/<pid>/status`` field in KiB (``VmRSS``, ``VmHWM``)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise LookupError(field)


def masked_text_frame(payload: bytes) -> bytes:
    """One client-to-server WebSocket text frame (masked, as RFC 6455 requires of clients)."""
    mask = os.urandom(4)
    size = len(payload)
    if size < 126:
        header = struct.pack("!BB", 0x81, 0x80 | size)
    elif size < 2**16:
        header = struct.pack("!BBH", 0x81, 0x80 | 126, size)
    else:
        header = struct.pack("!BBQ", 0x81, 0x80 | 127, size)
    body = bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
    return header + mask + body


def open_stuck_connection(port: int, receive_buffer: int = 4096) -> socket.socket:
    """Open a WebSocket connection that will never read: not even the handshake's answer."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, receive_buffer)
    sock.connect(("127.0.0.1", port))
    key = base64.b64encode(os.urandom(16)).decode()
    sock.sendall(
        (
            "GET / HTTP/1.1\r\n"
            f"Host: 127.0.0.1:{port}\r\n"
            "Upgrade: websocket\r\nConnection: Upgrade\r\n"
            f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n"
        ).encode()
    )
    return sock


def stuck_calls(count: int, batches: bool) -> bytes:
    """``count`` calls of ``/large`` as WebSocket frames, each alone or in a batch of one."""
    frames = []
    for i in range(count):
        call = {"jsonrpc": "2.0", "id": i, "method": "/large", "params": {}}
        frames.append(masked_text_frame(json.dumps([call] if batches else call).encode()))
    return b"".join(frames)


def still_established(server_port: int, client_port: int) -> bool:
    """Whether the kernel still has the server's end of that TCP connection open."""
    wanted = (f"{server_port:04X}", f"{client_port:04X}")
    for line in Path("/proc/net/tcp").read_text().splitlines()[1:]:
        fields = line.split()
        local, remote, state = fields[1], fields[2], fields[3]
        if (local.split(":")[1], remote.split(":")[1]) == wanted and state == "01":
            return True
    return False


class ServerProcess:
    """The server subprocess; its stderr lines are kept, and a line can be waited for."""

    def __init__(self, options: list[str]) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, str(SERVER), *options],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        assert self.proc.stdout is not None and self.proc.stderr is not None
        self.port = int(self.proc.stdout.readline())
        self.lines: list[tuple[float, str]] = []
        self.changed = threading.Condition()
        threading.Thread(target=self._read, args=(self.proc.stderr,), daemon=True).start()

    def _read(self, stream: object) -> None:
        for line in stream:  # type: ignore[attr-defined]
            with self.changed:
                self.lines.append((time.monotonic(), line.rstrip()))
                self.changed.notify_all()

    def wait_for(self, text: str, timeout: float) -> float | None:
        """Return when a line containing ``text`` was logged; None if none within ``timeout``."""
        end = time.monotonic() + timeout
        with self.changed:
            while True:
                for when, line in self.lines:
                    if text in line:
                        return when
                left = end - time.monotonic()
                if left <= 0 or status_kib(self.proc.pid, "VmRSS") > MEMORY_GUARD_KIB:
                    return None
                self.changed.wait(min(left, 0.2))

    def stop(self) -> None:
        self.proc.terminate()
        self.proc.wait(10)


async def call_times(url: str, count: int) -> list[float]:
    """Time ``count`` sequential calls of ``/small`` on a fresh srvwire connection."""
    times = []
    async with connect(url) as client:
        for _ in range(count):
            start = time.perf_counter()
            await client.call("/small", {}, srv_type="std_srvs/srv/Trigger")
            times.append(time.perf_counter() - start)
    return times


async def measure(args: argparse.Namespace) -> dict[str, object]:
    server = ServerProcess(args.server_options)
    url = f"ws://127.0.0.1:{server.port}"
    try:
        await call_times(url, 50)  # warm up: imports, first connection
        alone = await call_times(url, args.calls_timed)
        before_kib = status_kib(server.proc.pid, "VmRSS")
        stuck = open_stuck_connection(server.port)
        sent_at = time.monotonic()
        data = stuck_calls(args.stuck_calls, args.batches)
        stuck.setblocking(False)
        sent = 0
        while sent < len(data):  # the server may stop reading: send what it takes
            try:
                sent += stuck.send(data[sent:])
            except BlockingIOError:
                if time.monotonic() - sent_at > 5:
                    break
                await asyncio.sleep(0.01)
        with_stuck = await call_times(url, args.calls_timed)
        closed_at = await asyncio.to_thread(server.wait_for, args.close_line, args.wait)
        peak_kib = status_kib(server.proc.pid, "VmHWM")
        open_at_end = still_established(server.port, stuck.getsockname()[1])
        waited = time.monotonic() - sent_at
        stuck.close()
    finally:
        server.stop()
    return {
        "stuck_calls": args.stuck_calls,
        "batches": args.batches,
        "bytes_sent_by_stuck_client": sent,
        "rss_growth_mib": round((peak_kib - before_kib) / 1024, 1),
        "closed_after_s": None if closed_at is None else round(closed_at - sent_at, 2),
        "server_end_open_after_s": round(waited, 1) if open_at_end else None,
        "median_call_ms_alone": round(statistics.median(alone) * 1000, 3),
        "median_call_ms_with_stuck_peer": round(statistics.median(with_stuck) * 1000, 3),
        "ratio": round(statistics.median(with_stuck) / statistics.median(alone), 2),
        "slowest_ms_alone": round(max(alone) * 1000, 3),
        "slowest_ms_with_stuck_peer": round(max(with_stuck) * 1000, 3),
        "slowest_with_stuck_over_median_alone": round(
            max(with_stuck) / statistics.median(alone), 1
        ),
    }


def main() -> None:
    argv = sys.argv[1:]
    server_options = argv[argv.index("--") + 1 :] if "--" in argv else []
    own = argv[: argv.index("--")] if "--" in argv else argv
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stuck-calls", type=int, default=300)
    parser.add_argument("--batches", action="store_true", help="send each call as a batch of one")
    parser.add_argument("--calls-timed", type=int, default=300)
    parser.add_argument("--wait", type=float, default=40.0, help="seconds to wait for the close")
    parser.add_argument(
        "--close-line", default="write timeout", help="the server's log text that says it closed"
    )
    args = parser.parse_args(own)
    args.server_options = server_options
    print(json.dumps(asyncio.run(measure(args))))


if __name__ == "__main__":
    main()
