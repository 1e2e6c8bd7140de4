"""srvwire's pytest plugin: fixtures that serve your server and connect to it, per test.

Installed with srvwire and loaded by pytest through the ``pytest11`` entry point (turn it off
with ``-p no:srvwire``). A project overrides one fixture, ``srvwire_server``, and its tests
ask for the rest:

* ``srvwire_server``: the :class:`~srvwire.server.Server` under test; the default fails,
  asking for the override;
* ``srvwire_transport``: a fresh :class:`~srvwire.transports.memory.MemoryTransport`, or a
  WebSocket on 127.0.0.1 with ``@pytest.mark.srvwire(transport="websockets")``;
* ``srvwire_running``: ``srvwire_server`` served on it, shut down after the test;
* ``srvwire_url``: where clients connect;
* ``srvwire_client``: an open :class:`~srvwire.client.Client`, whose calls give up after
  :data:`TIMEOUT`;
* ``srvwire_sync_client``: an open :class:`srvwire.sync.Client`, the blocking client, for
  plain ``def`` tests; it serves ``srvwire_server`` from an event loop in a thread of its own;
* ``srvwire_wire``: a :class:`Wire`, JSON in and out with no client in between;
* ``srvwire_handler_errors``: the errors the server logged during the test.

``@pytest.mark.srvwire(...)`` on a test, class or module says how they serve and connect:
``transport="websockets"``, ``handler_errors="allow"``, and the credentials the clients
open with: ``token="..."`` (sent as ``Authorization: Bearer ...``) and ``headers={...}``,
for a server with ``auth=`` and services with ``scopes=``.

Rules:

* **Contract mode.** With ``--srvwire-url URL``, ``srvwire_client``, ``srvwire_wire`` and
  ``srvwire_url`` go to the server at that URL, over WebSockets, and nothing is served:
  ``srvwire_server`` is never asked for, and ``srvwire_running`` fails saying why.
* **A server's error fails the test.** What the server logs at ERROR or above while its test
  runs (a handler's exception and traceback, a response that does not validate) is collected
  in ``srvwire_handler_errors``. What is left in it when the test's body ends fails the test
  with the tracebacks; what is logged later, during teardown, fails the teardown. The test
  accepts them by clearing the list, or by ``@pytest.mark.srvwire(handler_errors="allow")``.
* **A blocking client's server runs in a thread.** A blocking call holds the thread it is made
  from, and with it the test's event loop, so ``srvwire_sync_client`` serves
  ``srvwire_server`` on the loop its client runs on, in a thread of its own; it cannot share
  a test with ``srvwire_running`` (or what needs it: ``srvwire_client``, ``srvwire_wire``,
  ``srvwire_url``), which serve on the test's loop. With ``--srvwire-url`` it connects there.
* **The fixtures run on the test's event loop.** pytest-asyncio runs an async fixture on the
  loop of its ``loop_scope``, fixed when the fixture is defined, so each async fixture here is
  defined once per loop scope (``_srvwire_client_module``, ...), and the public fixture, a
  plain one, asks for the variant of the loop scope the test runs in: the ``loop_scope`` of
  its ``asyncio`` marker, else ``asyncio_default_test_loop_scope``.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from collections.abc import AsyncIterator, Generator, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import pytest

from srvwire import sync
from srvwire.client import Client, connect
from srvwire.server import RunningServer, Server, serve
from srvwire.transports import get_transport
from srvwire.transports.base import Connection, Options, Transport
from srvwire.transports.memory import MemoryTransport

try:
    from pytest_asyncio import fixture as async_fixture
except ImportError:  # the fixtures that need it say so; the rest of pytest works on
    async_fixture = None  # type: ignore[assignment]

__all__ = ["HOST", "TIMEOUT", "Wire"]

HOST = "127.0.0.1"
"""Where ``srvwire_running`` listens (on port 0: any free port)."""

TIMEOUT = 5.0
"""Seconds: the default deadline of a ``srvwire_client`` call, and how long a :class:`Wire`
waits for a message. A call that hangs fails the test instead of hanging pytest."""

SHUTDOWN = 30.0
"""Seconds ``srvwire_sync_client`` waits for its server's graceful shutdown after the test."""

TRANSPORTS = ("memory", "websockets")
HANDLER_ERRORS = ("fail", "allow")

