"""srvwire's pytest plugin (``srvwire.testing``), tested as plugins are: on a user's project.

Each test writes a small project into pytester's directory (a conftest that overrides
``srvwire_server`` with the project's own services, and tests that use the fixtures), runs
pytest on it, and checks what that run reported. The runs are in this process, except the
contract test's, which runs beside a server this test serves on a real port.
"""

from __future__ import annotations

import asyncio
from importlib.metadata import entry_points
from typing import Any

import pytest

from srvwire.loader import load_service
from srvwire.server import Server, serve
from support import scaled

pytest_plugins = ["pytester"]

INI = {
    "asyncio_mode": "auto",
    "asyncio_default_fixture_loop_scope": "function",
    # Without hypothesis's plugin, which imports hypothesis to end each run: a second a run;
    # nor aiohttp-json-rpc's (a benchmark's dependency), which pytest 9 refuses to load.
    "addopts": "--strict-markers -p no:cacheprovider -p no:hypothesispytest -p no:aiohttp-json-rpc",
    "filterwarnings": "error",
}

# The user's project: a service type of its own, built from .srv text, and a bundled one.
CONFTEST = """
import asyncio

import pytest

import srvwire
from srvwire.models import build_service
from srvwire.parser import parse_service

DIVIDE_SRV = "int64 dividend\\nint64 divisor\\n---\\nint64 quotient\\n"
Divide = build_service(parse_service(DIVIDE_SRV, "calculator", "Divide"))
AddTwoInts = srvwire.load_service("example_interfaces/srv/AddTwoInts")


@pytest.fixture
def handler_loops():
    return []  # the event loop of each call to /add_two_ints


@pytest.fixture
def srvwire_server(handler_loops):
    server = srvwire.Server()

    async def add(request, response):
        handler_loops.append(asyncio.get_running_loop())
        response.sum = request.a + request.b
        return response

    def divide(request):
        return {"quotient": request.dividend // request.divisor}

    server.add_service("/add_two_ints", AddTwoInts, add)
    server.add_service("/divide", Divide, divide)
    return server
"""


def project(
    pytester: pytest.Pytester,
    *,
    ini: dict[str, str] | None = None,
    conftest: str | None = CONFTEST,
    **files: str,
) -> None:
    """Write the user's project: its ini file, its conftest, and ``files`` (name: source)."""
    settings = {**INI, **(ini or {})}
    pytester.makeini("[pytest]\n" + "".join(f"{k} = {v}\n" for k, v in settings.items()))
    if conftest is not None:
        pytester.makeconftest(conftest)
    pytester.makepyfile(**files)


def test_pytest_finds_the_plugin_by_its_entry_point() -> None:
    [plugin] = entry_points(group="pytest11", name="srvwire")
    assert plugin.value == "srvwire.testing"


# --- the fixtures -----------------------------------------------------------------------------

FIXTURE_TESTS = """
import pytest

import srvwire


async def test_a_typed_call(srvwire_client):
    response = await srvwire_client.call("/add_two_ints", {"a": 2, "b": 3})
    assert (type(response).__name__, response.sum) == ("AddTwoInts_Response", 5)


async def test_a_service_of_the_projects_own(srvwire_client, srvwire_server):
    # calculator/srv/Divide is on no search path: the client gets the server's own class.
    response = await srvwire_client.call("/divide", {"dividend": 7, "divisor": 2})
    assert response.quotient == 3
    assert type(response) is srvwire_server.registry.get("/divide").srv_type.Response
    with pytest.raises(srvwire.InvalidParams):
        await srvwire_client.call("/divide", {"dividend": "seven", "divisor": 1})


async def test_in_memory_by_default(srvwire_running, srvwire_url, srvwire_transport):
    assert isinstance(srvwire_transport, srvwire.MemoryTransport)
    assert srvwire_running.transport is srvwire_transport
    assert srvwire_url == srvwire_running.url == "memory://127.0.0.1:1"


async def test_the_wire(srvwire_wire):
    assert [service["name"] for service in srvwire_wire.services] == ["/add_two_ints", "/divide"]
    reply = await srvwire_wire.request("/add_two_ints", {"a": 1, "b": 2}, id="x")
    assert reply == {"jsonrpc": "2.0", "id": "x", "result": {"sum": 3}}
    reply = await srvwire_wire.call("{not json")
    assert (reply["id"], reply["error"]["code"]) == (None, -32700)


@pytest.mark.srvwire(transport="websockets")
async def test_over_a_websocket(srvwire_running, srvwire_client, srvwire_wire):
    assert srvwire_running.url.startswith("ws://127.0.0.1:")
    assert (await srvwire_client.call("/add_two_ints", {"a": 1, "b": 1})).sum == 2
    reply = await srvwire_wire.request("/add_two_ints", {"a": 2, "b": 2})
    assert reply["result"] == {"sum": 4}
"""


