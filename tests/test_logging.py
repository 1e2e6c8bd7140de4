"""What the server says: its addresses, an access log, and websockets kept quiet.

Log records are awaited as they come (:class:`Records`), never slept for.
"""

from __future__ import annotations

import asyncio
import logging
import re
import signal
import socket
import subprocess
import sys
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import pytest

from conftest import Echo, Hang, Subtract, open_wire, subtract
from srvwire.errors import ServiceError
from srvwire.loader import load_message
from srvwire.server import Server, serve
from srvwire.serving import AccessLoggedSession
from srvwire.session import ServerSession
from srvwire.transports.base import Transport
from srvwire.transports.websockets import _QuietLogger, interface_addresses
from support import ROOT, scaled

DURATION = r"\d+\.\d\d ms"


class Records(logging.Handler):
    """The records of one logger, to await one by one on the loop that logs them."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.queue: asyncio.Queue[logging.LogRecord] = asyncio.Queue()

    def emit(self, record: logging.LogRecord) -> None:
        self.queue.put_nowait(record)

    async def next(self) -> logging.LogRecord:
        async with asyncio.timeout(scaled(5)):
            return await self.queue.get()

    async def messages(self, count: int) -> list[str]:
        return [(await self.next()).getMessage() for _ in range(count)]


@pytest.fixture
async def access() -> AsyncIterator[Records]:
    logger = logging.getLogger("srvwire.access")
    records = Records()
    level = logger.level
    logger.addHandler(records)
    logger.setLevel(logging.INFO)
    try:
        yield records
    finally:
        logger.removeHandler(records)
        logger.setLevel(level)


def access_server() -> Server:
    server = Server(access_log=True, grace_period=scaled(2))
    server.add_service("/subtract", Subtract, subtract)

    async def refuse(request: Any) -> Any:
        raise ServiceError(4001, "battery too low")

    server.add_service("/refuse", Echo, refuse)
    server.add_service("/hang", Echo, Hang())
    return server


def call(method: str, id: int, **params: Any) -> dict[str, Any]:
    return {"jsonrpc": "2.0", "method": method, "id": id, "params": params}


async def test_the_access_log_has_a_line_per_call_with_its_outcome_and_duration(
    access: Records, transport: Transport
) -> None:
    async with serve(access_server(), "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        await w.call(call("subtract", 1, minuend=3, subtrahend=1))
        await w.call(call("subtract", 2, minuend="three"))
        await w.call(call("refuse", 3, text="x"))
        await w.call(call("no/such_service", 4))
        await w.call(call("hang", 5, text="x", _meta={"timeout": scaled(0.05)}))
        await w.call({"jsonrpc": "2.0", "method": "rpc.discover", "id": 6})
        lines = await access.messages(6)
        peer = lines[0].split()[0]
        if transport.name == "websockets":
            assert re.fullmatch(r"127\.0\.0\.1:\d+", peer)
        patterns = [
            rf"/subtract OK {DURATION}",
            rf"/subtract INVALID_PARAMS {DURATION}",
            rf"/refuse APPLICATION_ERROR 4001 {DURATION}",
            "no/such_service SERVICE_NOT_FOUND -",  # answered at once, as the caller named it
            rf"/hang DEADLINE_EXCEEDED {DURATION}",
            "rpc.discover OK -",
        ]
        for line, pattern in zip(lines, patterns, strict=True):
            assert re.fullmatch(rf"{re.escape(peer)} {pattern}", line), line
        await w.ws.close()


async def test_a_call_admission_refuses_is_logged_with_its_status_and_no_duration(
    access: Records, transport: Transport
) -> None:
    """Calls read in one pass, refused when admitted: the line says why, as for any other."""
    server = access_server()
    server.max_in_flight = 2
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        await w.send(call("hang", 1, text="x"))
        reply = await w.call(call("hang", 1, text="x"))  # the id of a call in flight
        assert reply["error"]["data"]["status"] == "INVALID_REQUEST"
        await w.send(call("hang", 2, text="x"))
        reply = await w.call(call("subtract", 3, minuend=1))  # a third call in flight
        assert reply["error"]["data"]["status"] == "RESOURCE_EXHAUSTED"
        lines = await access.messages(2)
        assert [line.split(" ", 1)[1] for line in lines] == [
            "hang INVALID_REQUEST -",  # as the caller named it
            "subtract RESOURCE_EXHAUSTED -",
        ]
        await w.ws.close()


async def test_a_call_whose_connection_went_away_is_logged_closed(
    access: Records, transport: Transport
) -> None:
    async with serve(access_server(), "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        await w.send(call("hang", 1, text="x"))
        await w.send(call("weird name\n" + "x" * 200, 2))
        (refused,) = await access.messages(1)  # read after the first: that one is running
        assert refused.endswith(" 'weird name\\n" + "x" * 89 + "...' SERVICE_NOT_FOUND -")
        await w.ws.close()
        record = await access.next()
        assert re.fullmatch(rf"\S+ /hang CLOSED {DURATION}", record.getMessage())
        assert record.outcome == "CLOSED"  # type: ignore[attr-defined]
        assert record.service == "/hang"  # type: ignore[attr-defined]
        assert record.duration_ms >= 0  # type: ignore[attr-defined]


async def test_without_the_access_log_a_connection_does_no_work_for_it(
    caplog: pytest.LogCaptureFixture, transport: Transport
) -> None:
    server = Server()
    server.add_service("/subtract", Subtract, subtract)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        with caplog.at_level(logging.DEBUG, "srvwire.access"):
            await w.call(call("subtract", 1, minuend=3, subtrahend=1))
        (connection,) = running._connections
        assert type(connection.session) is ServerSession  # not AccessLoggedSession
        assert caplog.records == []
        await w.ws.close()


async def test_the_access_log_can_go_to_a_logger_of_ones_own(transport: Transport) -> None:
    mine = logging.getLogger("test_logging.mine")
    records = Records()
    mine.addHandler(records)
    mine.setLevel(logging.INFO)
    try:
        server = Server(access_log=mine)
        server.add_service("/subtract", Subtract, subtract)
        async with serve(server, "127.0.0.1", 0, transport=transport) as running:
            w = await open_wire(running)
            await w.call(call("subtract", 1, minuend=3, subtrahend=1))
            (connection,) = running._connections
            assert type(connection.session) is AccessLoggedSession
            assert (await records.next()).getMessage().endswith(" ms")
            await w.ws.close()
    finally:
        mine.removeHandler(records)


# --- topics in the access log --------------------------------------------------------------

String = load_message("std_msgs/msg/String")


async def recv_data(wire: Any) -> Any:
    """The next message that is not an announcement."""
    while (message := await wire.recv()).get("method") in ("$/services", "$/topics"):
        pass
    return message


async def subscribe(wire: Any, id: int, topic: str, **meta: Any) -> list[Any]:
    """Subscribe; return what came before ``$/subscribed``."""
    params: dict[str, Any] = {"topic": topic}
    if meta:
        params["_meta"] = meta
    await wire.send({"jsonrpc": "2.0", "id": id, "method": "$/subscribe", "params": params})
    before = []
    while (message := await recv_data(wire)).get("method") != "$/subscribed":
        before.append(message)
    return before


async def test_a_subscription_has_a_line_when_it_ends_saying_how(
    access: Records, transport: Transport
) -> None:
    # A budget of one byte: a message published while another waits for the writer does not
    # fit, so best effort drops and reliable ends (a burst within the budget would all go).
    server = Server(access_log=True, max_queued_bytes=1)
    chatter = server.topic("/chatter", String)
    lossy = server.topic("/lossy", String, qos={"reliability": "best_effort"})
    tight = server.topic("/tight", String)
    server.topic("/gone", String)
    subscription = rf"(\S+) \$/subscribe (\S+) (\S+) {DURATION} delivered (\d+) dropped (\d+)"
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        await subscribe(w, 1, "/chatter")
        for text in "ab":
            chatter.publish({"data": text})
            assert (await recv_data(w))["params"]["message"] == {"data": text}
        await w.send({"jsonrpc": "2.0", "id": 9, "method": "$/cancel", "params": {"id": 1}})
        came = await subscribe(w, 2, "/lossy", timeout=scaled(0.5))
        for text in "abc":  # at once: the outbox keeps the last
            lossy.publish({"data": text})
        came += await subscribe(w, 3, "/tight")
        tight.publish({"data": "a"})
        tight.publish({"data": "b"})  # at once: a reliable subscription is ended
        came += await subscribe(w, 4, "/gone")
        server.remove_topic("/gone")
        came += await subscribe(w, 5, "/chatter")
        ended = {}
        while len(ended) < 4:  # the cancel's reply, a message, and the four ends, in any order
            message = came.pop(0) if came else await recv_data(w)
            if "id" in message and message["id"] != 9:
                ended[message["id"]] = message["error"]["data"]["status"]
        assert ended == {
            1: "CANCELLED",
            2: "DEADLINE_EXCEEDED",
            3: "RESOURCE_EXHAUSTED",
            4: "SERVICE_NOT_FOUND",
        }
        lines = {}
        while len(lines) < 4:
            record = await access.next()
            if record.service != "$/subscribe":  # type: ignore[attr-defined]
                continue  # $/cancel's line
            match = re.fullmatch(subscription, record.getMessage())
            assert match is not None, record.getMessage()
            lines[match[2]] = match.groups()[2:]
            assert record.service == "$/subscribe"  # type: ignore[attr-defined]
            assert record.topic == match[2]  # type: ignore[attr-defined]
        assert lines == {
            "/chatter": ("CANCELLED", "2", "0"),
            "/lossy": ("DEADLINE_EXCEEDED", "1", "2"),
            "/tight": ("RESOURCE_EXHAUSTED", "0", "0"),
            "/gone": ("SERVICE_NOT_FOUND", "0", "0"),
        }
        await w.ws.close()
        record = await access.next()  # the last, ended with its connection
        match = re.fullmatch(subscription, record.getMessage())
        assert match is not None and match.groups()[1:] == ("/chatter", "CLOSED", "0", "0")
        assert (record.delivered, record.dropped) == (0, 0)  # type: ignore[attr-defined]
        assert match[1] == record.peer  # type: ignore[attr-defined]


async def test_a_refused_subscription_names_its_topic(
    access: Records, transport: Transport
) -> None:
    server = Server(access_log=True)
    server.topic("/chatter", String)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        for id, topic in ((1, "/nope"), (2, "bad topic\n")):
            params = {"topic": topic}
            await w.send({"jsonrpc": "2.0", "id": id, "method": "$/subscribe", "params": params})
            assert (await recv_data(w))["error"]["data"]["status"] == "SERVICE_NOT_FOUND"
        await w.send({"jsonrpc": "2.0", "id": 3, "method": "$/subscribe", "params": [1]})
        assert (await recv_data(w))["error"]["data"]["status"] == "INVALID_PARAMS"
        lines = await access.messages(3)
        assert [line.split(" ", 1)[1] for line in lines] == [
            "$/subscribe /nope SERVICE_NOT_FOUND -",
            "$/subscribe 'bad topic\\n' SERVICE_NOT_FOUND -",
            "$/subscribe - INVALID_PARAMS -",
        ]
        await w.ws.close()


async def test_publishes_without_an_answer_are_summed_up_per_topic_when_the_connection_ends(
    access: Records, transport: Transport
) -> None:
    server = Server(access_log=True)
    received: list[Any] = []
    server.subscription("/cmd", String)(received.append)
    server.subscription("/quiet", String)(received.append)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        publish = {"jsonrpc": "2.0", "method": "$/publish"}
        for n in range(200):
            await w.send({**publish, "params": {"topic": "/cmd", "message": {"data": str(n)}}})
        await w.send({**publish, "params": {"topic": "/cmd", "message": {"data": 1}}})
        await w.send({**publish, "params": {"topic": "/nope", "message": {"data": "x"}}})
        await w.send({**publish, "params": {"topic": "/quiet", "message": {"data": "x"}}})
        # Acknowledged publishes are calls: a line each, once answered.
        ack = {**publish, "id": 1, "params": {"topic": "/cmd", "message": {"data": "y"}}}
        assert (await w.call(ack))["result"] is None
        bad = {**publish, "id": 2, "params": {"topic": "/cmd", "message": {"data": []}}}
        assert (await w.call(bad))["error"]["data"]["status"] == "INVALID_PARAMS"
        missing = {**publish, "id": 3, "params": {"topic": "/nope", "message": {}}}
        assert (await w.call(missing))["error"]["data"]["status"] == "SERVICE_NOT_FOUND"
        lines = await access.messages(3)  # and none for the 203 without an answer
        assert [line.split(" ", 1)[1].rsplit(" ", 2)[0] for line in lines[:2]] == [
            "$/publish /cmd OK",
            "$/publish /cmd INVALID_PARAMS",
        ]
        assert all(re.search(rf" {DURATION}$", line) for line in lines[:2])
        assert lines[2].split(" ", 1)[1] == "$/publish /nope SERVICE_NOT_FOUND -"
        assert len(received) == 202
        await w.ws.close()
        summary = {}
        for _ in range(2):
            record = await access.next()
            summary[record.topic] = record  # type: ignore[attr-defined]
    cmd, quiet = summary["/cmd"], summary["/quiet"]
    assert re.fullmatch(
        rf"\S+ \$/publish /cmd INVALID_PARAMS {DURATION} received 201 invalid 1", cmd.getMessage()
    )
    assert (cmd.received, cmd.invalid) == (201, 1)  # type: ignore[attr-defined]
    assert re.fullmatch(
        r"\S+ \$/publish /quiet OK 0\.00 ms received 1 invalid 0", quiet.getMessage()
    )
    assert access.queue.empty()


async def test_acknowledged_publishes_with_one_id_have_a_line_and_a_duration_each(
    access: Records, transport: Transport
) -> None:
    # An acknowledged publish is answered before the next message is read, so its id is free
    # again at once: each has its own start (kept by id until answered, one would otherwise
    # take the other's and leave it none, "-").
    server = Server(access_log=True)
    received: list[Any] = []
    server.subscription("/cmd", String)(received.append)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        for text in ("a", "b"):  # sent back to back, before either is answered
            message = {"topic": "/cmd", "message": {"data": text}}
            await w.send({"jsonrpc": "2.0", "id": 7, "method": "$/publish", "params": message})
        assert [await w.recv_reply() for _ in range(2)] == [
            {"jsonrpc": "2.0", "id": 7, "result": None}
        ] * 2
        records = [await access.next() for _ in range(2)]
        assert [(r.service, r.topic, r.outcome) for r in records] == [  # type: ignore[attr-defined]
            ("$/publish", "/cmd", "OK")
        ] * 2
        assert all(r.duration_ms is not None for r in records)  # type: ignore[attr-defined]
        assert [m.data for m in received] == ["a", "b"]
        await w.ws.close()
    assert access.queue.empty()


async def test_removing_a_topic_sums_up_what_was_published_on_it_then(
    access: Records, transport: Transport
) -> None:
    server = Server(access_log=True)
    received: list[Any] = []
    server.subscription("/cmd", String)(received.append)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        w = await open_wire(running)
        publish = {"jsonrpc": "2.0", "method": "$/publish"}
        for n in range(3):
            await w.send({**publish, "params": {"topic": "/cmd", "message": {"data": str(n)}}})
        ack = {**publish, "id": 1, "params": {"topic": "/cmd", "message": {"data": "y"}}}
        assert (await w.call(ack))["result"] is None  # all four handled, in order
        assert (await access.next()).getMessage().split(" ", 1)[1].startswith("$/publish /cmd OK")
        server.remove_topic("/cmd")
        record = await access.next()  # while the connection stays open
        assert re.fullmatch(
            rf"\S+ \$/publish /cmd OK {DURATION} received 3 invalid 0", record.getMessage()
        )
        await w.ws.close()
    assert len(received) == 4 and access.queue.empty()  # no second summary at the close


# --- where the server listens ---------------------------------------------------------------


def ipv6_loopback() -> bool:
    """Whether this machine can listen on ::1."""
    try:
        with socket.socket(socket.AF_INET6) as sock:
            sock.bind(("::1", 0))
    except OSError:
        return False
    return True


async def reachable(url: str) -> bool:
    w = await open_wire(url)
    reply = await w.call(call("subtract", 1, minuend=3, subtrahend=1))
    await w.ws.close()
    return bool(reply["result"] == {"difference": 2})


@pytest.fixture
def plain_server() -> Server:
    server = Server()
    server.add_service("/subtract", Subtract, subtract)
    return server


async def test_a_wildcard_host_lists_the_address_of_every_interface(
    plain_server: Server,
) -> None:
    async with serve(plain_server, "0.0.0.0", 0) as running:
        port = running.port
        addresses = interface_addresses(socket.AF_INET)
        assert running.urls == [f"ws://{a}:{port}" for a in addresses]
        assert running.url == f"ws://127.0.0.1:{port}"  # one to paste, not ws://0.0.0.0
        for url in running.urls:
            assert await reachable(url), url


async def test_listening_on_several_hosts_and_on_every_interface(plain_server: Server) -> None:
    if not ipv6_loopback():  # then the machine cannot listen on ::1, and says so
        with pytest.raises(OSError):
            await serve(plain_server, ["127.0.0.1", "::1"], 0)
        return
    async with serve(plain_server, ["127.0.0.1", "::1"], 0) as running:
        v4, v6 = running.urls
        assert re.fullmatch(r"ws://127\.0\.0\.1:\d+", v4)
        assert re.fullmatch(r"ws://\[::1\]:\d+", v6)
        assert await reachable(v4) and await reachable(v6)
    async with serve(plain_server, None, 0) as running:
        urls = running.urls
        assert urls[0].startswith("ws://127.0.0.1:")
        assert any(url.startswith("ws://[::1]:") for url in urls)
        for url in urls:
            assert await reachable(url), url


async def test_the_memory_transport_listens_on_one_host(plain_server: Server) -> None:
    from srvwire.transports.memory import MemoryTransport

    with pytest.raises(ValueError, match="the memory transport listens on one host name"):
        await serve(plain_server, ["a", "b"], 0, transport=MemoryTransport())


async def test_an_empty_list_of_hosts_is_refused(plain_server: Server) -> None:
    with pytest.raises(ValueError, match="no host to listen on"):
        await serve(plain_server, [], 0)


# --- websockets' own lines ------------------------------------------------------------------


@pytest.fixture
def websockets_level() -> Iterator[logging.Logger]:
    logger = logging.getLogger("websockets.server")
    level = logger.level
    try:
        yield logger
    finally:
        logger.setLevel(level)


async def test_websockets_says_nothing_per_connection_unless_asked(
    plain_server: Server, caplog: pytest.LogCaptureFixture, websockets_level: logging.Logger
) -> None:
    caplog.set_level(logging.INFO)  # as logging.basicConfig(level=logging.INFO) would
    async with serve(plain_server, "127.0.0.1", 0) as running:
        assert await reachable(running.url)
        assert [r for r in caplog.records if r.name.startswith("websockets")] == []
        websockets_level.setLevel(logging.INFO)  # asked for
        assert await reachable(running.url)
    said = [r.getMessage() for r in caplog.records if r.name == "websockets.server"]
    assert "connection open" in said


def test_websockets_warnings_and_errors_always_pass(
    caplog: pytest.LogCaptureFixture, websockets_level: logging.Logger
) -> None:
    quiet = _QuietLogger()
    with caplog.at_level(logging.DEBUG):
        quiet.info("connection open")
        quiet.warning("a warning")
        quiet.error("handler failed")
    assert caplog.messages == ["a warning", "handler failed"]


# --- Server.run(): the startup line ---------------------------------------------------------

SCRIPT = """\
import logging, sys
from srvwire.loader import load_service
from srvwire.server import Server

