"""The server's edge, over real sockets: origins and Host, tokens, scopes, TLS, the connection
cap, the health check, and the client's own care with credentials."""

from __future__ import annotations

import asyncio
import base64
import contextlib
import errno
import json
import logging
import ssl
import threading
import time
from collections.abc import AsyncIterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import pytest
import trustme
from websockets.asyncio.client import connect as ws_connect
from websockets.exceptions import InvalidStatus

from conftest import Subtract, make_transport, subtract
from srvwire import (
    Context,
    Identity,
    PermissionDenied,
    Server,
    ServiceUnavailable,
    TokenAuth,
    Unauthenticated,
    connect,
    serve,
)
from srvwire.auth import bearer_subprotocol
from srvwire.handshake import NOT_WEBSOCKET
from srvwire.inline import Pending, finish, first_step
from srvwire.server import RunningServer
from srvwire.transports import picows as picows_transport
from srvwire.transports.base import Handshake
from support import scaled

TOKEN = "s3cret-token"
READER_TOKEN = "reader-token"
NO_CREDENTIALS = (
    "no credentials: send the header 'Authorization: Bearer <token>', or offer the "
    "subprotocols 'srvwire.v1' and 'srvwire.bearer.<base64url of the token>'"
)
EVIL_ORIGIN = (
    "Origin https://evil.example is not allowed: a page from another site may not connect; "
    "list it in the origins (srvwire serve --origin ORIGIN) to allow it\n"
)
NULL_ORIGIN = (
    "Origin null (a file:// page or a sandboxed frame) is not allowed; "
    "list 'null' in the origins to allow it\n"
)


def rebinding_host(port: int) -> str:
    return (
        f"Host 'evil.example:{port}' is not a name of this server: it listens on loopback, "
        "whose names are localhost, 127.0.0.1 and [::1]; a page can point any DNS "
        "name at 127.0.0.1. List an origin with that host to allow it\n"
    )


class Robot:
    """Two services: ``/add`` for anyone who may connect, ``/arm`` for ``robot:write``."""

    def __init__(self, **options: Any) -> None:
        self.calls: list[tuple[str, Any]] = []
        self.server = Server(grace_period=scaled(2), **options)

        @self.server.service("/add", Subtract)
        def add(request: Any, context: Context) -> Any:
            self.calls.append(("/add", context.identity))
            return subtract(request)

        @self.server.service("/arm", Subtract, scopes={"robot:write"})
        def arm(request: Any, context: Context) -> Any:
            self.calls.append(("/arm", context.identity))
            return subtract(request)


TOKENS = TokenAuth(
    {TOKEN: Identity("operator", {"robot:write"}), READER_TOKEN: "reader"},
)


@pytest.fixture(params=["websockets", "picows"])
def edge(request: pytest.FixtureRequest) -> str:
    """Each WebSocket transport: both carry out the edge policy at the upgrade."""
    return str(request.param)


@pytest.fixture
async def open_robot(edge: str) -> AsyncIterator[tuple[Robot, RunningServer]]:
    robot = Robot()
    async with serve(robot.server, "127.0.0.1", 0, transport=edge) as running:
        yield robot, running


@pytest.fixture
async def authed_robot(edge: str) -> AsyncIterator[tuple[Robot, RunningServer]]:
    robot = Robot(auth=TOKENS)
    async with serve(robot.server, "127.0.0.1", 0, transport=edge) as running:
        yield robot, running