def test_the_fixtures_serve_the_users_server(pytester: pytest.Pytester) -> None:
    project(pytester, test_calculator=FIXTURE_TESTS)
    result = pytester.runpytest()
    result.assert_outcomes(passed=5)


def test_without_a_srvwire_server_the_error_says_how_to_give_one(
    pytester: pytest.Pytester,
) -> None:
    project(pytester, conftest=None, test_it="async def test_a_call(srvwire_client): pass")
    result = pytester.runpytest()
    result.assert_outcomes(errors=1)
    result.stdout.fnmatch_lines(
        [
            "*ERROR at setup of test_a_call*",
            "the srvwire fixtures serve your srvwire.Server, and no fixture provides it: "
            "define srvwire_server in your conftest.py, for example",
            "",
            "    @pytest.fixture",
            "    def srvwire_server():",
            "        return my_app.build_server()",
        ]
    )


@pytest.mark.parametrize(
    ("marker", "message"),
    [
        (
            'transport="pigeon"',
            "ERROR: test_it.py::test_it: @pytest.mark.srvwire(transport='pigeon'): "
            "use 'memory' or 'websockets'",
        ),
        (
            'handler_errors="ignore"',
            "ERROR: test_it.py::test_it: @pytest.mark.srvwire(handler_errors='ignore'): "
            "use 'fail' or 'allow'",
        ),
        (
            "timeout=1",
            "ERROR: test_it.py::test_it: @pytest.mark.srvwire has no option 'timeout' "
            "(it takes transport=..., handler_errors=..., token=..., headers=...)",
        ),
        (
            'token=""',
            "ERROR: test_it.py::test_it: @pytest.mark.srvwire(token=''): use a non-empty string",
        ),
        (
            'headers={"X-Badge": 42}',
            "ERROR: test_it.py::test_it: @pytest.mark.srvwire(headers={'X-Badge': 42}): "
            "use a dict of strings",
        ),
    ],
)
def test_a_mistake_in_the_marker_stops_the_run(
    pytester: pytest.Pytester, marker: str, message: str
) -> None:
    project(pytester, test_it=f"import pytest\n@pytest.mark.srvwire({marker})\ndef test_it(): pass")
    result = pytester.runpytest()
    assert result.ret == pytest.ExitCode.USAGE_ERROR
    result.stderr.fnmatch_lines([message])


# --- credentials --------------------------------------------------------------------------------

# A server with authentication, whose /motors needs a scope; tokens and a badge header admit.
SECURE_CONFTEST = """
import pytest

import srvwire

SetBool = srvwire.load_service("std_srvs/srv/SetBool")


async def badge_reader(handshake):
    if handshake.header("X-Badge") != "42":
        raise srvwire.Unauthenticated("show badge 42")
    return srvwire.Identity("badge 42", scopes={"robot:write"})


def motors(request, context):
    return {"success": True, "message": context.identity.name}


@pytest.fixture
def srvwire_server(request):
    badge = request.node.get_closest_marker("badge") is not None
    operator = srvwire.Identity("operator", scopes={"robot:write"})
    auth = badge_reader if badge else srvwire.TokenAuth({"op": operator, "view": "viewer"})
    server = srvwire.Server(auth=auth)
    server.add_service("/motors", SetBool, motors, scopes={"robot:write"})
    return server
"""

