"""A user's own types work from a client that has no interface files: reflection and one class.

The server runs in another process with its own search path (a package ``my_robot`` that nests
types from itself, ``std_msgs`` and ``geometry_msgs``); the client has the default path only and
no environment variable. Its calls are typed from the server's description, its requests are
checked before sending, and a type it has too is its own class.
"""

from __future__ import annotations

import asyncio
import os
import shutil
import subprocess
import sys
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import pydantic
import pytest

import srvwire
from srvwire.dispatch import ServiceRegistry
from srvwire.errors import (
    InterfaceConflictError,
    InterfaceError,
    InterfaceNotFoundError,
    InvalidParams,
    RegistrationError,
)
from srvwire.loader import ENV_VAR, InterfaceLoader, bundled_interfaces
from srvwire.models import build_message, build_service
from srvwire.parser import parse_message, parse_service
from srvwire.typeregistry import TypeRegistry, fingerprint, full_definition, process_types
from support import scaled

BATTERY = "# The battery, as the robot reports it.\nfloat32 voltage\nuint8 percent 100\n"
STATUS = (
    "# What the robot says about itself.\n"
    "std_msgs/Header header\n"
    "geometry_msgs/Pose pose\n"
    "BatteryState battery\n"
    "string[] faults\n"
)
GET_STATUS = "string robot  # which robot\n---\nRobotStatus status\nbool ok\n"

APP = """
import srvwire

loader = srvwire.InterfaceLoader([{folder!r}])
GetStatus = loader.load_service("my_robot/srv/GetStatus")
server = srvwire.Server()


@server.service("/get_status", GetStatus)
def get_status(request):
    response = GetStatus.Response(ok=request.robot == "r1")
    response.status.header.frame_id = request.robot
    response.status.pose.position.x = 1.5
    response.status.battery.voltage = 24.0
    return response
"""


def write(root: Path, relative: str, text: str) -> Path:
    path = root / relative
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    return path


def robot_package(root: Path, battery: str = BATTERY) -> Path:
    write(root, "my_robot/msg/BatteryState.msg", battery)
    write(root, "my_robot/msg/RobotStatus.msg", STATUS)
    write(root, "my_robot/srv/GetStatus.srv", GET_STATUS)
    return root