async def http(
    port: int,
    path: str = "/",
    headers: dict[str, str] | None = None,
    *,
    upgrade: bool = True,
    context: ssl.SSLContext | None = None,
) -> tuple[int, dict[str, str], str]:
    """Send one raw HTTP/1.1 GET (a WebSocket upgrade unless told not to); return the status,
    the headers (names in lower case) and the body of the answer."""
    sent = {"Host": f"127.0.0.1:{port}"}
    if upgrade:
        sent |= {
            "Upgrade": "websocket",
            "Connection": "Upgrade",
            "Sec-WebSocket-Key": base64.b64encode(b"0123456789abcdef").decode(),
            "Sec-WebSocket-Version": "13",
        }
    sent |= headers or {}
    reader, writer = await asyncio.open_connection(
        "127.0.0.1", port, ssl=context, server_hostname="localhost" if context else None
    )
    try:
        request = f"GET {path} HTTP/1.1\r\n" + "".join(f"{k}: {v}\r\n" for k, v in sent.items())
        writer.write(request.encode() + b"\r\n")
        head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), scaled(5))
        lines = head.decode().split("\r\n")
        status = int(lines[0].split()[1])
        answer = {}
        for line in lines[1:]:
            if line:
                name, _, value = line.partition(":")
                answer[name.strip().lower()] = value.strip()
        body = b""
        if "content-length" in answer:
            body = await reader.readexactly(int(answer["content-length"]))
        return status, answer, body.decode()
    finally:
        writer.close()


# --- origins and Host -----------------------------------------------------------------------


@pytest.mark.parametrize(
    ("headers", "expected"),
    [
        ({"Origin": "https://evil.example"}, lambda port: EVIL_ORIGIN),
        ({"Origin": "null"}, lambda port: NULL_ORIGIN),
        (
            {"Host": "evil.example:{port}", "Origin": "http://evil.example:{port}"},
            rebinding_host,
        ),
        ({"Host": "evil.example:{port}"}, rebinding_host),
    ],
    ids=["evil-origin", "null-origin", "rebinding", "rebinding-no-origin"],
)
async def test_hostile_handshakes_are_refused_before_the_upgrade(
    open_robot: tuple[Robot, RunningServer], headers: dict[str, str], expected: Any
) -> None:
    robot, running = open_robot
    port = running.port
    sent = {key: value.format(port=port) for key, value in headers.items()}
    status, answer, body = await http(port, headers=sent)
    assert (status, body) == (403, expected(port))
    assert "sec-websocket-accept" not in answer
    assert robot.calls == [] and running._connections == set()


async def test_a_hostile_page_cannot_call_even_through_the_websockets_client(
    open_robot: tuple[Robot, RunningServer],
) -> None:
    robot, running = open_robot
    with pytest.raises(InvalidStatus) as refused:
        async with ws_connect(running.url, origin="https://evil.example"):  # type: ignore[arg-type]
            pass
    assert refused.value.response.status_code == 403
    assert refused.value.response.body.decode() == EVIL_ORIGIN
    assert robot.calls == []


@pytest.mark.parametrize("host", ["127.0.0.1", "localhost"])
async def test_a_page_of_the_server_itself_is_served(
    open_robot: tuple[Robot, RunningServer], host: str
) -> None:
    robot, running = open_robot
    url = f"ws://{host}:{running.port}"
    origin = f"http://{host}:{running.port}"
    async with ws_connect(url, origin=origin) as ws:  # type: ignore[arg-type]
        first = json.loads(await ws.recv())
        assert [s["name"] for s in first["params"]["services"]] == ["/add"]
        await ws.send('{"jsonrpc":"2.0","id":1,"method":"/add","params":[5,3]}')
        assert json.loads(await ws.recv())["result"] == {"difference": 2}
    assert robot.calls == [("/add", None)]


async def test_listed_origins_are_served_and_name_the_server(edge: str) -> None:
    robot = Robot(origins=["https://app.example", "null"])
    async with serve(robot.server, "127.0.0.1", 0, transport=edge) as running:
        port = running.port
        status, _, _ = await http(port, headers={"Origin": "https://app.example"})
        assert status == 101
        status, _, _ = await http(port, headers={"Origin": "null"})
        assert status == 101
        # A proxy in front passes its own Host: a listed origin's host is a name of the server.
        status, _, _ = await http(
            port, headers={"Host": "app.example", "Origin": "https://app.example"}
        )
        assert status == 101
        status, _, body = await http(port, headers={"Origin": "https://evil.example"})
        assert (status, body) == (403, EVIL_ORIGIN)


async def test_star_allows_every_origin_and_host(edge: str) -> None:
    robot = Robot(origins=["*"])
    async with serve(robot.server, "127.0.0.1", 0, transport=edge) as running:
        status, _, _ = await http(
            running.port, headers={"Host": "evil.example", "Origin": "https://evil.example"}
        )
        assert status == 101