LoopScope = Literal["function", "class", "module", "package", "session"]
LOOP_SCOPES: tuple[LoopScope, ...] = ("function", "class", "module", "package", "session")

MARKER = (
    "srvwire(transport='memory', handler_errors='fail', token=None, headers={}): how the "
    "srvwire fixtures serve this test: transport='websockets' listens on a real port of "
    "127.0.0.1 instead of in memory; handler_errors='allow' lets errors the server logs pass "
    "instead of failing the test; token and headers are the credentials srvwire_client, "
    "srvwire_sync_client and srvwire_wire open their connection with"
)

OPTIONS = "(transport=..., handler_errors=..., token=..., headers=...)"

NO_SERVER = """\
the srvwire fixtures serve your srvwire.Server, and no fixture provides it: define \
srvwire_server in your conftest.py, for example

    @pytest.fixture
    def srvwire_server():
        return my_app.build_server()

or run the tests against a server that is already running, with --srvwire-url ws://HOST:PORT"""

SYNC_AND_ASYNC = (
    "srvwire_sync_client serves srvwire_server from a thread of its own, and this test also "
    "serves it on its event loop (srvwire_running, which srvwire_client, srvwire_wire and "
    "srvwire_url use): a blocking call would hold that loop. Use srvwire_sync_client or the "
    "async fixtures in one test, not both"
)

ON_THE_TESTS_LOOP = {"srvwire_running", "srvwire_client", "srvwire_wire", "srvwire_url"}

NO_PYTEST_ASYNCIO = (
    "the srvwire fixtures are async and need pytest-asyncio: pip install pytest-asyncio"
)

_ERRORS = pytest.StashKey[list[logging.LogRecord]]()


# --- options --------------------------------------------------------------------------------


def pytest_addoption(parser: pytest.Parser) -> None:
    group = parser.getgroup("srvwire")
    group.addoption(
        "--srvwire-url",
        metavar="URL",
        default=None,
        help="contract tests: connect srvwire_client and srvwire_wire to the server already "
        "running at URL (ws://host:port) instead of serving srvwire_server",
    )


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", MARKER)
    url = _url(config)
    if url is not None:
        try:
            get_transport("websockets").check_url(url)
        except ValueError as exc:
            raise pytest.UsageError(f"--srvwire-url: {exc}") from None


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        _marked(item)  # a mistake in a marker stops the run before any test


def _url(config: pytest.Config) -> str | None:
    url: str | None = config.getoption("srvwire_url")
    return url


@dataclass(frozen=True, slots=True)
class _Marked:
    """What ``@pytest.mark.srvwire`` says for one test; the closest marker wins, per option."""

    transport: str = "memory"
    handler_errors: str = "fail"
    token: str | None = None
    headers: tuple[tuple[str, str], ...] = ()

    def opening_headers(self) -> list[tuple[str, str]]:
        """The headers a connection opens with: ``headers``, then the token's."""
        bearer = [] if self.token is None else [("Authorization", f"Bearer {self.token}")]
        return [*self.headers, *bearer]


def _marked(item: pytest.Item) -> _Marked:
    found: dict[str, Any] = {}
    for marker in item.iter_markers("srvwire"):  # the closest first
        if marker.args:
            raise pytest.UsageError(
                f"{item.nodeid}: @pytest.mark.srvwire takes keyword arguments only {OPTIONS}"
            )
        for key, value in marker.kwargs.items():
            found.setdefault(key, value)
    for key, allowed in (("transport", TRANSPORTS), ("handler_errors", HANDLER_ERRORS)):
        if key in found and found[key] not in allowed:
            raise pytest.UsageError(
                f"{item.nodeid}: @pytest.mark.srvwire({key}={found[key]!r}): "
                f"use {' or '.join(map(repr, allowed))}"
            )
    unknown = sorted(set(found) - {"transport", "handler_errors", "token", "headers"})
    if unknown:
        raise pytest.UsageError(
            f"{item.nodeid}: @pytest.mark.srvwire has no option {unknown[0]!r} (it takes "
            f"{OPTIONS.strip('()')})"
        )
    token = found.get("token")
    if token is not None and not (isinstance(token, str) and token):
        raise pytest.UsageError(
            f"{item.nodeid}: @pytest.mark.srvwire(token={token!r}): use a non-empty string"
        )
    headers = found.get("headers", {})
    if not (
        isinstance(headers, Mapping)
        and all(isinstance(k, str) and isinstance(v, str) for k, v in headers.items())
    ):
        raise pytest.UsageError(
            f"{item.nodeid}: @pytest.mark.srvwire(headers={headers!r}): use a dict of strings"
        )
    found["headers"] = tuple(headers.items())
    return _Marked(**found)


