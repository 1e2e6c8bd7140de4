"""Testing the tutorial's robot with srvwire's pytest plugin, and no fixtures of your own.

``conftest.py``, beside this file, says which server to test: the plugin serves it for each
test, in this process with no port, and hands the test a client or a raw connection to it.
Run the tests with::

    python -m pytest examples/testing_with_the_plugin.py

They need pytest and pytest-asyncio with ``asyncio_mode = "auto"``, as srvwire's own
``pyproject.toml`` sets it.
"""

from __future__ import annotations

import logging
from typing import Any

import pytest

import srvwire
from srvwire.testing import Wire

Trigger = srvwire.load_service("std_srvs/srv/Trigger")
SetBool = srvwire.load_service("std_srvs/srv/SetBool")

JOINTS = ["joint_0", "joint_1", "joint_2", "joint_3", "joint_4"]


# --8<-- [start:client]
async def test_a_command_then_the_state(srvwire_client: srvwire.Client) -> None:
    move = {"command_type": "move", "parameters": [0.1, 0.2, 0.3, 0.4, 0.5]}
    assert (await srvwire_client.call("/execute_robot_command", move)).success

    response = await srvwire_client.call("/get_robot_state", {"query_type": "position"})
    assert (response.names, response.values) == (JOINTS, [0.1, 0.2, 0.3, 0.4, 0.5])


async def test_a_misspelt_service_name(srvwire_client: srvwire.Client) -> None:
    with pytest.raises(srvwire.ServiceNotFound) as caught:
        await srvwire_client.call("/get_robot_status", {"query_type": "status"})

    assert caught.value.data["candidates"] == ["/get_robot_state"]


# --8<-- [end:client]


# --8<-- [start:action]
async def test_a_short_calibration(srvwire_client: srvwire.Client) -> None:
    goal = await srvwire_client.send_goal("/calibrate", {"duration": 0.05})
    progress = [feedback.progress async for feedback in goal.feedback()]
    outcome = await goal.result()

    assert progress == sorted(progress)  # the latest each time it is read: maybe not all five
    assert (outcome.status, outcome.result.joints_done) == ("succeeded", 5)


# --8<-- [end:action]


# --8<-- [start:sync]
def test_with_the_blocking_client(srvwire_sync_client: srvwire.sync.Client) -> None:
    stop = srvwire_sync_client.proxy("/execute_robot_command")
    assert stop(command_type="stop").message == "Robot stopped"

    response = srvwire_sync_client.call("/get_robot_state", {"query_type": "status"})
    assert response.message == "Robot status: STOPPED"


# --8<-- [end:sync]


# --8<-- [start:wire]
async def test_the_reply_on_the_wire(srvwire_wire: Wire) -> None:
    reply = await srvwire_wire.request("/get_robot_state", {"query_type": "status"}, id=7)

    assert reply["id"] == 7
    assert reply["result"]["message"] == "Robot status: IDLE"


async def test_a_request_that_is_not_json(srvwire_wire: Wire) -> None:
    reply = await srvwire_wire.call('{"jsonrpc": "2.0", "id": 1, "method": ')

    assert (reply["id"], reply["error"]["code"]) == (None, -32700)


# --8<-- [end:wire]


# --8<-- [start:websockets]
@pytest.mark.srvwire(transport="websockets")
async def test_over_a_real_socket(
    srvwire_running: srvwire.RunningServer, srvwire_client: srvwire.Client
) -> None:
    assert srvwire_running.url.startswith("ws://127.0.0.1:")  # a free port of its own

    response = await srvwire_client.call("/get_robot_state", {"query_type": "position"})
    assert response.names == JOINTS


# --8<-- [end:websockets]


# --8<-- [start:handler_errors]
async def test_a_handler_that_raises(
    srvwire_server: srvwire.Server,
    srvwire_client: srvwire.Client,
    srvwire_handler_errors: list[logging.LogRecord],
) -> None:
    async def home(request: Any, response: Any) -> Any:
        raise RuntimeError("the arm is stuck")

    srvwire_server.add_service("/home", Trigger, home)  # the server being served
    with pytest.raises(srvwire.InternalError):
        await srvwire_client.call("/home")

    [record] = srvwire_handler_errors  # what the server logged, with the traceback
    assert record.exc_info is not None and str(record.exc_info[1]) == "the arm is stuck"
    srvwire_handler_errors.clear()  # expected: without this, the test fails


# --8<-- [end:handler_errors]


# --8<-- [start:credentials]
class TestTheMotors:
    """A server with authentication: the marker gives the fixtures' clients a token."""

    @pytest.fixture
    def srvwire_server(self) -> srvwire.Server:  # this class's server, not conftest.py's
        operator = srvwire.Identity("operator", scopes={"robot:write"})
        server = srvwire.Server(auth=srvwire.TokenAuth({"op-token": operator, "view": "viewer"}))

        @server.service("/motors", SetBool, scopes={"robot:write"})
        async def motors(request: Any) -> Any:
            return {"success": True, "message": "on" if request.data else "off"}

        return server

    @pytest.mark.srvwire(token="op-token")
    async def test_the_operator_turns_them_on(self, srvwire_client: srvwire.Client) -> None:
        assert (await srvwire_client.call("/motors", {"data": True})).message == "on"

    @pytest.mark.srvwire(token="view")
    async def test_a_viewer_may_not(self, srvwire_client: srvwire.Client) -> None:
        assert "/motors" not in srvwire_client.services  # not even listed to it
        with pytest.raises(srvwire.PermissionDenied):
            await srvwire_client.call("/motors", {"data": True}, srv_type=SetBool)


# --8<-- [end:credentials]
