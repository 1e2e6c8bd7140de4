"""The memory a client that never reads can take, measured against the bound docs/limits.md states.

A server runs in a subprocess (``servers/large_reply_server.py``, whose ``/large`` answers
500 KB), so its RSS is its own. A raw client with a small receive buffer opens a WebSocket,
pipelines 300 calls of ``/large`` (alone, then as one-call batches) and never reads a byte.
The server's peak RSS (``VmHWM``) less its RSS before must stay under the bound, the
connection must be closed after the write timeout, with its log line, and another client's
calls must be answered meanwhile.
"""

from __future__ import annotations

import asyncio
import base64
import json
import logging
import os
import socket
import struct
import sys
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from websockets.asyncio.client import connect as ws_connect

import srvwire
from srvwire.errors import RegistrationError
from srvwire.models import build_action, build_message, build_service
from srvwire.parser import parse_action, parse_message, parse_service
from srvwire.server import RunningServer
from srvwire.serving import ServedConnection
from srvwire.transports.websockets import READ_SIZE
from support import ROOT, scaled

SERVER = ROOT / "tests" / "servers" / "large_reply_server.py"
FLOODING_SERVER = ROOT / "tests" / "servers" / "flooding_server.py"
MIB = 2**20
KIB = 2**10

# The terms of docs/limits.md's bound, as this test sets them.
BUDGET = 1 * MIB  # max_queued_bytes
REPLY = 500_000 + 64  # the largest reply: its message, and the JSON-RPC envelope around it
MAX_IN_FLIGHT = 256
PER_CALL = 4 * KIB  # what a call in flight holds before its handler runs (measured)
SLACK = 2 * MIB  # the allocator's own slack, which RSS counts (measured)
WRITE_TIMEOUT = 2.0
CALLS = 300


ADD_TWO_INTS = "example_interfaces/srv/AddTwoInts"


def bound() -> int:
    """docs/limits.md's bound, for handlers that answer without waiting and small requests:
    the budget, the reply that crosses it three times over, the calls in flight, the slack."""
    return BUDGET + 3 * REPLY + MAX_IN_FLIGHT * PER_CALL + SLACK


def status_kib(pid: int, field: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise LookupError(field)


def masked_text_frame(payload: bytes) -> bytes:
    """One client-to-server text frame, masked as RFC 6455 requires of a client."""
    mask = os.urandom(4)
    size = len(payload)
    if size < 126:
        header = struct.pack("!BB", 0x81, 0x80 | size)
    else:
        header = struct.pack("!BBH", 0x81, 0x80 | 126, size)
    return header + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(payload))


class ServerProcess:
    def __init__(self, process: asyncio.subprocess.Process, port: int) -> None:
        self.process = process
        self.port = port
        self.url = f"ws://127.0.0.1:{port}"

    async def logged(self, text: str) -> str:
        """Return the first line of the server's log that contains ``text``."""
        assert self.process.stderr is not None
        while line := (await self.process.stderr.readline()).decode():
            if text in line:
                return line
        raise AssertionError(f"the server ended without logging {text!r}")

    @property
    def rss(self) -> int:
        return status_kib(self.process.pid, "VmRSS") * KIB

    @property
    def peak_rss(self) -> int:
        return status_kib(self.process.pid, "VmHWM") * KIB


