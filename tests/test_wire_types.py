"""Robot data on the wire: non-finite floats a browser can parse, byte arrays as base64, and
messages larger than the size limits, over real connections.

The replies of a server in a browser-safe ``inf_nan`` mode are parsed by Node's ``JSON.parse``,
the parser a browser client uses, so the claim "a browser can read every reply" is checked by
the parser it is about.
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
from collections.abc import AsyncIterator
from typing import Any

import pytest
from websockets.asyncio.server import ServerConnection, serve as ws_serve

import srvwire
from conftest import open_wire
from srvwire import models
from srvwire.loader import InterfaceLoader, bundled_interfaces
from srvwire.models import InfNan
from srvwire.server import RunningServer, Server, serve
from srvwire.transports.base import Transport
from support import DATA, scaled

WIRE_PKGS = DATA / "wire_pkgs"
LOADER = InterfaceLoader([WIRE_PKGS, bundled_interfaces()])
Scan = LOADER.load_service("wire_msgs/srv/Scan")
Capture = LOADER.load_service("wire_msgs/srv/Capture")
NAN, INF = math.nan, math.inf


def node_json_parse(text: str) -> Any:
    """Parse ``text`` with Node's ``JSON.parse``; return what it read, or raise ValueError."""
    node = shutil.which("node")
    if node is None:
        pytest.fail("these tests need Node.js (node), as make test does for wscat", pytrace=False)
    script = (
        'let s = ""; process.stdin.on("data", (d) => (s += d));'
        'process.stdin.on("end", () => {'
        "  try { process.stdout.write(JSON.stringify(JSON.parse(s))); }"
        '  catch (e) { process.stdout.write(e.name + ": " + e.message); process.exitCode = 1; }'
        "});"
    )
    done = subprocess.run(
        [node, "-e", script],
        input=text,
        capture_output=True,
        text=True,
        timeout=scaled(30),
        check=False,
    )
    if done.returncode != 0:
        raise ValueError(done.stdout or done.stderr)
    return json.loads(done.stdout)


async def scan(request: Any) -> Any:
    """Non-finite values in float32/float64 fields, arrays and nested messages."""
    return {
        "reading": {
            "value": request.fill,
            "variance": INF,
            "ranges": request.samples,
            "position": [NAN, 0.5, -INF],
        },
        "history": [{"value": -INF, "ranges": [NAN]}],
        "corners": [INF, -INF],
        "mean": NAN,
    }