# --- the fixtures ---------------------------------------------------------------------------


@pytest.fixture
def srvwire_server() -> Server:
    """The srvwire.Server under test: override it in your conftest.py."""
    pytest.fail(NO_SERVER, pytrace=False)


@pytest.fixture
def srvwire_transport(request: pytest.FixtureRequest) -> Transport:
    """A fresh MemoryTransport; WebSockets if marked ``transport="websockets"`` or given a URL."""
    if _url(request.config) is not None or _marked(request.node).transport == "websockets":
        return get_transport("websockets")
    return MemoryTransport()


@pytest.fixture
def srvwire_running(request: pytest.FixtureRequest) -> RunningServer:
    """``srvwire_server`` served on ``srvwire_transport`` for the test, then shut down."""
    url = _url(request.config)
    if url is not None:
        pytest.fail(
            f"srvwire_running is not available with --srvwire-url: the tests run against the "
            f"server at {url}, which this process does not serve; use srvwire_url, "
            "srvwire_client or srvwire_wire",
            pytrace=False,
        )
    server = request.getfixturevalue("srvwire_server")
    if not isinstance(server, Server):
        pytest.fail(f"srvwire_server returned {server!r}, not a srvwire.Server", pytrace=False)
    running: RunningServer = _on_the_tests_loop(request, "running")
    return running


@pytest.fixture
def srvwire_url(request: pytest.FixtureRequest) -> str:
    """Where the server is: ``srvwire_running.url``, or the URL given with ``--srvwire-url``."""
    url = _url(request.config)
    if url is None:
        running: RunningServer = request.getfixturevalue("srvwire_running")
        url = running.url
    return url


@pytest.fixture
def srvwire_client(request: pytest.FixtureRequest) -> Client:
    """An open Client to ``srvwire_url``, closed after the test; calls time out after TIMEOUT."""
    client: Client = _on_the_tests_loop(request, "client")
    return client


@pytest.fixture
def srvwire_sync_client(request: pytest.FixtureRequest) -> Iterator[sync.Client]:
    """An open blocking client to ``srvwire_server``, served in a thread; closed after the test."""
    url = _url(request.config)
    headers = _marked(request.node).opening_headers()
    if url is not None:
        with sync.connect(url, timeout=TIMEOUT, headers=headers) as client:
            yield client
        return
    if ON_THE_TESTS_LOOP & set(request.fixturenames):
        pytest.fail(SYNC_AND_ASYNC, pytrace=False)
    server = request.getfixturevalue("srvwire_server")
    if not isinstance(server, Server):
        pytest.fail(f"srvwire_server returned {server!r}, not a srvwire.Server", pytrace=False)
    transport: Transport = request.getfixturevalue("srvwire_transport")
    errors: list[logging.LogRecord] = request.getfixturevalue("srvwire_handler_errors")
    thread = sync.LoopThread("srvwire_sync_client")
    serving = contextlib.AsyncExitStack()
    try:
        running = thread.run(
            serving.enter_async_context(_serving(server, transport, errors)), TIMEOUT
        )
        options = connect(running.url, transport=transport, timeout=TIMEOUT, headers=headers)
        with sync.Client(options, loop=thread) as client:
            yield client
    finally:
        try:
            thread.run(serving.aclose(), SHUTDOWN)
        finally:
            thread.stop()


@pytest.fixture
def srvwire_wire(request: pytest.FixtureRequest) -> Wire:
    """A raw connection to ``srvwire_url``, JSON in and out, closed after the test."""
    wire: Wire = _on_the_tests_loop(request, "wire")
    return wire


@pytest.fixture
def srvwire_handler_errors(request: pytest.FixtureRequest) -> list[logging.LogRecord]:
    """The records the server logged at ERROR or above during the test; clear it to accept them."""
    records: list[logging.LogRecord] = request.node.stash.setdefault(_ERRORS, [])
    return records