@pytest.fixture
async def large_reply_server() -> AsyncIterator[ServerProcess]:
    process = await asyncio.create_subprocess_exec(
        sys.executable,
        str(SERVER),
        "--max-queued-bytes",
        str(BUDGET),
        "--write-timeout",
        str(WRITE_TIMEOUT),
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    try:
        assert process.stdout is not None
        async with asyncio.timeout(scaled(30)):
            port = int(await process.stdout.readline())
        yield ServerProcess(process, port)
    finally:
        process.terminate()
        await process.wait()


async def open_stuck_connection(port: int, messages: list[bytes]) -> socket.socket:
    """Open a WebSocket with a 4 KiB receive buffer, send ``messages``, and never read."""
    loop = asyncio.get_running_loop()
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.setblocking(False)
    await loop.sock_connect(sock, ("127.0.0.1", port))
    key = base64.b64encode(os.urandom(16)).decode()
    handshake = (
        f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n"
        "Upgrade: websocket\r\nConnection: Upgrade\r\n"
        f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n"
    )
    frames = b"".join(masked_text_frame(message) for message in messages)
    await loop.sock_sendall(sock, handshake.encode() + frames)
    return sock


async def open_served_stuck_connection(
    running: RunningServer,
) -> tuple[socket.socket, ServedConnection]:
    """Open a stuck connection (:func:`open_stuck_connection`) to the running server in this
    process, wait until the server serves it (it sends ``$/services`` then), and return the
    socket and the server's connection."""
    sock = await open_stuck_connection(running.port, [])
    loop = asyncio.get_running_loop()
    opening = b""
    while b"$/services" not in opening:
        opening += await asyncio.wait_for(loop.sock_recv(sock, 4096), scaled(10))
    (served,) = running._connections
    return sock, served


@pytest.mark.parametrize("batches", [False, True], ids=["calls", "one-call batches"])
async def test_a_client_that_never_reads_holds_no_more_than_the_bound(
    large_reply_server: ServerProcess, batches: bool
) -> None:
    server = large_reply_server
    trigger = "std_srvs/srv/Trigger"
    async with srvwire.connect(server.url) as warm:  # warm up: the first of everything
        await warm.call("/large", {}, srv_type=trigger)
        for _ in range(100):
            await warm.call("/small", {}, srv_type=trigger)
    before = server.rss
    calls = [{"jsonrpc": "2.0", "id": i, "method": "/large", "params": {}} for i in range(CALLS)]
    stuck = await open_stuck_connection(
        server.port, [json.dumps([call] if batches else call).encode() for call in calls]
    )
    try:
        async with srvwire.connect(server.url) as other:  # served while the first is stuck
            for _ in range(20):
                assert (await other.call("/small", {}, srv_type=trigger)).success
        async with asyncio.timeout(scaled(WRITE_TIMEOUT + 30)):
            line = await server.logged("closed the connection from")
        assert line.startswith("WARNING ")
        assert line.rstrip().endswith(
            "with code 1008: write timeout: the peer did not read what was sent for 2 s"
        )
        growth = server.peak_rss - before
        assert growth < bound(), f"grew {growth / MIB:.1f} MiB, over {bound() / MIB:.1f} MiB"
    finally:
        stuck.close()


# The same bound for topic data: the budget holds it too.
TOPIC_MESSAGE = 10_000 + 100  # flooding_server.py's message, in its $/message envelope


async def test_a_subscriber_that_never_reads_holds_no_more_than_the_budget() -> None:
    """A server publishes 10 KB about a thousand times a second; a raw client subscribes with a
    queue deep enough to hold 100 MB (``depth`` 10 000) and never reads. The server's peak RSS
    growth stays under docs/limits.md's bound with no calls in flight, ``B + 3·R + P``, and the
    slack: the topic data it holds counts against ``max_queued_bytes``."""
    process = await asyncio.create_subprocess_exec(
        sys.executable,
        str(FLOODING_SERVER),
        "--max-queued-bytes",
        str(BUDGET),
        stdout=asyncio.subprocess.PIPE,
    )
    try:
        assert process.stdout is not None
        async with asyncio.timeout(scaled(30)):
            port = int(await process.stdout.readline())
        server = ServerProcess(process, port)
        async with srvwire.connect(server.url) as reader:  # warm up, and keep reading
            async with reader.subscribe("/flood", qos={"depth": 100}) as flood:
                for _ in range(1000):
                    await flood.receive()
                before = server.rss
                subscribe = {
                    "jsonrpc": "2.0",
                    "id": 1,
                    "method": "$/subscribe",
                    "params": {"topic": "/flood", "qos": {"depth": 10_000}},
                }
                stuck = await open_stuck_connection(port, [json.dumps(subscribe).encode()])
                try:
                    for n in range(3000):  # about 3 s, 30 MB published
                        await flood.receive()
                        if n % 500 == 0:
                            reply = await reader.call(
                                "/add_two_ints", {"a": n, "b": 1}, srv_type=ADD_TWO_INTS
                            )
                            assert reply.sum == n + 1
                finally:
                    stuck.close()
        growth = server.peak_rss - before
        limit = BUDGET + 3 * TOPIC_MESSAGE + TOPIC_MESSAGE + SLACK  # B + 3·R + P, and the slack
        assert growth < limit, f"grew {growth / MIB:.1f} MiB, over {limit / MIB:.1f} MiB"
    finally:
        process.kill()
        await process.wait()


# --- pings from a client that never reads ---------------------------------------------------------


def masked_ping(payload: bytes) -> bytes:
    """One client-to-server ping (at most 125 bytes), masked."""
    mask = os.urandom(4)
    masked = bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
    return struct.pack("!BB", 0x89, 0x80 | len(payload)) + mask + masked


@pytest.mark.parametrize("transport", ["websockets", "picows"], indirect=True)
async def test_pings_from_a_client_that_never_reads_queue_no_more_than_the_budget(
    transport: srvwire.transports.base.Transport,
) -> None:
    # Each ping asks for a pong; a client that never reads would have them all queued. Past
    # the budget the server keeps the answer to the latest ping only; the pongs to the pings
    # of one read (websockets writes them after the read) may cross it, as a reply does.
    budget = 64 * KIB
    server = srvwire.Server(max_queued_bytes=budget)
    async with srvwire.serve(server, "127.0.0.1", 0, transport=transport) as running:
        sock, served = await open_served_stuck_connection(running)
        loop = asyncio.get_running_loop()
        ws = served.conn._ws  # type: ignore[attr-defined]
        sending = getattr(ws, "underlying_transport", None) or ws.transport
        sending.get_extra_info("socket").setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 8 * KIB)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 * KIB)
        chunk = b"".join(masked_ping(b"p" * 125) for _ in range(1000))
        most = 0
        try:
            for _ in range(20):  # 2.6 MB of pongs asked for; the server reads as it goes
                await loop.sock_sendall(sock, chunk)
                most = max(most, served.conn.buffered())
        finally:
            sock.close()
        assert served.conn.congested or most > budget // 2  # the pongs did fill the buffer
        assert most <= budget + READ_SIZE, most