def test_a_bad_origin_is_refused_when_the_server_is_made() -> None:
    with pytest.raises(ValueError) as exc:
        Server(origins=["app.example"])
    assert str(exc.value) == (
        "not an origin: 'app.example'; write scheme://host[:port], such as "
        "https://app.example.com, or 'null', or '*'"
    )


# --- tokens ---------------------------------------------------------------------------------


async def test_a_client_without_a_token_is_refused_with_401(
    authed_robot: tuple[Robot, RunningServer],
) -> None:
    robot, running = authed_robot
    status, answer, body = await http(running.port)
    assert (status, body) == (401, NO_CREDENTIALS + "\n")
    assert answer["www-authenticate"] == "Bearer"
    with pytest.raises(ServiceUnavailable) as exc:
        await connect(running.url, transport=running.transport, timeout=scaled(5))
    assert exc.value.message == (
        f"cannot connect to {running.url}: the server refused the connection: HTTP 401: "
        + NO_CREDENTIALS
    )
    assert robot.calls == []


async def test_a_wrong_token_is_refused_and_never_logged(
    authed_robot: tuple[Robot, RunningServer], caplog: pytest.LogCaptureFixture
) -> None:
    robot, running = authed_robot
    caplog.set_level(logging.DEBUG)
    with pytest.raises(ServiceUnavailable) as exc:
        await connect(running.url, transport=running.transport, token="guess", timeout=scaled(5))
    assert exc.value.message == (
        f"cannot connect to {running.url}: the server refused the connection: HTTP 401: "
        "the token is not valid"
    )
    status, _, body = await http(running.port, headers={"Authorization": "Basic Zm9vOmJhcg=="})
    assert (status, body) == (401, "the Authorization header is not 'Bearer <token>'\n")
    assert "refused a connection" in caplog.text
    assert "guess" not in caplog.text and "Zm9vOmJhcg" not in caplog.text
    assert robot.calls == []


async def test_a_client_knocking_in_a_loop_gets_no_log_line_per_knock(
    authed_robot: tuple[Robot, RunningServer], caplog: pytest.LogCaptureFixture
) -> None:
    # srvwire logs refusals at most once a second; the transport adds no line of its own per
    # connection (picows logs each connection accepted and each disconnected at INFO).
    robot, running = authed_robot
    caplog.set_level(logging.INFO)
    for _ in range(20):
        status, _, _ = await http(running.port, headers={"Authorization": "Bearer guess"})
        assert status == 401
    lines = [(r.name, r.getMessage()) for r in caplog.records]
    assert lines and all(message.startswith("refused a connection from") for _, message in lines), (
        lines
    )
    assert robot.calls == []