@pytest.fixture
def no_path_variable(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(ENV_VAR, raising=False)


@pytest.fixture(scope="module")
def robot_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """``srvwire serve`` in another process, its own search path holding ``my_robot``.

    One for the module: the classes a client builds from it are the process's from then on,
    recorded with its URL.
    """
    tmp_path = tmp_path_factory.mktemp("robot")
    yield from serving(tmp_path, robot_package(tmp_path / "server_interfaces"))


def serving(tmp_path: Path, interfaces: Path) -> Iterator[str]:
    yield from serving_app(write(tmp_path, "robot_app.py", APP.format(folder=str(interfaces))))


def serving_app(app: Path) -> Iterator[str]:
    """``srvwire serve`` the server of ``app`` in a subprocess, with no interface path variable;
    yield its URL."""
    env = {k: v for k, v in os.environ.items() if k != ENV_VAR}
    with subprocess.Popen(
        [sys.executable, "-m", "srvwire", "serve", f"{app}:server", "--port", "0"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    ) as process:
        try:
            assert process.stdout is not None and process.stderr is not None
            first = process.stdout.readline()
            assert first.startswith("serving 1 "), first + process.stderr.read()
            yield first.split(" on ")[1].strip()
        finally:
            process.kill()


@pytest.fixture
async def client(robot_server: str, no_path_variable: None) -> AsyncIterator[srvwire.Client]:
    async with srvwire.connect(robot_server, timeout=scaled(10)) as value:
        yield value


async def test_a_type_only_the_server_has_is_typed_from_its_description(
    client: srvwire.Client, robot_server: str
) -> None:
    response = await client.call("/get_status", {"robot": "r1"})
    assert type(response).__name__ == "GetStatus_Response"
    assert response.ok is True
    status = response.status
    assert type(status).type_name == "my_robot/msg/RobotStatus"
    assert (status.header.frame_id, status.pose.position.x) == ("r1", 1.5)
    assert (status.battery.voltage, status.battery.percent) == (24.0, 100)
    # The nested types the client has itself are its own classes.
    assert type(status.header) is srvwire.load_message("std_msgs/msg/Header")
    assert type(status.pose) is srvwire.load_message("geometry_msgs/msg/Pose")
    # The server's comments came along.
    assert type(status.battery).__doc__ == "The battery, as the robot reports it."
    # Where each class came from.
    assert process_types().get("my_robot/msg/RobotStatus").source == f"server {robot_server}"
    header = process_types().get("std_msgs/msg/Header")
    assert header.source == str(bundled_interfaces() / "std_msgs/msg/Header.msg")


async def test_a_request_is_checked_before_it_is_sent(client: srvwire.Client) -> None:
    with pytest.raises(InvalidParams) as excinfo:
        await client.call("/get_status", {"robot": 7})
    assert excinfo.value.message == (
        "invalid params for /get_status: robot: Input should be a valid string "
        "(checked by the client; nothing was sent)"
    )


async def test_one_class_whichever_way_it_was_obtained(
    client: srvwire.Client, tmp_path: Path
) -> None:
    # 1. load_message with the default search path.
    Header = srvwire.load_message("std_msgs/Header")
    # 2. another loader, whose search path holds its own copy of the same files.
    copy = tmp_path / "copy"
    shutil.copytree(bundled_interfaces() / "geometry_msgs", copy / "geometry_msgs")
    Pose = InterfaceLoader([copy]).load_message("geometry_msgs/Pose")
    assert InterfaceLoader([copy]).path_of("geometry_msgs/Pose").is_relative_to(copy)
    # 3. reflection: the server's description of /get_status.
    GetStatus = await client.service_type("/get_status")
    RobotStatus = type(GetStatus.Response().status)
    status = RobotStatus(header=Header(frame_id="base"), pose=Pose())
    assert status.header.frame_id == "base"
    assert GetStatus.Response(status=status, ok=True).status is status
    # The same type from the loader of a folder that holds my_robot too is that class.
    assert (
        InterfaceLoader([robot_package(tmp_path / "mine")]).load_message("my_robot/RobotStatus")
        is RobotStatus
    )


async def test_a_local_file_that_differs_from_the_server_is_an_error(
    client: srvwire.Client, robot_server: str, tmp_path: Path
) -> None:
    await client.call("/get_status", {"robot": "r1"})  # the server's BatteryState, interned
    other = robot_package(tmp_path / "other", battery="float64 voltage\n")
    with pytest.raises(InterfaceConflictError) as excinfo:
        InterfaceLoader([other]).load_message("my_robot/BatteryState")
    assert str(excinfo.value) == (
        f"two different definitions of my_robot/msg/BatteryState: server {robot_server} and "
        f"{other / 'my_robot/msg/BatteryState.msg'} (declaration 1: 'float32 voltage' against "
        "'float64 voltage'); a type name has one definition per process"
    )


async def test_a_nested_type_the_server_defines_differently_is_an_error(
    tmp_path: Path, no_path_variable: None
) -> None:
    interfaces = robot_package(tmp_path / "interfaces")
    header = "uint32 seq\nbuiltin_interfaces/Time stamp\nstring frame_id\n"
    write(interfaces, "std_msgs/msg/Header.msg", header)
    for url in serving(tmp_path, interfaces):
        async with srvwire.connect(url, timeout=scaled(10)) as client:
            with pytest.raises(InterfaceConflictError) as excinfo:
                await client.call("/get_status", {"robot": "r1"})
    assert str(excinfo.value) == (
        "two different definitions of std_msgs/msg/Header: "
        f"{bundled_interfaces() / 'std_msgs/msg/Header.msg'} and server {url} (declaration 1: "
        "'builtin_interfaces/Time stamp' against 'uint32 seq'); a type name has one definition "
        "per process"
    )


# --- in one process: the server's own classes -------------------------------------------------

LIMITS = "# Speed limits.\nfloat64 max_speed 1.0\n"
SET_LIMITS = "Limits limits\n---\nbool ok\n"


def limits_server() -> tuple[srvwire.Server, type[srvwire.Service]]:
    """A server whose type is built from text: no file on any search path defines it."""
    Limits = build_message(parse_message(LIMITS, "inproc_robot", "Limits"))
    spec = parse_service(SET_LIMITS, "inproc_robot", "SetLimits")
    SetLimits = build_service(spec, lambda type_: Limits)
    server = srvwire.Server()
    server.add_service(
        "/set_limits", SetLimits, lambda request: {"ok": request.limits.max_speed < 5}
    )
    return server, SetLimits


def serving_descriptions(monkeypatch: pytest.MonkeyPatch) -> list[object]:
    """Record each rpc.discover document a server in this process writes."""
    described: list[object] = []
    discover_json = ServiceRegistry.discover_json

    def counted(registry: ServiceRegistry, scopes: frozenset[str] | None = None) -> str:
        described.append(registry)
        return discover_json(registry, scopes)

    monkeypatch.setattr(ServiceRegistry, "discover_json", counted)
    return described


async def test_a_client_in_the_servers_process_gets_the_servers_own_classes(
    monkeypatch: pytest.MonkeyPatch, no_path_variable: None
) -> None:
    server, SetLimits = limits_server()
    described = serving_descriptions(monkeypatch)
    transport = srvwire.MemoryTransport()
    async with (
        srvwire.serve(server, "127.0.0.1", 0, transport=transport) as running,
        srvwire.connect(running.url, transport=transport, timeout=scaled(5)) as client,
    ):
        reply = await client.call("/set_limits", {"limits": {"max_speed": 2}})
        assert type(reply) is SetLimits.Response and reply.ok is True
        request = SetLimits.Request(limits={"max_speed": 9})
        assert (await client.call("/set_limits", request)).ok is False
        with pytest.raises(InvalidParams, match=r"checked by the client; nothing was sent"):
            await client.call("/set_limits", {"limits": {"max_speed": "fast"}})
        assert await client.service_type("/set_limits") is SetLimits
        definitions = await client.definitions()
    assert len(described) == 2  # once for the calls, once for definitions()
    assert definitions == {
        "inproc_robot/msg/Limits": LIMITS,
        "inproc_robot/srv/SetLimits": SET_LIMITS,
    }


async def test_the_description_is_asked_again_after_the_services_change(
    monkeypatch: pytest.MonkeyPatch, no_path_variable: None
) -> None:
    server, _ = limits_server()
    described = serving_descriptions(monkeypatch)
    Reset = build_service(parse_service("---\nbool done\n", "inproc_robot", "Reset"))
    transport = srvwire.MemoryTransport()
    async with (
        srvwire.serve(server, "127.0.0.1", 0, transport=transport) as running,
        srvwire.connect(running.url, transport=transport, timeout=scaled(5)) as client,
    ):
        # Calls that need the description at the same time share one answer.
        await asyncio.gather(*(client.call("/set_limits", {}) for _ in range(5)))
        await client.call("/set_limits", {})
        assert len(described) == 1
        server.add_service("/reset", Reset, lambda request: {"done": True})
        await client.wait_for_service("/reset")
        assert type(await client.call("/reset")) is Reset.Response
        assert len(described) == 2


def test_rpc_discover_carries_every_definition_text() -> None:
    server, _ = limits_server()
    [method] = server.registry.discover()["methods"]
    assert method["x-srvwire-type"] == "inproc_robot/srv/SetLimits"
    assert method["x-srvwire-definitions"] == {
        "inproc_robot/srv/SetLimits": SET_LIMITS,
        "inproc_robot/msg/Limits": LIMITS,
    }
    # The fingerprint of the whole: the service and the message it nests, as $/services says.
    assert method["x-srvwire-fingerprint"] == fingerprint(
        {
            "inproc_robot/srv/SetLimits": ("inproc_robot/Limits limits", "---", "bool ok"),
            "inproc_robot/msg/Limits": ("float64 max_speed 1.0",),
        }
    )
    assert server.registry.fingerprints() == {"/set_limits": method["x-srvwire-fingerprint"]}


def test_registering_another_definition_under_a_known_name_is_refused() -> None:
    limits_server()  # the process's inproc_robot/msg/Limits
    Limits = build_message(parse_message("float32 max_speed\n", "inproc_robot", "Limits"))
    spec = parse_service(SET_LIMITS, "inproc_robot", "SetLimits")
    server = srvwire.Server()
    with pytest.raises(RegistrationError) as excinfo:
        server.add_service("/other", build_service(spec, lambda type_: Limits), lambda r: {})
    assert str(excinfo.value) == (
        "cannot register /other: two different definitions of inproc_robot/msg/Limits: the "
        "class inproc_robot.msg.Limits given for /set_limits and the class "
        "inproc_robot.msg.Limits given for /other (declaration 1: 'float64 max_speed 1.0' "
        "against 'float32 max_speed'); a type name has one definition per process"
    )


async def test_a_type_written_by_hand_and_not_described_is_an_error() -> None:
    class Point(pydantic.BaseModel):
        x: int = 0

    class Custom:  # a service type with no interface file behind it
        Request = Point
        Response = Point

    server = srvwire.Server()
    server.add_service("/custom", Custom, lambda request: request)
    transport = srvwire.MemoryTransport()
    async with (
        srvwire.serve(server, "127.0.0.1", 0, transport=transport) as running,
        srvwire.connect(running.url, transport=transport, timeout=scaled(5)) as client,
    ):
        assert client.services == {"/custom": "Custom"}
        with pytest.raises(InterfaceNotFoundError) as excinfo:
            await client.call("/custom", {"x": 1})
    assert str(excinfo.value) == (
        f"cannot type the calls of /custom: Custom is not on the local search path, and the "
        f"server {running.url} does not describe it"
    )


HUGE_SRV = "int32 a\n---\nint32[4294967295] values\n"
NESTED_SRV = "huge_pkg/Row[100000] rows\n---\nint32[16] small\n"


async def test_a_described_type_with_more_fixed_values_than_a_message_can_carry_is_refused() -> (
    None
):
    # Made without the field (a reply that leaves it out), an instance would hold every value:
    # 4294967295 from one line, or 100000 rows of 100 from two. No message of such a type fits
    # in the client's max_message_size, so the client refuses to build it, naming the field.
    row = build_message(parse_message("float64[100] cells\n", "huge_pkg", "Row"))
    server = srvwire.Server(max_message_size=None)  # /rows's request is past the server's too
    huge = build_service(parse_service(HUGE_SRV, "huge_pkg", "Huge"))
    server.add_service("/huge", huge, lambda request: {})
    nested = build_service(parse_service(NESTED_SRV, "huge_pkg", "Rows"), lambda _: row)
    server.add_service("/rows", nested, lambda request: {})
    async with srvwire.serve(server, "127.0.0.1", 0) as running:
        async with srvwire.connect(running.url, timeout=scaled(5)) as client:
            with pytest.raises(InterfaceError) as excinfo:
                await client.call("/huge", {"a": 1})
            assert str(excinfo.value) == (
                f"the server {running.url} describes huge_pkg/Huge_Response, which holds "
                "4294967295 values, 4294967295 of them in the field 'values' "
                "(int32[4294967295]), more than max_message_size=1048576 can carry; refused, "
                "so that a reply that leaves them out cannot make this client hold them"
            )
            with pytest.raises(InterfaceError) as excinfo:
                await client.service_type("/rows")
            assert "10000000 values, 10000000 of them in the field 'rows' (huge_pkg/Row[" in (
                str(excinfo.value)
            )
        # Under a limit that lets such messages through, the type is built, allocating nothing.
        async with srvwire.connect(
            running.url, timeout=scaled(5), max_message_size=2**24
        ) as client:
            Rows = await client.service_type("/rows")
            assert Rows.Response().small == [0] * 16


async def test_a_described_topic_or_action_type_with_too_many_fixed_values_is_refused() -> None:
    # The same limit for the types of topics and actions built from the server's description:
    # a message received or a goal's outcome that leaves the field out would hold every value.
    from srvwire.models import build_action
    from srvwire.parser import parse_action

    server = srvwire.Server()
    server.topic("/huge", build_message(parse_message(HUGE_MSG, "huge_pkg", "Scan")))
    action = build_action(parse_action(HUGE_ACTION, "huge_pkg", "Sweep"))

    async def sweep(goal: Any, handle: Any) -> Any:
        return {}

    server.add_action("/sweep", action, sweep)
    async with srvwire.serve(server, "127.0.0.1", 0) as running:
        async with srvwire.connect(running.url, timeout=scaled(5)) as client:
            await client.wait_for_topic("/huge")
            with pytest.raises(InterfaceError) as excinfo:
                await client.topic_type("/huge")
            assert str(excinfo.value) == (
                f"the server {running.url} describes huge_pkg/Scan, which holds 4294967296 "
                "values, 4294967295 of them in the field 'ranges' (float32[4294967295]), more "
                "than max_message_size=1048576 can carry; refused, so that a reply that leaves "
                "them out cannot make this client hold them"
            )
            with pytest.raises(InterfaceError) as excinfo:
                await client.send_goal("/sweep", {"order": 1})
            assert "holds 4294967295 values, 4294967295 of them in the field 'seen'" in str(
                excinfo.value
            )


HUGE_MSG = "int32 count\nfloat32[4294967295] ranges\n"
HUGE_ACTION = "int32 order\n---\nint32[4294967295] seen\n---\nint32 step\n"


def test_a_description_with_bad_names_or_text_is_an_interface_error() -> None:
    from srvwire.calls import ServiceTypes
    from srvwire.errors import InterfaceError

    def nowhere(name: str) -> Any:
        raise InterfaceNotFoundError(name, f"no {name} here")

    types = ServiceTypes(nowhere, nowhere, TypeRegistry())
    good = {"odd_pkg/srv/Go": "int32 a\n---\n", "odd/msg/too/many": "x", "nameless": "y"}
    assert types.remote("/go", "odd_pkg/srv/Go", good, "server ws://x").service.type_name == (
        "odd_pkg/srv/Go"
    )
    broken = {"odd_pkg/srv/Stop": "int32 a\n---\nodd_pkg/Loop l\n", "odd_pkg/msg/Loop": "Loop l\n"}
    with pytest.raises(InterfaceError) as excinfo:
        types.remote("/stop", "odd_pkg/srv/Stop", broken, "server ws://x")
    assert str(excinfo.value) == (
        "the server ws://x describes a message that nests itself: odd_pkg/msg/Loop -> "
        "odd_pkg/msg/Loop"
    )
    with pytest.raises(InterfaceError) as excinfo:
        types.remote("/bad", "odd_pkg/srv/Bad", {"odd_pkg/srv/Bad": "int32\n"}, "server ws://x")
    assert str(excinfo.value) == (
        "server ws://x:2:1: a service needs a '---' line between the request and the response; "
        "found none"
    )


# --- a local type that differs from the server's -----------------------------------------------

SPEED_APP = """
import srvwire

loader = srvwire.InterfaceLoader([{folder!r}])
SetSpeed = loader.load_service("{package}/srv/SetSpeed")
server = srvwire.Server()


@server.service("/set_speed", SetSpeed)
def set_speed(request):
    return {{"ok": True}}
{older}
"""

OLDER = """
server.registry.fingerprints = dict  # as a server from before fingerprints: none announced
"""


def speed_package(root: Path, package: str, limits: str) -> Path:
    write(root, f"{package}/msg/Limits.msg", limits)
    write(root, f"{package}/srv/SetSpeed.srv", "# How fast.\nLimits limits\n---\nbool ok\n")
    return root


def serving_speed(tmp_path: Path, package: str, limits: str, older: str = "") -> Iterator[str]:
    interfaces = speed_package(tmp_path / "server_interfaces", package, limits)
    app = write(
        tmp_path,
        "speed_app.py",
        SPEED_APP.format(folder=str(interfaces), package=package, older=older),
    )
    yield from serving_app(app)


def counting_descriptions(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Record each rpc.discover a client asks for."""
    asked: list[str] = []
    methods = srvwire.Client._methods

    async def counted(self: srvwire.Client, *args: Any) -> Any:
        asked.append(self.url)
        return await methods(self, *args)

    monkeypatch.setattr(srvwire.Client, "_methods", counted)
    return asked


async def test_a_local_type_that_differs_from_the_servers_is_an_error_before_the_call(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, no_path_variable: None
) -> None:
    # The client has fp_robot on its own path, with another Limits: its local SetSpeed is
    # found first, and the fingerprint the server announced says it is not the server's.
    mine = speed_package(tmp_path / "client_interfaces", "fp_robot", "float64 max_speed\n")
    loader = InterfaceLoader([mine])
    asked = counting_descriptions(monkeypatch)
    for url in serving_speed(tmp_path, "fp_robot", "float32 max_speed\nfloat32 max_turn\n"):
        async with srvwire.connect(
            url, timeout=scaled(10), type_resolver=loader.load_service
        ) as client:
            with pytest.raises(InterfaceConflictError) as excinfo:
                await client.call("/set_speed", {"limits": {"max_speed": 1.0}})
            assert asked == [url]  # the description, asked for only to say what differs
            # A typed request of the local class is refused the same way: nothing is sent.
            with pytest.raises(InterfaceConflictError):
                await client.call(
                    "/set_speed", loader.load_service("fp_robot/srv/SetSpeed").Request()
                )
    assert str(excinfo.value) == (
        f"two different definitions of fp_robot/msg/Limits: {mine / 'fp_robot/msg/Limits.msg'} "
        f"and server {url} (declaration 1: 'float64 max_speed' against 'float32 max_speed'); "
        "a type name has one definition per process"
    )


async def test_the_same_local_type_is_compared_without_a_round_trip(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, no_path_variable: None
) -> None:
    # Comments differ; the definitions do not.
    mine = speed_package(tmp_path / "client_interfaces", "fp_same", "float32 max_speed  # m/s\n")
    loader = InterfaceLoader([mine])
    SetSpeed = loader.load_service("fp_same/srv/SetSpeed")
    asked = counting_descriptions(monkeypatch)
    for url in serving_speed(tmp_path, "fp_same", "# Limits.\nfloat32 max_speed\n"):
        async with srvwire.connect(
            url, timeout=scaled(10), type_resolver=loader.load_service
        ) as client:
            assert (await client.call("/set_speed", {"limits": {"max_speed": 1.0}})).ok
            assert (await client.call("/set_speed", SetSpeed.Request())).ok
            link = client._link
            assert link is not None
            assert link.fingerprints == {"/set_speed": fingerprint(full_definition(SetSpeed) or {})}
            assert link.verified == {("/set_speed", SetSpeed)}
    assert asked == []  # no rpc.discover: the types are local, and the fingerprints agree


async def test_a_server_that_announces_no_fingerprint_is_not_compared(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, no_path_variable: None
) -> None:
    # The local Limits differs, but nothing says so: the call goes as before fingerprints.
    mine = speed_package(tmp_path / "client_interfaces", "fp_older", "float64 max_speed\n")
    loader = InterfaceLoader([mine])
    asked = counting_descriptions(monkeypatch)
    for url in serving_speed(tmp_path, "fp_older", "float32 max_speed\n", OLDER):
        async with srvwire.connect(
            url, timeout=scaled(10), type_resolver=loader.load_service
        ) as client:
            assert (await client.call("/set_speed", {"limits": {"max_speed": 1.0}})).ok
            assert client._link is not None and client._link.fingerprints == {}
    assert asked == []


# --- a topic's local type that differs from the server's ----------------------------------------

STATUS_APP = """
import srvwire

loader = srvwire.InterfaceLoader([{folder!r}])
Status = loader.load_message("{package}/msg/Status")
server = srvwire.Server()
AddTwoInts = srvwire.load_service("example_interfaces/srv/AddTwoInts")
server.add_service("/add", AddTwoInts, lambda request: {{}})
status = server.topic("/status", Status, qos={{"durability": "transient_local", "depth": 1}})
status.publish(Status(name="r1", battery=0.5))
server.subscription("/report", Status)(lambda message: None)
{older}
"""

OLDER_TOPICS = """
import srvwire.topics

described = srvwire.topics.Topic.describe
srvwire.topics.Topic.describe = lambda topic: {
    key: value for key, value in described(topic).items() if key != "fingerprint"
}  # as a server from before topics had fingerprints
"""

TOPIC_STATUS = "# What the robot says.\nstring name\nfloat64 battery\n"


def serving_status(tmp_path: Path, package: str, older: str = "") -> Iterator[str]:
    interfaces = tmp_path / "server_interfaces"
    write(interfaces, f"{package}/msg/Status.msg", TOPIC_STATUS)
    app = STATUS_APP.format(folder=str(interfaces), package=package, older=older)
    yield from serving_app(write(tmp_path, "status_app.py", app))


async def test_a_topics_local_type_that_differs_from_the_servers_is_an_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, no_path_variable: None
) -> None:
    # The client's Status has one more field, with a default: a message of the server's would
    # validate as it, and show a value the server never sent.
    mine = tmp_path / "client_interfaces"
    local = write(mine, "fp_topics/msg/Status.msg", TOPIC_STATUS + "uint8 mode 7\n")
    asked = counting_descriptions(monkeypatch)
    for url in serving_status(tmp_path, "fp_topics"):
        async with srvwire.connect(url, timeout=scaled(10), search_path=[mine]) as client:
            await client.wait_for_topic("/status")
            with pytest.raises(InterfaceConflictError) as excinfo:
                async for message in client.subscribe("/status"):
                    pytest.fail(f"a message typed by the wrong class arrived: {message!r}")
            assert asked == [url]  # the description, asked for only to say what differs
            with pytest.raises(InterfaceConflictError) as published:
                await client.publish("/report", {"name": "r2"}, ack=True)
            with pytest.raises(InterfaceConflictError):  # the class itself: the same
                await client.subscribe(
                    "/status", srvwire.load_message("fp_topics/msg/Status", search_path=[mine])
                ).start()
            with pytest.raises(InterfaceConflictError):
                await client.topic_type("/status")
    assert (
        str(excinfo.value)
        == str(published.value)
        == (
            f"two different definitions of fp_topics/msg/Status: {local} and server {url} "
            "(declaration 3: 'uint8 mode 7' against nothing); a type name has one definition per "
            "process"
        )
    )


async def test_a_topics_same_local_type_is_compared_without_a_round_trip(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, no_path_variable: None
) -> None:
    mine = tmp_path / "client_interfaces"
    write(mine, "fp_topics_same/msg/Status.msg", "string name  # which robot\nfloat64 battery\n")
    Status = srvwire.load_message("fp_topics_same/msg/Status", search_path=[mine])
    asked = counting_descriptions(monkeypatch)
    for url in serving_status(tmp_path, "fp_topics_same"):
        async with srvwire.connect(url, timeout=scaled(10), search_path=[mine]) as client:
            await client.wait_for_topic("/status")
            assert client._topics["/status"]["fingerprint"] == fingerprint(
                full_definition(Status) or {}
            )
            async with client.subscribe("/status") as sub:
                message = await sub.receive()
            assert type(message) is Status and (message.name, message.battery) == ("r1", 0.5)
            await client.publish("/report", {"name": "r2"}, ack=True)
    assert asked == []  # no rpc.discover: the type is local, and the fingerprints agree


async def test_a_server_that_announces_no_topic_fingerprint_is_not_compared(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, no_path_variable: None
) -> None:
    # The local Status differs, but nothing says so: its messages arrive as before fingerprints.
    mine = tmp_path / "client_interfaces"
    write(mine, "fp_topics_older/msg/Status.msg", TOPIC_STATUS + "uint8 mode 7\n")
    asked = counting_descriptions(monkeypatch)
    for url in serving_status(tmp_path, "fp_topics_older", OLDER_TOPICS):
        async with srvwire.connect(url, timeout=scaled(10), search_path=[mine]) as client:
            await client.wait_for_topic("/status")
            assert "fingerprint" not in client._topics["/status"]
            async with client.subscribe("/status") as sub:
                message = await sub.receive()
            assert (message.name, message.mode) == ("r1", 7)
    assert asked == []


TURN_APP = """
import srvwire

Turn = srvwire.InterfaceLoader([{folder!r}]).load_action("fp_turns/action/Turn")
AddTwoInts = srvwire.load_service("example_interfaces/srv/AddTwoInts")
server = srvwire.Server()
server.add_service("/add", AddTwoInts, lambda request: {{}})


@server.action("/turn", Turn)
async def turn(goal, handle):
    return {{"done": True}}
"""


async def test_an_actions_local_type_found_by_name_that_differs_is_an_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, no_path_variable: None
) -> None:
    # No action_type: the client finds its own copy by the advertised name, and compares it.
    server_interfaces = tmp_path / "server_interfaces"
    write(server_interfaces, "fp_turns/action/Turn.action", "int32 turns\n---\nbool done\n---\n")
    mine = tmp_path / "client_interfaces"
    local = write(mine, "fp_turns/action/Turn.action", "int64 turns\n---\nbool done\n---\n")
    app = write(tmp_path, "turn_app.py", TURN_APP.format(folder=str(server_interfaces)))
    for url in serving_app(app):
        async with srvwire.connect(url, timeout=scaled(10), search_path=[mine]) as client:
            with pytest.raises(InterfaceConflictError) as excinfo:
                await client.send_goal("/turn", {"turns": 1})
    assert str(excinfo.value) == (
        f"two different definitions of fp_turns/action/Turn: {local} and server {url} "
        "(declaration 1: 'int64 turns' against 'int32 turns'); a type name has one definition "
        "per process"
    )