@pytest.mark.parametrize("transport", ["websockets", "picows"], indirect=True)
async def test_pings_from_a_client_that_resets_write_no_warning_per_pong(
    transport: srvwire.transports.base.Transport, caplog: pytest.LogCaptureFixture
) -> None:
    # The client closes with its pongs unread: the kernel resets the connection while the
    # server still answers the pings it read. asyncio warns for every write to a transport
    # that failed; the server writes no pong to one that is closing.
    caplog.set_level(logging.WARNING, logger="asyncio")
    async with srvwire.serve(srvwire.Server(), "127.0.0.1", 0, transport=transport) as running:
        sock, served = await open_served_stuck_connection(running)
        loop = asyncio.get_running_loop()
        handler = served.serving
        assert handler is not None
        await loop.sock_sendall(sock, b"".join(masked_ping(b"p" * 125) for _ in range(20_000)))
        sock.close()  # what it received unread: a reset
        await asyncio.wait([handler])
    warnings = [r for r in caplog.records if "socket.send() raised" in r.getMessage()]
    assert warnings == []


# --- a type too large to make bare ------------------------------------------------------------

# A request that leaves a fixed array out makes the server create every value of it: one
# pointer per value, once per call in flight. The server refuses a type whose bare instance
# holds more values than a message of max_message_size bytes could carry (every value takes a
# byte of JSON at least), as a client refuses such a type when a server describes it.
LIMIT = 1000
REFUSED = (
    "cannot serve /big: srvwire_tests/srv/Big_Request holds 1001 values, 1001 of them in the "
    "field 'samples' (float64[1001]) when made without its fields, more than "
    "max_message_size=1000 can carry, and the server makes one for each request that leaves "
    "them out: a message of a few bytes would make it hold them all. Raise the server's "
    "max_message_size (None lifts this check with the limit), or declare the fixed array "
    "bounded (T[<=N]) or unbounded (T[])"
)


def sized(count: int, name: str = "Big") -> type[srvwire.Service]:
    return build_service(parse_service(f"float64[{count}] samples\n---\nbool ok\n", PKG, name))


PKG = "srvwire_tests"