CREDENTIAL_TESTS = """
import pytest

import srvwire

pytestmark = pytest.mark.srvwire(token="op")  # the module's default: the closest marker wins


async def test_the_modules_token(srvwire_client):
    assert (await srvwire_client.call("/motors", {"data": True})).message == "operator"


@pytest.mark.srvwire(token="view")
async def test_a_token_without_the_scope(srvwire_client):
    assert "/motors" not in srvwire_client.services
    with pytest.raises(srvwire.PermissionDenied):
        await srvwire_client.call("/motors", {"data": True}, srv_type="std_srvs/srv/SetBool")


@pytest.mark.srvwire(token="op", transport="websockets")
def test_the_blocking_client_over_a_socket(srvwire_sync_client):
    assert srvwire_sync_client.call("/motors", {"data": True}).message == "operator"


@pytest.mark.srvwire(token="view")
async def test_the_wire(srvwire_wire):
    assert srvwire_wire.services == []
    reply = await srvwire_wire.request("/motors", {"data": True})
    assert reply["error"]["data"]["missing_scopes"] == ["robot:write"]


@pytest.mark.badge
@pytest.mark.srvwire(headers={"X-Badge": "42"})
async def test_a_header_of_your_own(srvwire_client):
    assert (await srvwire_client.call("/motors", {"data": False})).message == "badge 42"


@pytest.mark.srvwire(token="a guess")
async def test_a_wrong_token(srvwire_client):
    pass
"""


def test_the_marker_gives_the_clients_their_credentials(pytester: pytest.Pytester) -> None:
    project(
        pytester,
        ini={"markers": "badge: serve with the badge reader"},
        conftest=SECURE_CONFTEST,
        test_secure=CREDENTIAL_TESTS,
    )
    result = pytester.runpytest()
    result.assert_outcomes(passed=5, errors=1)
    result.stdout.fnmatch_lines(
        ["*ERROR at setup of test_a_wrong_token*", "*ServiceUnavailable*HTTP 401*"]
    )


# --- the blocking client ----------------------------------------------------------------------

SYNC_TESTS = """
from concurrent.futures import ThreadPoolExecutor

import pytest

import srvwire


def test_a_typed_blocking_call(srvwire_sync_client, handler_loops):
    response = srvwire_sync_client.call("/add_two_ints", {"a": 2, "b": 3})
    assert (type(response).__name__, response.sum) == ("AddTwoInts_Response", 5)
    assert srvwire_sync_client.proxy("/divide")(dividend=7, divisor=2).quotient == 3
    assert srvwire_sync_client.url == "memory://127.0.0.1:1"
    assert len(handler_loops) == 1


def test_from_several_threads(srvwire_sync_client):
    with ThreadPoolExecutor(4) as pool:
        sums = list(pool.map(
            lambda i: srvwire_sync_client.call("/add_two_ints", {"a": i, "b": i}).sum, range(40)
        ))
    assert sums == [2 * i for i in range(40)]


async def test_in_an_async_test(srvwire_sync_client):
    assert srvwire_sync_client.call("/add_two_ints", {"a": 1, "b": 2}).sum == 3


@pytest.mark.srvwire(transport="websockets")
def test_over_a_websocket(srvwire_sync_client):
    assert srvwire_sync_client.url.startswith("ws://127.0.0.1:")
    assert srvwire_sync_client.call("/add_two_ints", {"a": 1, "b": 1}).sum == 2


def test_typed_errors(srvwire_sync_client):
    with pytest.raises(srvwire.InvalidParams):
        srvwire_sync_client.call("/divide", {"dividend": "seven", "divisor": 1})


def test_a_handler_that_raises(srvwire_sync_client):
    with pytest.raises(srvwire.InternalError):
        srvwire_sync_client.call("/divide", {"dividend": 1, "divisor": 0})


async def test_with_the_async_fixtures(srvwire_sync_client, srvwire_client):
    pass
"""