def frame_of(width: int, height: int) -> bytes:
    """An RGB frame's pixels: every byte value, over and over."""
    return (bytes(range(256)) * (width * height * 3 // 256 + 1))[: width * height * 3]


async def capture(request: Any) -> Any:
    pixels = request.payload or frame_of(request.width, request.height)
    return Capture.Response(
        frame={
            "height": request.height,
            "width": request.width,
            "encoding": "rgb8",
            "step": request.width * 3,
            "data": pixels,
        }
    )


def wire_server(**options: Any) -> Server:
    server = Server(grace_period=scaled(2), **options)
    server.add_service("/scan", Scan, scan)
    server.add_service("/capture", Capture, capture)
    return server


@pytest.fixture
async def serving(request: pytest.FixtureRequest) -> AsyncIterator[RunningServer]:
    """The server, on WebSockets, with the options the test's parameter gives."""
    async with serve(wire_server(**getattr(request, "param", {})), "127.0.0.1", 0) as running:
        yield running


# --- non-finite floats -----------------------------------------------------------------------

# What a browser sends: it can write the strings and null, not the bare tokens.
BROWSER_CALL = (
    '{"jsonrpc":"2.0","id":7,"method":"/scan",'
    '"params":{"fill":"Infinity","samples":[1.5,"NaN","-Infinity",null]}}'
)
BAD_CALL = '{"jsonrpc":"2.0","id":"x","method":"scan","params":{"fill":"nan"}}'


def expected_result(write: Any) -> dict[str, Any]:
    """The reply to BROWSER_CALL with each non-finite float written by ``write``."""
    nan, inf = write(NAN), write(INF)
    return {
        "reading": {
            "value": inf,
            "variance": inf,
            "ranges": [1.5, nan, write(-INF), nan],  # null is read as nan
            "position": [nan, 0.5, write(-INF)],
        },
        "history": [{"value": write(-INF), "variance": 0, "ranges": [nan], "position": [0, 0, 0]}],
        "corners": [inf, write(-INF)],
        "mean": nan,
    }


def as_string(value: float) -> str:
    return "NaN" if math.isnan(value) else ("Infinity" if value > 0 else "-Infinity")


@pytest.mark.parametrize(
    ("serving", "write"),
    [({}, as_string), ({"inf_nan": "strings"}, as_string), ({"inf_nan": "null"}, lambda v: None)],
    indirect=["serving"],
    ids=["default", "strings", "null"],
)
async def test_a_browser_parses_every_reply_of_a_browser_safe_server(
    serving: RunningServer, write: Any
) -> None:
    wire = await open_wire(serving)
    try:
        await wire.ws.send(BROWSER_CALL)
        reply = node_json_parse(await wire.ws.recv())
        assert reply == {"jsonrpc": "2.0", "id": 7, "result": expected_result(write)}
        await wire.ws.send(f"[{BROWSER_CALL},{BAD_CALL}]")  # a batch, with an error reply
        ok, bad = node_json_parse(await wire.ws.recv())
        assert ok["result"] == expected_result(write)
        assert (bad["id"], bad["error"]["data"]["errors"][0]["path"]) == ("x", "fill")
    finally:
        await wire.ws.close()


@pytest.mark.parametrize("serving", [{"inf_nan": "constants"}], indirect=True)
async def test_a_browser_cannot_parse_the_bare_tokens(serving: RunningServer) -> None:
    wire = await open_wire(serving)
    try:
        await wire.ws.send(BROWSER_CALL)
        text = await wire.ws.recv()
    finally:
        await wire.ws.close()
    assert '"value":Infinity' in text and '"mean":NaN' in text
    with pytest.raises(ValueError, match="SyntaxError"):
        node_json_parse(text)  # the whole reply, id included, is lost to a browser
    assert json.loads(text)["id"] == 7  # Python's json reads the tokens


@pytest.mark.parametrize(
    "serving",
    [{"inf_nan": "strings"}, {"inf_nan": "null"}, {"inf_nan": "constants"}],
    indirect=True,
    ids=["strings", "null", "constants"],
)
async def test_a_srvwire_client_reads_every_mode(serving: RunningServer) -> None:
    lossy = serving.server.registry.inf_nan == "null"
    async with srvwire.connect(serving.url, type_resolver=LOADER.load_service) as client:
        response = await client.call("/scan", Scan.Request(fill=INF, samples=[-INF, NAN, 2.0]))
    assert type(response) is Scan.Response
    reading = response.reading
    assert math.isnan(response.mean)
    assert math.isnan(reading.ranges[1]) and reading.ranges[2] == 2.0
    assert math.isnan(reading.position[0]) and reading.position[1] == 0.5
    if lossy:  # null says only that the value was not finite
        assert all(math.isnan(v) for v in (reading.value, reading.ranges[0], *response.corners))
    else:
        assert (reading.value, reading.variance, reading.ranges[0]) == (INF, INF, -INF)
        assert response.corners == [INF, -INF]
        assert response.history[0].value == -INF


@pytest.mark.parametrize(
    ("mode", "written"),
    [
        ("strings", '"fill":"Infinity","samples":["NaN",-1.5,"-Infinity"]'),
        ("null", '"fill":null,"samples":[null,-1.5,null]'),
        ("constants", '"fill":Infinity,"samples":[NaN,-1.5,-Infinity]'),
    ],
)
async def test_a_client_writes_requests_in_its_own_mode(mode: InfNan, written: str) -> None:
    received: list[str] = []

    async def server(ws: ServerConnection) -> None:
        services = {"services": [{"name": "/scan", "type": "wire_msgs/srv/Scan"}]}
        await ws.send(json.dumps({"jsonrpc": "2.0", "method": "$/services", "params": services}))
        async for message in ws:
            received.append(str(message))
            reply = {"jsonrpc": "2.0", "id": json.loads(message)["id"], "result": {}}
            await ws.send(json.dumps(reply))

    async with ws_serve(server, "127.0.0.1", 0) as raw:
        url = f"ws://127.0.0.1:{raw.sockets[0].getsockname()[1]}"
        options = {"type_resolver": LOADER.load_service, "inf_nan": mode}
        async with srvwire.connect(url, **options) as client:
            request = Scan.Request(fill=INF, samples=[NAN, -1.5, -INF])
            assert await client.call("/scan", request) == Scan.Response()
            assert await client.call("/scan", {"fill": INF, "samples": [NAN, -1.5, -INF]}) == (
                Scan.Response()
            )
    assert len(received) == 2
    for text in received:
        assert written in text


@pytest.mark.parametrize("mode", ["strings", "null", "constants"])
async def test_a_client_and_a_server_in_different_modes_understand_each_other(
    mode: InfNan,
) -> None:
    async with (
        serve(wire_server(inf_nan="constants"), "127.0.0.1", 0) as running,
        srvwire.connect(running.url, type_resolver=LOADER.load_service, inf_nan=mode) as client,
    ):
        response = await client.call("/scan", Scan.Request(fill=-INF, samples=[INF]))
    if mode == "null":  # the server read the client's null as nan
        assert math.isnan(response.reading.value)
    else:
        assert response.reading.value == -INF
    assert response.reading.variance == INF  # written by the server in its own mode


def test_the_modes_are_checked() -> None:
    with pytest.raises(ValueError, match="inf_nan must be one of strings, null, constants"):
        Server(inf_nan="NaN")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="inf_nan must be one of strings, null, constants"):
        srvwire.connect(inf_nan="none")  # type: ignore[arg-type]


# --- bytes and large messages ----------------------------------------------------------------

MIB = 2**20


async def test_a_frame_travels_as_bytes_and_base64(transport: Transport) -> None:
    async with (
        serve(wire_server(), "127.0.0.1", 0, transport=transport) as running,
        srvwire.connect(
            running.url, transport=transport, type_resolver=LOADER.load_service
        ) as client,
    ):
        # 320 x 240 RGB: 230 400 bytes, 307 200 as base64; well inside the default 1 MiB.
        response = await client.call("/capture", {"width": 320, "height": 240})
        assert response.frame.data == frame_of(320, 240)
        assert type(response.frame.data) is bytes
        echoed = await client.call("/capture", Capture.Request(width=2, height=1, payload=[1, 2]))
        assert echoed.frame.data == b"\x01\x02"
        wire = await open_wire(running)
        try:
            reply = await wire.call(
                {"jsonrpc": "2.0", "id": 1, "method": "capture", "params": {"payload": "AAH/"}}
            )
        finally:
            await wire.ws.close()
        assert reply["result"]["frame"]["data"] == "AAH/"  # base64 text, as rosbridge writes it


async def test_a_reply_over_the_clients_limit_names_the_clients_setting(
    transport: Transport,
) -> None:
    # 640 x 480 RGB: 921 600 bytes, 1 228 800 as base64: over the default 1 MiB.
    async with (
        serve(wire_server(), "127.0.0.1", 0, transport=transport) as running,
        srvwire.connect(
            running.url, transport=transport, type_resolver=LOADER.load_service
        ) as client,
    ):
        with pytest.raises(srvwire.ConnectionLost) as lost:
            await client.call("/capture", {"width": 640, "height": 480})
    message = str(lost.value)
    assert lost.value.data["close_code"] == 1009
    assert "over the client's max_message_size" in message
    assert f"{MIB} bytes" in message


async def test_a_request_over_the_servers_limit_names_the_servers_setting(
    transport: Transport,
) -> None:
    async with (
        serve(wire_server(), "127.0.0.1", 0, transport=transport) as running,
        srvwire.connect(
            running.url,
            transport=transport,
            type_resolver=LOADER.load_service,
            max_message_size=8 * MIB,
        ) as client,
    ):
        with pytest.raises(srvwire.ConnectionLost) as lost:
            await client.call("/capture", {"payload": bytes(MIB)})
    assert lost.value.data["close_code"] == 1009
    assert "over the server's max_message_size" in str(lost.value)
    assert f"{MIB} bytes" in str(lost.value)


async def test_the_client_refuses_an_oversize_request_and_carries_on(
    transport: Transport,
) -> None:
    async with (
        serve(wire_server(), "127.0.0.1", 0, transport=transport) as running,
        srvwire.connect(
            running.url, transport=transport, type_resolver=LOADER.load_service
        ) as client,
    ):
        with pytest.raises(srvwire.ResourceExhausted) as refused:
            await client.call("/capture", {"payload": frame_of(640, 480)})
        size = refused.value.data["size"]
        assert size > 921_600 * 4 // 3  # the base64 text and the envelope
        assert refused.value.data["max_message_size"] == MIB
        assert str(refused.value) == (
            f"RESOURCE_EXHAUSTED (-32004) [/capture]: the request is {size} bytes, "
            f"over max_message_size={MIB}; nothing was sent (raise max_message_size on the "
            "client and on the server for larger messages)"
        )
        small = await client.call("/capture", {"width": 1, "height": 1})  # the connection lives
        assert small.frame.data == b"\x00\x01\x02"


async def test_raised_limits_on_both_sides_carry_a_vga_frame(transport: Transport) -> None:
    pixels = frame_of(640, 480)
    async with (
        serve(
            wire_server(max_message_size=4 * MIB), "127.0.0.1", 0, transport=transport
        ) as running,
        srvwire.connect(
            running.url,
            transport=transport,
            type_resolver=LOADER.load_service,
            max_message_size=4 * MIB,
        ) as client,
    ):
        response = await client.call(
            "/capture", Capture.Request(width=640, height=480, payload=pixels)
        )
    assert response.frame.data == pixels
    assert (response.frame.width, response.frame.step, len(response.frame.data)) == (
        640,
        1920,
        921_600,
    )


async def test_a_mode_builds_its_serializers_once_not_per_call(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    built: list[Any] = []
    real = models.SchemaSerializer

    def counting(*args: Any, **kwargs: Any) -> Any:
        built.append(args)
        return real(*args, **kwargs)

    monkeypatch.setattr(models, "SchemaSerializer", counting)
    server = wire_server(inf_nan="null")
    # two per service: the writers of its response and of its whole reply, in this mode
    assert len(built) == 4
    async with (
        serve(server, "127.0.0.1", 0) as running,
        srvwire.connect(running.url, type_resolver=LOADER.load_service, inf_nan="null") as client,
    ):
        for _ in range(3):
            response = await client.call("/scan", Scan.Request(fill=INF))
            assert math.isnan(response.reading.value)
    assert len(built) == 5  # and one for the client's Scan requests, when it first met Scan