{configure}
AddTwoInts = load_service("example_interfaces/srv/AddTwoInts")
server = Server(grace_period=0)
server.add_service("/add_two_ints", AddTwoInts, lambda request: {{"sum": 0}})
server.run({host}, 0)
print("returned", logging.getLogger("srvwire").handlers, file=sys.stderr)
"""


def run_script(
    tmp_path: Path, host: str, configure: str = "", *, before: list[str] | None = None
) -> tuple[str, str]:
    """Run a script that calls server.run(); stop it with SIGINT once it has said where it
    listens; return that line and the rest of its standard error. The lines it wrote before
    that one go into ``before``; there must be none unless ``before`` is given."""
    script = tmp_path / "run_app.py"
    script.write_text(SCRIPT.format(host=host, configure=configure), encoding="utf-8")
    process = subprocess.Popen(
        [sys.executable, str(script)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    try:
        assert process.stderr is not None
        first = process.stderr.readline()
        earlier: list[str] = []
        while first and " serving " not in first:
            earlier.append(first)
            first = process.stderr.readline()
        reach = process.stderr.readline()  # who can reach it, said right after
        process.send_signal(signal.SIGINT)
        _, rest = process.communicate(timeout=scaled(10))
        rest = reach + rest
    finally:
        process.kill()
        process.wait()
    assert process.returncode == 0, rest
    if before is None:
        assert earlier == []
    else:
        before.extend(earlier)
    return first, rest


def test_run_says_where_it_listens_when_logging_is_not_configured(tmp_path: Path) -> None:
    before: list[str] = []
    first, rest = run_script(tmp_path, '"0.0.0.0"', before=before)
    # Listening on every address with no authentication is worth a warning, said first.
    assert [line.split(" ", 2)[2] for line in before] == [
        "WARNING srvwire.server: any host that can route to 0.0.0.0 can connect, with no "
        "authentication: anyone who can reach it can call every service (give the Server an "
        "auth=, or listen on 127.0.0.1)\n"
    ]
    match = re.fullmatch(
        r"\S+ \S+ INFO srvwire.server: serving 1 service on (ws://127\.0\.0\.1:(\d+)(, .*)?)\n",
        first,
    )
    assert match, first
    port = match.group(2)
    urls = match.group(1).split(", ")
    assert urls == [f"ws://{a}:{port}" for a in interface_addresses(socket.AF_INET)]
    said = [line.split(" ", 2)[2] for line in rest.splitlines()[:2]]
    assert said == [
        "INFO srvwire.server: any host that can route to 0.0.0.0 can connect; no "
        "authentication; unencrypted",
        "INFO srvwire.server: shutting down",
    ]
    assert rest.splitlines()[-1] == "returned []"  # its handler is gone once run() returns


def test_run_adds_nothing_to_a_configured_logging(tmp_path: Path) -> None:
    configure = 'logging.basicConfig(level=logging.INFO, format="mine: %(message)s")'
    first, rest = run_script(tmp_path, '"127.0.0.1"', configure)
    assert re.fullmatch(r"mine: serving 1 service on ws://127\.0\.0\.1:\d+\n", first), first
    assert rest.splitlines() == [
        "mine: only programs on this machine can connect (loopback); no authentication; "
        "unencrypted",
        "mine: shutting down",
        "returned []",
    ]