def _on_the_tests_loop(request: pytest.FixtureRequest, kind: str) -> Any:
    """Return the variant of the async fixture ``kind`` that runs on the test's event loop."""
    if async_fixture is None:
        pytest.fail(NO_PYTEST_ASYNCIO, pytrace=False)
    return request.getfixturevalue(f"_srvwire_{kind}_{_loop_scope(request.node)}")


def _loop_scope(item: pytest.Item) -> str:
    """The scope of the event loop pytest-asyncio runs ``item`` in."""
    marker = item.get_closest_marker("asyncio")
    if marker is not None:
        scope = marker.kwargs.get("loop_scope") or marker.kwargs.get("scope")
        if scope:
            return str(scope)
    try:
        return str(item.config.getini("asyncio_default_test_loop_scope") or "function")
    except ValueError:  # a pytest-asyncio from before the option: tests run per function
        return "function"


# --- the async fixtures, one of each per loop scope -----------------------------------------


class _Collect(logging.Handler):
    """Append what a server's logger records at ERROR or above to a test's list."""

    def __init__(self, records: list[logging.LogRecord]) -> None:
        super().__init__(logging.ERROR)
        self.records = records

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


@contextlib.asynccontextmanager
async def _serving(
    server: Server, transport: Transport, errors: list[logging.LogRecord]
) -> AsyncIterator[RunningServer]:
    collect = _Collect(errors)
    server.logger.addHandler(collect)
    try:
        async with serve(server, HOST, 0, transport=transport) as running:
            yield running
    finally:
        server.logger.removeHandler(collect)


def _define(scope: LoopScope) -> dict[str, Any]:
    """The async fixtures that run on the event loop of ``scope``; each lives for one test."""
    assert async_fixture is not None

    @async_fixture(loop_scope=scope, name=f"_srvwire_running_{scope}")
    async def running(
        srvwire_server: Server,
        srvwire_transport: Transport,
        srvwire_handler_errors: list[logging.LogRecord],
    ) -> AsyncIterator[RunningServer]:
        async with _serving(srvwire_server, srvwire_transport, srvwire_handler_errors) as value:
            yield value

    @async_fixture(loop_scope=scope, name=f"_srvwire_client_{scope}")
    async def client(
        request: pytest.FixtureRequest, srvwire_url: str, srvwire_transport: Transport
    ) -> AsyncIterator[Client]:
        # Types not on the search path come from the server's description: in this process,
        # the very classes the server registered.
        headers = _marked(request.node).opening_headers()
        async with connect(
            srvwire_url, transport=srvwire_transport, timeout=TIMEOUT, headers=headers
        ) as value:
            yield value

    @async_fixture(loop_scope=scope, name=f"_srvwire_wire_{scope}")
    async def wire(
        request: pytest.FixtureRequest, srvwire_url: str, srvwire_transport: Transport
    ) -> AsyncIterator[Wire]:
        headers = _marked(request.node).opening_headers()
        value = await Wire.open(srvwire_url, transport=srvwire_transport, headers=headers)
        try:
            yield value
        finally:
            await value.close()

    return {
        f"_srvwire_running_{scope}": running,
        f"_srvwire_client_{scope}": client,
        f"_srvwire_wire_{scope}": wire,
    }


if async_fixture is not None:
    for _scope in LOOP_SCOPES:
        globals().update(_define(_scope))  # pytest finds fixtures among a plugin's names


# --- errors the server logs fail the test ---------------------------------------------------


@pytest.hookimpl(wrapper=True)
def pytest_runtest_call(item: pytest.Item) -> Generator[None, None, None]:
    try:
        yield
    except BaseException:
        # The test failed by itself: show the server's side beside its own failure.
        errors = _take(item)
        if errors:
            item.add_report_section("call", "srvwire errors", _describe(errors))
        raise
    errors = _take(item)
    if errors and _marked(item).handler_errors == "fail":
        pytest.fail(_report(errors, "while the test ran"), pytrace=False)