async def send_a_frame_of_an_unknown_opcode(port: int) -> None:
    """Open a WebSocket by hand, send a masked frame of opcode 0x3 (reserved: the server must
    fail the connection), and read until the server closes."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        key = base64.b64encode(b"0123456789abcdef").decode()
        writer.write(
            f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\n"
            f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
            "Sec-WebSocket-Version: 13\r\n\r\n".encode()
        )
        head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), scaled(5))
        assert head.startswith(b"HTTP/1.1 101"), head
        writer.write(bytes((0x83, 0x80)) + b"\0\0\0\0")  # final, opcode 0x3, masked, empty
        await asyncio.wait_for(reader.read(), scaled(5))  # to the server's close
    finally:
        writer.close()


@pytest.mark.parametrize("name", ["websockets", "picows"])
async def test_a_client_breaking_the_protocol_in_a_loop_gets_no_log_line_each_time(
    name: str, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    # picows logs an error for each frame its parser refuses; srvwire lets one through per
    # interval and counts the rest into the next (an interval of an hour here: exactly one
    # line for the loop, whatever the machine's pace; then none, for the count).
    caplog.set_level(logging.INFO)
    monkeypatch.setattr(picows_transport, "PEER_LOG_INTERVAL", 3600.0)
    async with serve(Server(), "127.0.0.1", 0, transport=make_transport(name)) as running:
        for _ in range(20):
            await send_a_frame_of_an_unknown_opcode(running.port)
        lines = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
        if name == "websockets":
            assert lines == []
            return
        assert len(lines) == 1 and "WS parser error" in lines[0], lines
        caplog.clear()
        monkeypatch.setattr(picows_transport, "PEER_LOG_INTERVAL", 0.0)
        await send_a_frame_of_an_unknown_opcode(running.port)
        lines = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
        assert len(lines) == 1, lines
        assert lines[0].endswith("(19 more warnings or errors since the last line)"), lines


async def test_the_right_token_reaches_the_handler_as_an_identity(
    authed_robot: tuple[Robot, RunningServer],
) -> None:
    robot, running = authed_robot
    async with connect(
        running.url, transport=running.transport, token=TOKEN, timeout=scaled(5)
    ) as client:
        assert (await client.call("/arm", {"minuend": 5, "subtrahend": 3})).difference == 2
    assert robot.calls == [("/arm", Identity("operator", {"robot:write"}))]


async def test_a_raw_client_sends_the_token_as_a_header(
    authed_robot: tuple[Robot, RunningServer],
) -> None:
    robot, running = authed_robot
    headers = {"Authorization": f"Bearer {READER_TOKEN}"}
    async with ws_connect(running.url, additional_headers=headers) as ws:
        first = json.loads(await ws.recv())
        assert first["method"] == "$/services"
        await ws.send('{"jsonrpc":"2.0","id":1,"method":"/add","params":[1,1]}')
        assert json.loads(await ws.recv())["result"] == {"difference": 0}
    assert robot.calls == [("/add", Identity("reader"))]


async def test_a_browser_sends_the_token_as_a_subprotocol_which_is_never_echoed(
    authed_robot: tuple[Robot, RunningServer],
) -> None:
    robot, running = authed_robot
    offered = ["srvwire.v1", bearer_subprotocol(TOKEN)]
    assert offered[1] == "srvwire.bearer." + base64.urlsafe_b64encode(
        TOKEN.encode()
    ).decode().rstrip("=")
    async with ws_connect(
        running.url,
        subprotocols=offered,  # type: ignore[arg-type]
        origin=f"http://127.0.0.1:{running.port}",  # type: ignore[arg-type]
    ) as ws:
        assert ws.subprotocol == "srvwire.v1"
        assert ws.response is not None
        assert ws.response.headers["Sec-WebSocket-Protocol"] == "srvwire.v1"
        await ws.recv()
        await ws.send('{"jsonrpc":"2.0","id":1,"method":"/arm","params":[9,1]}')
        assert json.loads(await ws.recv())["result"] == {"difference": 8}
    assert robot.calls == [("/arm", Identity("operator", {"robot:write"}))]
    status, _, body = await http(
        running.port, headers={"Sec-WebSocket-Protocol": "srvwire.v1, srvwire.bearer.%%%"}
    )
    assert (status, body) == (
        401,
        "the srvwire.bearer.* subprotocol does not hold base64url UTF-8 text\n",
    )


async def test_a_token_lookup_function_and_the_query_string_when_asked(edge: str) -> None:
    async def lookup(token: str) -> Identity | None:
        return Identity("from-query") if token == "q" else None

    robot = Robot(auth=TokenAuth(lookup, query_parameter="access_token"))
    async with serve(robot.server, "127.0.0.1", 0, transport=edge) as running:
        async with ws_connect(running.url + "/?access_token=q") as ws:
            await ws.recv()
            await ws.send('{"jsonrpc":"2.0","id":1,"method":"/add","params":[1,1]}')
            await ws.recv()
        status, _, _ = await http(running.port, "/?access_token=nope")
        assert status == 401
    assert robot.calls == [("/add", Identity("from-query"))]


def test_tokens_never_show_in_a_repr() -> None:
    handshake = Handshake(headers=[("Authorization", f"Bearer {TOKEN}"), ("Host", "x")])
    options = connect("ws://localhost:1", token=TOKEN)
    for shown in (repr(TOKENS), repr(handshake), repr(options), repr(options.headers)):
        assert TOKEN not in shown
    assert repr(TOKENS) == "<TokenAuth with 2 tokens>"
    assert "('Authorization', '<hidden>')" in repr(handshake)
    assert repr(options.headers) == "[('Authorization', '<hidden>')]"
    query = Handshake(path=f"/?access_token={TOKEN}")
    assert repr(query).startswith("Handshake(GET '/', ")


@pytest.mark.parametrize("url", ["ws://robot.example:8765", "ws://10.0.0.7:8765"])
def test_the_client_keeps_a_token_off_plain_ws_to_another_host(url: str) -> None:
    host = url.split("//")[1].split(":")[0]
    with pytest.raises(ValueError) as exc:
        connect(url, token=TOKEN)
    assert str(exc.value) == (
        f"refusing to send credentials over plain ws:// to {host}, where anyone on the way "
        "can read them: use wss://, or pass allow_plaintext_token=True"
    )
    with pytest.raises(ValueError):
        connect(url, headers={"authorization": "Bearer x"})
    connect(url, token=TOKEN, allow_plaintext_token=True)
    connect(url.replace("ws:", "wss:"), token=TOKEN)
    connect("ws://localhost:8765", token=TOKEN)
    connect("ws://[::1]:8765", token=TOKEN)


# --- scopes ---------------------------------------------------------------------------------


async def test_a_call_without_the_scope_is_denied_before_validation(
    authed_robot: tuple[Robot, RunningServer],
) -> None:
    robot, running = authed_robot
    async with connect(
        running.url, transport=running.transport, token=READER_TOKEN, timeout=scaled(5)
    ) as client:
        assert dict(client.services) == {"/add": "srvwire_tests/srv/Subtract"}
        assert [info.name for info in await client.list_services()] == ["/add"]
        with pytest.raises(PermissionDenied) as exc:
            await client.call("/arm", {"minuend": "not a number"})
    assert str(exc.value) == (
        "PERMISSION_DENIED (-32006) [/arm]: permission denied: /arm needs the scope "
        "robot:write, which this connection's identity does not hold"
    )
    assert exc.value.data == {"missing_scopes": ["robot:write"]}
    assert robot.calls == []


async def test_an_identity_with_the_scope_sees_and_calls_everything(
    authed_robot: tuple[Robot, RunningServer],
) -> None:
    _, running = authed_robot
    async with connect(
        running.url, transport=running.transport, token=TOKEN, timeout=scaled(5)
    ) as client:
        assert sorted(client.services) == ["/add", "/arm"]
        assert [info.name for info in await client.list_services()] == ["/add", "/arm"]


async def test_a_scoped_service_is_hidden_without_authentication(
    open_robot: tuple[Robot, RunningServer],
) -> None:
    _, running = open_robot
    async with connect(running.url, transport=running.transport, timeout=scaled(5)) as client:
        assert list(client.services) == ["/add"]
        with pytest.raises(PermissionDenied):
            await client.call("/arm", {"minuend": 1, "subtrahend": 1})


async def test_expired_credentials_are_answered_unauthenticated(edge: str) -> None:
    robot = Robot(
        auth=TokenAuth(
            {
                "old": Identity("late", {"robot:write"}, expires=time.time() - 1),
                "new": Identity("fresh", expires=time.time() + 3600),
            }
        )
    )
    async with serve(robot.server, "127.0.0.1", 0, transport=edge) as running:
        async with connect(
            running.url, transport=running.transport, token="old", timeout=scaled(5)
        ) as client:
            with pytest.raises(Unauthenticated) as exc:
                await client.call("/add", {"minuend": 1, "subtrahend": 1})
        async with connect(
            running.url, transport=running.transport, token="new", timeout=scaled(5)
        ) as client:
            await client.call("/add", {"minuend": 1, "subtrahend": 1})
    assert str(exc.value) == (
        "UNAUTHENTICATED (-32005) [/add]: the credentials of this connection expired; "
        "reconnect with fresh ones"
    )
    assert robot.calls == [("/add", Identity("fresh", expires=robot.calls[0][1].expires))]


async def test_the_memory_transport_carries_the_token_for_tests_of_scoped_services() -> None:
    robot = Robot(auth=TOKENS)
    transport = make_transport("memory")
    async with serve(robot.server, "localhost", 0, transport=transport) as running:
        async with connect(running.url, transport=transport, token=TOKEN) as client:
            await client.call("/arm", {"minuend": 2, "subtrahend": 1})
        with pytest.raises(ServiceUnavailable) as exc:
            await connect(running.url, transport=transport, token="nope")
    assert exc.value.message == (
        f"cannot connect to {running.url}: the server refused the connection: HTTP 401: "
        "the token is not valid"
    )
    assert robot.calls == [("/arm", Identity("operator", {"robot:write"}))]


# --- TLS ------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def ca() -> trustme.CA:
    return trustme.CA()


def server_context(ca: trustme.CA, *, client_ca: trustme.CA | None = None) -> ssl.SSLContext:
    context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    ca.issue_cert("localhost", "127.0.0.1").configure_cert(context)
    if client_ca is not None:
        context.verify_mode = ssl.CERT_REQUIRED
        client_ca.configure_trust(context)
    return context


async def test_a_silent_connection_to_a_picows_tls_listener_ends_at_the_handshake_timeout(
    ca: trustme.CA, monkeypatch: pytest.MonkeyPatch
) -> None:
    # picows' own handshake timeout starts once the TLS handshake is done, for which asyncio
    # waits 60 s by default: the listener gives the TLS handshake the same timeout. Made
    # short here, so that the 60 s, were they still there, would stand out.
    monkeypatch.setattr(picows_transport, "HANDSHAKE_TIMEOUT", 0.2)
    async with serve(
        Robot().server, "localhost", 0, transport="picows", ssl=server_context(ca)
    ) as running:
        reader, writer = await asyncio.open_connection("127.0.0.1", running.port)
        try:
            with contextlib.suppress(ConnectionResetError):  # asyncio aborts it
                assert await asyncio.wait_for(reader.read(), 30) == b""
        finally:
            writer.close()


async def test_tls_round_trip_with_a_ca_file(ca: trustme.CA, tmp_path: Path, edge: str) -> None:
    robot = Robot()
    cafile = tmp_path / "ca.pem"
    ca.cert_pem.write_to_path(str(cafile))
    async with serve(
        robot.server, "localhost", 0, transport=edge, ssl=server_context(ca)
    ) as running:
        assert running.url.startswith("wss://localhost:")
        assert running.reach == (
            "only programs on this machine can connect (loopback); no authentication; over TLS"
        )
        async with connect(
            running.url, transport=running.transport, ssl=cafile, timeout=scaled(5)
        ) as client:
            assert (await client.call("/add", {"minuend": 3, "subtrahend": 1})).difference == 2
        with pytest.raises(ServiceUnavailable) as exc:
            await connect(running.url, transport=running.transport, timeout=scaled(5))
        assert exc.value.message.startswith(
            f"cannot connect to {running.url}: the server's TLS certificate is not trusted: "
        )
        with pytest.raises(ServiceUnavailable) as plain:
            await connect(
                running.url.replace("wss:", "ws:"), transport=running.transport, timeout=scaled(5)
            )
        assert "it may speak TLS (try wss://)" in plain.value.message
        status, _, body = await http(
            running.port, "/healthz", upgrade=False, context=ssl_client(ca)
        )
        assert (status, body) == (200, "ok\n")


def ssl_client(ca: trustme.CA) -> ssl.SSLContext:
    context = ssl.create_default_context()
    ca.configure_trust(context)
    return context


async def test_wss_to_a_plain_server_says_it_may_not_speak_tls(
    open_robot: tuple[Robot, RunningServer],
) -> None:
    _, running = open_robot
    url = running.url.replace("ws:", "wss:")
    with pytest.raises(ServiceUnavailable) as exc:
        await connect(url, transport=running.transport, timeout=scaled(5))
    assert exc.value.message.startswith(
        f"cannot connect to {url}: the TLS handshake failed; the server may not speak TLS "
        "(try ws://): "
    )


class _WebPage(BaseHTTPRequestHandler):
    """A plain web server's answer to any GET, in HTTP/1.0 (http.server's default)."""

    def do_GET(self) -> None:
        body = b"<html>a web page</html>"
        self.send_response(200)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, format: str, *args: Any) -> None:
        pass  # not on the test's stderr


async def test_a_plain_web_server_is_not_taken_for_a_tls_one(edge: str) -> None:
    web = ThreadingHTTPServer(("127.0.0.1", 0), _WebPage)
    thread = threading.Thread(target=web.serve_forever, daemon=True)
    thread.start()
    url = f"ws://127.0.0.1:{web.server_address[1]}"
    try:
        with pytest.raises(ServiceUnavailable) as exc:
            await connect(url, transport=edge, timeout=scaled(5))
    finally:
        web.shutdown()
        web.server_close()
        thread.join()
    message = exc.value.message
    assert message.startswith(
        f"cannot connect to {url}: the server did not answer as a WebSocket server does ("
    ), message
    assert message.endswith("); is a srvwire server at this address?"), message
    assert "1.0" in message  # what it answered with
    assert "TLS" not in message


async def test_mutual_tls_makes_the_certificate_subject_the_identity(
    ca: trustme.CA, edge: str
) -> None:
    clients = trustme.CA()
    robot = Robot()
    context = server_context(ca, client_ca=clients)
    async with serve(robot.server, "localhost", 0, transport=edge, ssl=context) as running:
        assert running.reach == (
            "only programs on this machine can connect (loopback); callers must authenticate; "
            "over TLS"
        )
        mine = ssl_client(ca)
        clients.issue_cert(
            "operator@robot.example",
            common_name="operator",
            organization_name="Lab",
            organization_unit_name="Robots",
        ).configure_cert(mine)
        async with connect(
            running.url, transport=running.transport, ssl=mine, timeout=scaled(5)
        ) as client:
            await client.call("/add", {"minuend": 3, "subtrahend": 1})
        with pytest.raises(ServiceUnavailable):  # no client certificate: no TLS session
            await connect(
                running.url, transport=running.transport, ssl=ssl_client(ca), timeout=scaled(5)
            )
    assert robot.calls == [("/add", Identity("O=Lab,OU=Robots,CN=operator"))]


# --- the connection cap, health, and plain HTTP ---------------------------------------------


async def test_past_max_connections_the_handshake_is_503_and_the_others_carry_on(edge: str) -> None:
    robot = Robot(max_connections=1)
    async with serve(robot.server, "127.0.0.1", 0, transport=edge) as running:
        async with connect(running.url, transport=running.transport, timeout=scaled(5)) as first:
            status, answer, body = await http(running.port)
            assert (status, body) == (
                503,
                "too many connections (the limit is 1); try again later\n",
            )
            assert answer["retry-after"] == "5"
            assert (await first.call("/add", {"minuend": 2, "subtrahend": 1})).difference == 1
        # The first one left: there is room again.
        async with connect(running.url, transport=running.transport, timeout=scaled(5)) as second:
            await second.call("/add", {"minuend": 2, "subtrahend": 1})


async def test_healthz_while_serving_and_while_draining(edge: str) -> None:
    release = asyncio.Event()
    entered = asyncio.Event()
    server = Server(grace_period=scaled(5))

    @server.service("/slow", Subtract)
    async def slow(request: Any) -> Any:
        entered.set()
        await release.wait()
        return subtract(request)

    running = await serve(server, "127.0.0.1", 0, transport=edge)
    async with connect(running.url, transport=running.transport, timeout=scaled(10)) as client:
        status, _, body = await http(running.port, "/healthz", upgrade=False)
        assert (status, body) == (200, "ok\n")
        call = asyncio.create_task(client.call("/slow", {"minuend": 1, "subtrahend": 1}))
        await entered.wait()
        closing = first_step(running.close())  # shutdown's first step: draining
        assert isinstance(closing, Pending)
        status, _, body = await http(running.port, "/healthz", upgrade=False)
        assert (status, body) == (503, "draining\n")
        status, answer, body = await http(running.port)
        assert (status, body, answer["retry-after"]) == (
            503,
            "the server is shutting down\n",
            "5",
        )
        release.set()
        assert (await call).difference == 0
        await finish(closing)


async def test_a_plain_get_says_what_the_port_is(open_robot: tuple[Robot, RunningServer]) -> None:
    _, running = open_robot
    status, answer, body = await http(running.port, "/", upgrade=False)
    assert (status, body) == (426, NOT_WEBSOCKET)
    assert answer["upgrade"] == "websocket"
    assert body == (
        "This is a srvwire server: JSON-RPC 2.0 services over WebSocket. Connect with a "
        "WebSocket client to this URL (for example: srvwire service list --url ws://HOST:PORT, "
        "or wscat -c ws://HOST:PORT). GET /healthz tells whether it is serving.\n"
    )


async def test_running_out_of_file_descriptors_is_said_once_per_interval(
    caplog: pytest.LogCaptureFixture,
) -> None:
    loop = asyncio.get_running_loop()
    passed_on: list[str] = []

    def previous(_: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
        passed_on.append(context["message"])

    loop.set_exception_handler(previous)
    emfile = OSError(errno.EMFILE, "Too many open files")
    try:
        async with serve(Robot().server, "127.0.0.1", 0):
            # What asyncio's accept loop reports, each time it retries the accept.
            for _ in range(50):
                loop.call_exception_handler(
                    {"message": "socket.accept() out of system resource", "exception": emfile}
                )
            loop.call_exception_handler({"message": "something else"})
        assert loop.get_exception_handler() is previous
    finally:
        loop.set_exception_handler(None)
    said = [r.getMessage() for r in caplog.records if "cannot accept" in r.getMessage()]
    assert said == [
        "cannot accept new connections: [Errno 24] Too many open files (0 connections open; "
        "1 failed accepts since the last line, said at most every 10 s); raise the limit of "
        "open files (ulimit -n) or lower max_connections"
    ]
    assert passed_on == ["something else"]


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"max_connections": 0}, "max_connections must be at least 1, not 0"),
        (
            {"auth": "s3cret"},
            "auth must be an authenticator, such as TokenAuth({token: identity}), not a str",
        ),
    ],
)
def test_bad_edge_options_are_refused(options: dict[str, Any], message: str) -> None:
    with pytest.raises((ValueError, TypeError)) as exc:
        Server(**options)
    assert str(exc.value) == message


async def test_serving_a_public_address_without_authentication_warns(
    caplog: pytest.LogCaptureFixture,
) -> None:
    async with serve(Robot().server, "0.0.0.0", 0):
        pass
    async with serve(Robot(auth=TOKENS).server, "0.0.0.0", 0):
        pass
    async with serve(Robot().server, "127.0.0.1", 0):
        pass
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert warned == [
        "any host that can route to 0.0.0.0 can connect, with no authentication: anyone who "
        "can reach it can call every service (give the Server an auth=, or listen on "
        "127.0.0.1)"
    ]


async def test_credentials_that_expire_mid_connection_end_its_calls(
    caplog: pytest.LogCaptureFixture, edge: str
) -> None:
    caplog.set_level(logging.INFO)
    robot = Robot(auth=TokenAuth({"t": Identity("op", expires=time.time() + 3600)}))
    async with serve(robot.server, "127.0.0.1", 0, transport=edge) as running:
        async with connect(
            running.url, transport=running.transport, token="t", timeout=scaled(5)
        ) as client:
            await client.call("/add", {"minuend": 1, "subtrahend": 1})
            (served,) = running._connections
            assert served.expiry is not None
            loop = asyncio.get_running_loop()
            assert 3500 < served.expiry.when() - loop.time() <= 3600  # armed for that moment
            served.expiry.cancel()
            served.expire()  # what the timer does when the hour is up
            with pytest.raises(Unauthenticated):
                await client.call("/add", {"minuend": 1, "subtrahend": 1})
    assert len(robot.calls) == 1
    assert "the credentials of the connection from ('127.0.0.1', " in caplog.text
