"""Testing your own services with pytest, shown on the tutorial's robot.

The handlers are tested directly, as the async functions they are, and end to end: through
a real server on a free port and a real client, and through the same server in this process
with no socket at all. Run the tests with::

    python -m pytest examples/testing_services.py

They need pytest and pytest-asyncio with ``asyncio_mode = "auto"``, as srvwire's own
``pyproject.toml`` sets it. No test sleeps: a deadline is proved against a handler that never
answers, so running out of time is the only way the call can end.
"""

from __future__ import annotations

# --8<-- [start:imports]
import asyncio
from collections.abc import AsyncIterator
from typing import Any

import pytest
import robot_state_server

import srvwire

# Loaded from .srv files at run time, so a type checker knows only that they are services;
# `srvwire gen` writes typed classes instead, if you want mypy to check the fields.
RobotStateQuery: Any = robot_state_server.RobotStateQuery
RobotCommand: Any = robot_state_server.RobotCommand
Trigger = srvwire.load_service("std_srvs/srv/Trigger")
# --8<-- [end:imports]

JOINTS = ["joint_0", "joint_1", "joint_2", "joint_3", "joint_4"]


# --8<-- [start:direct]
async def test_move_then_read_the_positions() -> None:
    node = robot_state_server.RobotStateNode()
    move = RobotCommand.Request(command_type="move", parameters=[1.0, 0.5, -0.5, 0.0, 0.3])

    response = await node.execute_robot_command(move, RobotCommand.Response())

    assert (response.success, response.execution_time) == (True, 1.0)
    query = RobotStateQuery.Request(query_type="position")
    response = await node.get_robot_state(query, RobotStateQuery.Response())
    assert response.values == [1.0, 0.5, -0.5, 0.0, 0.3]


async def test_an_unknown_command_is_refused_without_moving() -> None:
    node = robot_state_server.RobotStateNode()
    dance = RobotCommand.Request(command_type="dance")

    response = await node.execute_robot_command(dance, RobotCommand.Response())

    assert (response.success, response.message) == (False, "Unknown command type: dance")
    assert node.state == robot_state_server.RobotState()


# --8<-- [end:direct]


# --8<-- [start:fixtures]
@pytest.fixture
def server() -> srvwire.Server:
    return robot_state_server.build_server()


@pytest.fixture
async def client(server: srvwire.Server) -> AsyncIterator[srvwire.Client]:
    async with srvwire.serve(server, "127.0.0.1", 0) as running:  # port 0: a free port
        async with srvwire.connect(running.url, timeout=5) as client:
            yield client


# --8<-- [end:fixtures]


# --8<-- [start:end_to_end]
async def test_query_over_the_wire(client: srvwire.Client) -> None:
    response = await client.call("/get_robot_state", {"query_type": "position"})

    assert response.success
    assert response.names == JOINTS


async def test_a_misspelt_service_name(client: srvwire.Client) -> None:
    with pytest.raises(srvwire.ServiceNotFound) as caught:
        await client.call("/get_robot_status", {"query_type": "status"})

    assert caught.value.data["candidates"] == ["/get_robot_state"]


async def test_a_request_that_does_not_validate(client: srvwire.Client) -> None:
    with pytest.raises(srvwire.InvalidParams) as caught:
        await client.call("/execute_robot_command", {"command_type": "move", "parameters": "fast"})

    assert [problem["path"] for problem in caught.value.errors] == ["parameters"]


# --8<-- [end:end_to_end]


# --8<-- [start:in_process]
@pytest.fixture
async def in_process(server: srvwire.Server) -> AsyncIterator[srvwire.Client]:
    transport = srvwire.MemoryTransport()  # a server and its clients in this process, no port
    async with srvwire.serve(server, "robot", 0, transport=transport) as running:
        async with srvwire.connect(running.url, transport=transport, timeout=5) as client:
            yield client


async def test_a_command_then_the_state_in_process(in_process: srvwire.Client) -> None:
    move = {"command_type": "move", "parameters": [0.1, 0.2, 0.3, 0.4, 0.5]}
    assert (await in_process.call("/execute_robot_command", move)).success

    response = await in_process.call("/get_robot_state", {"query_type": "position"})
    assert response.values == [0.1, 0.2, 0.3, 0.4, 0.5]


# --8<-- [end:in_process]


# --8<-- [start:deadline]
async def test_a_deadline_cancels_the_handler(server: srvwire.Server) -> None:
    never = asyncio.Event()  # nobody sets it: the handler cannot answer in time
    handler_cancelled = asyncio.Event()

    async def stuck(request: Any, response: Any) -> Any:
        try:
            await never.wait()
        finally:
            handler_cancelled.set()
        return response

    server.add_service("/stuck", Trigger, stuck)
    async with srvwire.serve(server, "127.0.0.1", 0) as running:
        async with srvwire.connect(running.url) as client:
            with pytest.raises(srvwire.DeadlineExceeded):
                await client.call("/stuck", timeout=0.1)

            # The deadline travelled with the call, so the server cancels the handler too.
            await asyncio.wait_for(handler_cancelled.wait(), timeout=5)


# --8<-- [end:deadline]