@pytest.hookimpl(wrapper=True)
def pytest_runtest_teardown(item: pytest.Item) -> Generator[None, None, None]:
    try:
        yield
    finally:
        errors = _take(item)
        if _ERRORS in item.stash:
            del item.stash[_ERRORS]  # the records hold tracebacks: keep none past the test
    if errors and _marked(item).handler_errors == "fail":
        pytest.fail(_report(errors, "while the test's fixtures were torn down"), pytrace=False)


def _take(item: pytest.Item) -> list[logging.LogRecord]:
    """Return the records collected so far for ``item`` and empty its list."""
    records = item.stash.get(_ERRORS, None)
    if not records:
        return []
    taken = list(records)
    records.clear()
    return taken


def _describe(records: list[logging.LogRecord]) -> str:
    """Each record's message, with its traceback when it has one."""
    formatter = logging.Formatter("%(name)s %(levelname)s: %(message)s")
    return "\n\n".join(formatter.format(record) for record in records)


def _report(records: list[logging.LogRecord], when: str) -> str:
    errors = "1 error" if len(records) == 1 else f"{len(records)} errors"
    return (
        f"srvwire_server logged {errors} {when}; its callers saw only InternalError:\n\n"
        f"{_describe(records)}\n\n"
        "If the test expects this, check and clear srvwire_handler_errors in it, or mark it "
        '@pytest.mark.srvwire(handler_errors="allow").'
    )


# --- a raw connection -----------------------------------------------------------------------


class Wire:
    """A raw connection to a srvwire server, for protocol-level tests: JSON in, JSON out.

    What goes out is exactly what the test gives: no srvwire client checks or numbers it, so
    the server meets what a client in another language, or a broken one, would send. Open one
    with :meth:`open`, or ask for the ``srvwire_wire`` fixture.
    """

    def __init__(self, connection: Connection, services: list[dict[str, str]]) -> None:
        self.connection = connection
        self.services = services
        """The services of the ``$/services`` notification that opened the session."""

    @classmethod
    async def open(
        cls,
        url: str,
        *,
        transport: str | Transport = "websockets",
        within: float = TIMEOUT,
        headers: Sequence[tuple[str, str]] = (),
    ) -> Wire:
        """Connect to ``url`` and read the ``$/services`` the server opens the session with.

        ``headers`` go with the opening request as they are (credentials:
        ``[("Authorization", "Bearer ...")]``)."""
        connection = await get_transport(transport).connect(url, Options(), headers=headers)
        try:
            wire = cls(connection, [])
            first = await wire.recv(within)
            if not (isinstance(first, dict) and first.get("method") == "$/services"):
                raise AssertionError(f"the server opened the session with {first!r}")
            wire.services = first["params"]["services"]
        except BaseException:
            await connection.close()
            raise
        return wire

    async def send(self, message: Any) -> None:
        """Send ``message``: a ``str`` or ``bytes`` as it is, anything else as JSON."""
        if isinstance(message, str | bytes):
            await self.connection.send(message)
        else:
            await self.connection.send(json.dumps(message))

    async def recv(self, within: float = TIMEOUT) -> Any:
        """Receive the next message and return it decoded from JSON.

        Raise ``TimeoutError`` if none comes within ``within`` seconds, and
        :class:`~srvwire.transports.base.TransportClosed` once the connection has ended.
        """
        try:
            async with asyncio.timeout(within):
                message = await self.connection.recv()
        except TimeoutError:
            raise TimeoutError(f"no message from the server within {within:g} s") from None
        return json.loads(message)

    async def recv_reply(self, within: float = TIMEOUT) -> Any:
        """Receive the next message that is not an announcement (``$/services``, ``$/topics``)."""
        while True:
            message = await self.recv(within)
            if not (
                isinstance(message, dict) and message.get("method") in ("$/services", "$/topics")
            ):
                return message

    async def call(self, message: Any, within: float = TIMEOUT) -> Any:
        """Send ``message`` and return the reply (a list, for a batch)."""
        await self.send(message)
        return await self.recv_reply(within)

    async def request(self, method: str, params: Any = None, id: Any = 1) -> Any:
        """Call ``method`` with ``params`` (left out when None) under ``id``; return the reply."""
        message: dict[str, Any] = {"jsonrpc": "2.0", "id": id, "method": method}
        if params is not None:
            message["params"] = params
        return await self.call(message)

    async def close(self) -> None:
        """Close the connection; idempotent."""
        await self.connection.close()