def test_the_blocking_client_fixture(pytester: pytest.Pytester) -> None:
    project(pytester, test_blocking_client=SYNC_TESTS)
    result = pytester.runpytest("-p", "no:logging")
    result.assert_outcomes(passed=5, failed=1, errors=1)
    result.stdout.fnmatch_lines(
        [
            "*ERROR at setup of test_with_the_async_fixtures*",
            "srvwire_sync_client serves srvwire_server from a thread of its own, and this test "
            "also serves it on its event loop (srvwire_running, which srvwire_client, "
            "srvwire_wire and srvwire_url use): a blocking call would hold that loop. Use "
            "srvwire_sync_client or the async fixtures in one test, not both",
            "*_ test_a_handler_that_raises _*",
            "srvwire_server logged 1 error while the test ran; its callers saw only InternalError:",
            "",
            "srvwire.server ERROR: handler for /divide raised an exception (request id 2)",
            "Traceback (most recent call last):",
            '*return {"quotient": request.dividend // request.divisor}*',
            "ZeroDivisionError: integer division or modulo by zero",
        ]
    )


# --- handler errors -----------------------------------------------------------------------------

ERROR_TESTS = """
import pytest

import srvwire


async def divide_by_zero(client):
    with pytest.raises(srvwire.InternalError):
        await client.call("/divide", {"dividend": 1, "divisor": 0})


async def test_a_handler_that_raises(srvwire_client):
    await divide_by_zero(srvwire_client)  # all the client sees: this test body passes


@pytest.mark.srvwire(handler_errors="allow")
async def test_allowed(srvwire_client):
    await divide_by_zero(srvwire_client)


async def test_checked_and_cleared(srvwire_client, srvwire_handler_errors):
    await divide_by_zero(srvwire_client)
    [record] = srvwire_handler_errors
    assert record.exc_info[0] is ZeroDivisionError
    # Request 1 asked for the server's description: calculator/srv/Divide is not on the path.
    assert record.getMessage() == "handler for /divide raised an exception (request id 2)"
    srvwire_handler_errors.clear()


async def test_failing_by_itself(srvwire_client):
    await srvwire_client.call("/divide", {"dividend": 1, "divisor": 0})


@pytest.fixture
async def divides_by_zero_at_teardown(srvwire_client):
    yield
    await divide_by_zero(srvwire_client)


async def test_raised_during_teardown(divides_by_zero_at_teardown):
    pass
"""


def test_a_handler_exception_fails_the_test_with_its_traceback(pytester: pytest.Pytester) -> None:
    project(pytester, test_user_errors=ERROR_TESTS)
    result = pytester.runpytest("-p", "no:logging")  # no captured log: the plugin's own report
    result.assert_outcomes(passed=3, failed=2, errors=1)
    traceback = [
        "srvwire.server ERROR: handler for /divide raised an exception (request id 2)",
        "Traceback (most recent call last):",
        '*return {"quotient": request.dividend // request.divisor}*',
        "ZeroDivisionError: integer division or modulo by zero",
    ]
    result.stdout.fnmatch_lines(
        [
            "*_ ERROR at teardown of test_raised_during_teardown _*",
            "srvwire_server logged 1 error while the test's fixtures were torn down; *",
            "",
            *traceback,
            "*_ test_a_handler_that_raises _*",
            "srvwire_server logged 1 error while the test ran; its callers saw only InternalError:",
            "",
            *traceback,
            "",
            "If the test expects this, check and clear srvwire_handler_errors in it, or mark "
            'it @pytest.mark.srvwire(handler_errors="allow").',
            "*_ test_failing_by_itself _*",
            "E * srvwire.errors.InternalError: * handler for /divide raised an exception",
            "*- Captured srvwire errors call -*",
            *traceback,
        ]
    )
    # In order; not consecutive, since with CI set pytest writes each summary line's whole
    # message, over several lines.
    result.stdout.fnmatch_lines(
        [
            "FAILED test_user_errors.py::test_a_handler_that_raises - Failed: *",
            "FAILED test_user_errors.py::test_failing_by_itself - srvwire.errors.Internal*",
            "ERROR test_user_errors.py::test_raised_during_teardown - Failed: *",
        ]
    )


# --- loop scopes ------------------------------------------------------------------------------