async def test_a_request_with_more_fixed_values_than_a_message_can_carry_is_refused() -> None:
    server = srvwire.Server(max_message_size=LIMIT)
    with pytest.raises(RegistrationError) as excinfo:
        server.add_service("/big", sized(LIMIT + 1), lambda request: {"ok": True})
    assert str(excinfo.value) == REFUSED
    assert len(server.registry) == 0
    # At the limit it is served, and a call that leaves the array out gets it made bare.
    server.add_service("/fits", sized(LIMIT, "Fits"), lambda r: {"ok": len(r.samples) == LIMIT})
    # Nested: 10 rows of 100 is the limit; one more value in the request is past it.
    row = build_message(parse_message("float64[100] cells\n", PKG, "Row"))
    rows = f"{PKG}/Row[10] rows\n---\nbool ok\n"
    nested = build_service(parse_service(rows, PKG, "Rows"), lambda _: row)
    server.add_service("/rows", nested, lambda request: {"ok": len(request.rows) == 10})
    more = build_service(parse_service("bool flag\n" + rows, PKG, "More"), lambda _: row)
    with pytest.raises(RegistrationError, match=r"holds 1001 values, 1000 of them in the field "):
        server.add_service("/more", more, lambda request: {})
    # None lifts the check with the limit.
    srvwire.Server(max_message_size=None).add_service("/big", sized(LIMIT + 1), lambda r: {})
    async with srvwire.serve(server, "127.0.0.1", 0) as running:
        async with ws_connect(running.url) as ws:
            for id_, method in enumerate(("/fits", "/rows")):
                await ws.send(json.dumps({"jsonrpc": "2.0", "id": id_, "method": method}))
                reply = {"method": "$/services"}
                while "method" in reply:  # the server's notifications come first
                    reply = json.loads(await asyncio.wait_for(ws.recv(), scaled(5)))
                assert reply == {"jsonrpc": "2.0", "id": id_, "result": {"ok": True}}


async def test_a_response_made_bare_for_the_handler_counts_too() -> None:
    # A handler that takes (request, response) is given a response made bare for each call.
    server = srvwire.Server(max_message_size=LIMIT)
    big = build_service(parse_service(f"bool ok\n---\nint8[{LIMIT + 1}] data\n", PKG, "Out"))
    with pytest.raises(RegistrationError) as excinfo:
        server.add_service("/out", big, lambda request, response: response)
    assert str(excinfo.value).startswith(
        "cannot serve /out: srvwire_tests/srv/Out_Response holds 1001 values"
    )
    assert "makes one for each call, to give the handler" in str(excinfo.value)
    assert str(excinfo.value).endswith(
        ", or let the handler take the request only and return the response"
    )
    server.add_service("/out", big, lambda request: {})  # it builds what it returns


async def test_a_topic_clients_publish_on_and_an_action_goal_count_too() -> None:
    server = srvwire.Server(max_message_size=LIMIT)
    scan = build_message(parse_message(f"float32[{LIMIT + 1}] ranges\n", PKG, "Scan"))
    server.topic("/scan", scan)  # the server only publishes it: it makes none of its own
    with pytest.raises(RegistrationError) as excinfo:
        server.subscription("/scan", scan)(lambda msg: None)
    assert str(excinfo.value).startswith(
        "cannot take messages on the topic /scan: srvwire_tests/msg/Scan holds 1001 values"
    )
    assert "for each message a client publishes that leaves them out" in str(excinfo.value)
    action = build_action(parse_action(f"int32[{LIMIT + 1}] seen\n---\n---\n", PKG, "Walk"))
    with pytest.raises(
        RegistrationError,
        match=r"^cannot serve /walk: srvwire_tests/action/Walk_Goal holds 1001 values",
    ):
        server.add_action("/walk", action, lambda goal, handle: None)


async def test_a_server_checks_the_limit_it_starts_with() -> None:
    # srvwire serve --max-message-size sets the limit after the services are registered.
    server = srvwire.Server(max_message_size=None)
    server.add_service("/big", sized(LIMIT + 1), lambda request: {})
    server.max_message_size = LIMIT
    with pytest.raises(RegistrationError) as excinfo:
        await srvwire.serve(server, "127.0.0.1", 0)
    assert str(excinfo.value) == REFUSED