LOOP_TESTS = """
import asyncio

import pytest

{header}
LOOPS = []  # each test's event loop


async def test_first(srvwire_client, srvwire_wire, handler_loops):
    LOOPS.append(asyncio.get_running_loop())
    assert (await srvwire_client.call("/add_two_ints", {{"a": 1, "b": 2}})).sum == 3
    reply = await srvwire_wire.request("/add_two_ints", {{"a": 1, "b": 2}})
    assert reply["result"] == {{"sum": 3}}
    assert handler_loops == [asyncio.get_running_loop()] * 2


async def test_second(srvwire_client, handler_loops):
    LOOPS.append(asyncio.get_running_loop())
    assert (await srvwire_client.call("/add_two_ints", {{"a": 2, "b": 2}})).sum == 4
    assert handler_loops == [asyncio.get_running_loop()]
    assert (LOOPS[0] is LOOPS[1]) is {shared}
"""


@pytest.mark.parametrize(
    ("ini", "header", "shared"),
    [
        pytest.param({}, "", False, id="function"),
        pytest.param(
            {}, 'pytestmark = pytest.mark.asyncio(loop_scope="module")', True, id="module"
        ),
        pytest.param(
            {"asyncio_default_test_loop_scope": "session"}, "", True, id="session-by-default"
        ),
        pytest.param(
            {"asyncio_default_fixture_loop_scope": "session"},
            "",
            False,
            id="fixtures-on-session-tests-on-function",
        ),
        pytest.param(
            {"asyncio_mode": "strict"}, "pytestmark = pytest.mark.asyncio", False, id="strict"
        ),
    ],
)
def test_the_fixtures_run_on_the_tests_event_loop(
    pytester: pytest.Pytester, ini: dict[str, str], header: str, shared: bool
) -> None:
    project(pytester, ini=ini, test_loops=LOOP_TESTS.format(header=header, shared=shared))
    result = pytester.runpytest()
    result.assert_outcomes(passed=2)


# --- contract tests -----------------------------------------------------------------------------

CONTRACT_TESTS = """
def test_a_blocking_call(srvwire_sync_client, srvwire_url):
    assert srvwire_sync_client.url == srvwire_url
    assert srvwire_sync_client.call("/add_two_ints", {"a": 3, "b": 2}).sum == 5


async def test_a_call(srvwire_client, srvwire_url):
    assert srvwire_client.url == srvwire_url
    assert (await srvwire_client.call("/add_two_ints", {"a": 2, "b": 2})).sum == 4


async def test_the_wire(srvwire_wire):
    reply = await srvwire_wire.request("add_two_ints", {"a": 1, "b": 2})
    assert reply["result"] == {"sum": 3}


async def test_the_running_server(srvwire_running):
    pass
"""


async def test_contract_tests_run_against_a_server_given_by_its_url(
    pytester: pytest.Pytester,
) -> None:
    # No srvwire_server in this project: with --srvwire-url, nothing asks for it.
    project(pytester, conftest=None, test_contract=CONTRACT_TESTS)
    server = Server()
    AddTwoInts = load_service("example_interfaces/srv/AddTwoInts")

    def add(request: Any) -> Any:
        return {"sum": request.a + request.b}

    server.add_service("/add_two_ints", AddTwoInts, add)
    async with serve(server, "127.0.0.1", 0) as running:
        # In a thread, so that this loop goes on serving while the other pytest runs.
        result = await asyncio.to_thread(
            pytester.runpytest_subprocess, f"--srvwire-url={running.url}", timeout=scaled(60)
        )
    result.assert_outcomes(passed=3, errors=1)
    result.stdout.fnmatch_lines(
        [
            "*ERROR at setup of test_the_running_server*",
            "srvwire_running is not available with --srvwire-url: the tests run against the "
            f"server at {running.url}, which this process does not serve; use srvwire_url, "
            "srvwire_client or srvwire_wire",
        ]
    )


def test_a_url_that_is_no_websocket_url_is_a_usage_error(pytester: pytest.Pytester) -> None:
    project(pytester, test_it="def test_it(): pass")
    result = pytester.runpytest("--srvwire-url=http://localhost:8765")
    assert result.ret == pytest.ExitCode.USAGE_ERROR
    result.stderr.fnmatch_lines(
        ["ERROR: --srvwire-url: not a WebSocket URL: 'http://localhost:8765'*"]
    )
