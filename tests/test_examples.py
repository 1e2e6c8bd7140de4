"""The robot-state tutorial's examples, run for real against each other.

The server runs as a child process on a free port (it logs its URL once it listens); the
client runs in this process through its ``run``/``main`` functions, so a test can watch each
response as it arrives — and kill the server in the middle of the sequence.
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib.util
import logging
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from types import ModuleType
from typing import IO, Any

import pytest

from srvwire import connect
from srvwire.errors import DeadlineExceeded, ServiceUnavailable
from srvwire.server import serve
from srvwire.transports.memory import MemoryTransport
from support import ROOT, scaled

EXAMPLES = ROOT / "examples"
URL_LINE = re.compile(r"serving \d+ services?(?: and \d+ actions?)? on (ws://\S+)")


def load_example(name: str) -> ModuleType:
    """Import ``examples/<name>.py`` as a module of its own."""
    spec = importlib.util.spec_from_file_location(f"example_{name}", EXAMPLES / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


server_example = load_example("robot_state_server")
client_example = load_example("robot_command_client")
publisher_example = load_example("joint_state_publisher")


class ServerProcess:
    """``robot_state_server.py`` running in a child process, its log collected as it comes."""

    def __init__(self, *args: str) -> None:
        self.process = subprocess.Popen(
            [sys.executable, str(EXAMPLES / "robot_state_server.py"), *args],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        self.lines: list[str] = []
        self.done = False  # whether its stderr has ended
        self.changed = threading.Condition()
        assert self.process.stderr is not None
        self.reader = threading.Thread(target=self._collect, args=(self.process.stderr,))
        self.reader.start()

    def _collect(self, stream: IO[str]) -> None:
        for line in stream:
            with self.changed:
                self.lines.append(line)
                self.changed.notify_all()
        with self.changed:  # the server exited: wake whoever still waits for a line
            self.done = True
            self.changed.notify_all()

    def wait_for_log(self, pattern: re.Pattern[str], timeout: float) -> re.Match[str]:
        """Wait until the server logs a line matching ``pattern``; fail after ``timeout``."""
        deadline = time.monotonic() + timeout
        with self.changed:
            while (match := pattern.search("".join(self.lines))) is None:
                remaining = deadline - time.monotonic()
                if remaining <= 0 or self.done:
                    pytest.fail(
                        f"the example server did not log {pattern.pattern!r} within "
                        f"{timeout:g} s (exit status {self.process.poll()}); its log:\n"
                        + "".join(self.lines)
                    )
                self.changed.wait(remaining)
        return match

    def kill(self) -> None:
        if self.process.poll() is None:
            self.process.kill()
        self.process.wait()
        self.reader.join()  # the pipe ends with the process
        assert self.process.stderr is not None
        self.process.stderr.close()


@dataclass
class RunningServer:
    """The example server, listening at ``url``."""

    server: ServerProcess
    url: str

    @property
    def process(self) -> subprocess.Popen[str]:
        return self.server.process

    def wait_for_line(self, text: str) -> None:
        """Wait until the server has logged ``text``: it logs before it replies, but its log
        comes through a pipe that the test's reader thread may not have read yet."""
        self.server.wait_for_log(re.compile(re.escape(text)), scaled(10))


@contextlib.contextmanager
def start_server() -> Iterator[RunningServer]:
    """Run ``robot_state_server.py --port 0`` for the duration of the block, then kill it."""
    server = ServerProcess("--port", "0")
    try:
        match = server.wait_for_log(URL_LINE, scaled(10))
        yield RunningServer(server, match.group(1))
    finally:
        server.kill()


@pytest.fixture
def robot_server() -> Iterator[RunningServer]:
    with start_server() as running:
        yield running


# --- the examples against each other ----------------------------------------------------------


async def test_the_demo_sequence(robot_server: RunningServer) -> None:
    seen: list[tuple[Any, Any]] = []
    status = await client_example.run(
        robot_server.url,
        scaled(5),
        on_response=lambda step, response: seen.append((step, response)),
        calibration_time=0,  # the services only: the action has tests of its own below
    )
    assert status == 0
    asked = [step.describe() for step, _ in seen]
    assert asked == [
        "query position",
        "query status",
        "query configuration",
        "command move [1.0, 0.5, -0.5, 0.0, 0.3]",
        "query position",
        "command stop",
        "command calibrate",
        "query status",
    ]
    answers = [response.model_dump() for _, response in seen]
    joints = ["joint_0", "joint_1", "joint_2", "joint_3", "joint_4"]
    assert answers == [
        {
            "success": True,
            "message": "Current joint positions",
            "values": [0.0] * 5,
            "names": joints,
        },
        {
            "success": True,
            "message": "Robot status: IDLE",
            "values": [1.0],
            "names": ["is_calibrated"],
        },
        {
            "success": True,
            "message": "Robot configuration",
            "values": [5.0, 5.0, 10.0],
            "names": ["joint_count", "max_speed", "max_torque"],
        },
        {
            "success": True,
            "message": "Moving to the requested joint positions",
            "execution_time": 1.0,
        },
        {
            "success": True,
            "message": "Current joint positions",
            "values": [1.0, 0.5, -0.5, 0.0, 0.3],
            "names": joints,
        },
        {"success": True, "message": "Robot stopped", "execution_time": 0.1},
        {"success": True, "message": "Robot calibrated", "execution_time": 5.0},
        {
            "success": True,
            "message": "Robot status: CALIBRATED",
            "values": [1.0],
            "names": ["is_calibrated"],
        },
    ]
    robot_server.wait_for_line("query 'position'")
    robot_server.wait_for_line("command 'move'")


async def test_the_joint_state_publisher_moves_the_robot(
    robot_server: RunningServer, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="joint_state_publisher")
    await publisher_example.publish(robot_server.url, rate=100.0, count=3)
    last = publisher_example.joint_state(2).position
    assert caplog.messages[-1] == f"the robot now reports {last}"
    assert [m for m in caplog.messages if m.startswith("published")] == [
        f"published joint states {publisher_example.joint_state(n).position}" for n in range(3)
    ]
    async with connect(robot_server.url, timeout=scaled(5)) as client:
        response = await client.call("/get_robot_state", {"query_type": "position"})
        assert response.values == last  # the state lives in the server, not the connection
        echo = client.subscribe("/joint_states")  # transient_local: the latest, at once
        async for message in echo:
            assert message.position == last
            break


async def test_the_server_ignores_joint_states_of_another_robot(
    node: Any, caplog: pytest.LogCaptureFixture
) -> None:
    JointState = server_example.JointState
    node.on_joint_states(JointState(name=["a", "b"], position=[1.0, 2.0]))
    assert node.state.joint_positions == [0.0] * 5
    assert caplog.messages == ["ignoring a joint state with 2 positions; the robot has 5 joints"]
    node.on_joint_states(JointState(position=[1.0, 2.0, 3.0, 4.0, 5.0]))
    assert (await query(node, "position")).values == [1.0, 2.0, 3.0, 4.0, 5.0]


def test_the_client_logs_each_answer(
    robot_server: RunningServer, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level("INFO", logger="robot_command_client")
    argv = ["--url", robot_server.url, "--timeout", str(scaled(5)), "--calibration-time", "0.5"]
    assert client_example.main(argv) == 0
    lines = [record.getMessage() for record in caplog.records]
    assert lines[0] == "query position".ljust(40) + (
        " -> ok: Current joint positions "
        "[joint_0=0.0, joint_1=0.0, joint_2=0.0, joint_3=0.0, joint_4=0.0]"
    )
    assert lines[3] == "command move [1.0, 0.5, -0.5, 0.0, 0.3]".ljust(40) + (
        " -> ok: Moving to the requested joint positions (took 1.0 s)"
    )
    assert lines[7] == "query status".ljust(40) + (
        " -> ok: Robot status: CALIBRATED [is_calibrated=1.0]"
    )
    # Then the action: accepted, its progress (the latest each time it is read), its result.
    assert lines[8] == "action calibrate (0.5 s)".ljust(40) + " -> accepted"
    progress = lines[9:-1]
    assert progress and all(line.startswith("  calibrating joint_") for line in progress)
    assert lines[-1] == "action calibrate".ljust(40) + (
        " -> succeeded: Robot calibrated (5 joints done)"
    )


PORT = re.compile(r"(ws://127\.0\.0\.1:)\d+")


def tutorial_demo_transcript() -> str:
    """The ``make demo`` output the tutorial shows: the ``text`` block after ``make demo``."""
    tutorial = (ROOT / "docs" / "tutorial.md").read_text(encoding="utf-8")
    match = re.search(r"```sh\nmake demo\n```\n\n```text\n(.*?)```\n", tutorial, re.DOTALL)
    assert match, "docs/tutorial.md no longer shows `make demo` and its output"
    return match.group(1)


def test_make_demo_runs_the_whole_tutorial() -> None:
    result = subprocess.run(
        [sys.executable, str(EXAMPLES / "demo.py")],
        capture_output=True,
        text=True,
        timeout=scaled(30),
        check=False,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    assert result.stderr == ""
    # What docs/tutorial.md shows is what the demo prints, but for the free port it picked.
    assert PORT.sub(r"\g<1>PORT", result.stdout) == PORT.sub(
        r"\g<1>PORT", tutorial_demo_transcript()
    )


def test_the_url_is_read_from_the_server_log_whatever_the_count(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.syspath_prepend(str(EXAMPLES))  # demo.py imports robot_command_client
    demo = load_example("demo")
    for line in (
        "INFO srvwire.server: serving 1 service on ws://127.0.0.1:1234",
        "INFO srvwire.server: serving 2 services on ws://127.0.0.1:1234",
        "INFO srvwire.server: serving 2 services and 1 action on ws://127.0.0.1:1234",
    ):
        for pattern in (demo.URL_LINE, URL_LINE):
            match = pattern.search(line)
            assert match and match.group(1) == "ws://127.0.0.1:1234", (pattern, line)


def sync_client_transcript() -> str:
    """What docs/sync.md shows ``python examples/sync_client.py`` printing."""
    page = (ROOT / "docs" / "sync.md").read_text(encoding="utf-8")
    match = re.search(
        r"\npython examples/sync_client.py\n```\n\n```text\n(.*?)```\n",
        page,
        re.DOTALL,
    )
    assert match, "docs/sync.md no longer shows what examples/sync_client.py prints"
    return match.group(1)


def test_the_blocking_client_script(robot_server: RunningServer) -> None:
    result = subprocess.run(
        [sys.executable, str(EXAMPLES / "sync_client.py"), "--url", robot_server.url],
        capture_output=True,
        text=True,
        timeout=scaled(30),
        check=False,
    )
    assert (result.returncode, result.stderr) == (0, "")
    assert result.stdout == sync_client_transcript()
    robot_server.wait_for_line("command 'move'")


def test_the_blocking_topics_and_action_script(
    robot_server: RunningServer, capsys: pytest.CaptureFixture[str]
) -> None:
    load_example("sync_topics").run(robot_server.url, scaled(5), duration=0.5)
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "joint states: [0.1, 0.2, 0.3, 0.4, 0.5]"  # published, read back
    assert lines[-1] == "succeeded: Robot calibrated"
    every = [f"calibrating joint_{i} ({i * 20}%)" for i in range(5)]
    feedback = lines[1:-1]  # the latest each time: a slow reader may skip some, in order
    assert feedback and feedback == [line for line in every if line in feedback]
    robot_server.wait_for_line("calibrate -> Robot calibrated")


def test_the_blocking_client_script_without_a_server() -> None:
    with socket.socket() as unused:
        unused.bind(("127.0.0.1", 0))
        url = f"ws://127.0.0.1:{unused.getsockname()[1]}"
        result = subprocess.run(
            [sys.executable, str(EXAMPLES / "sync_client.py"), "--url", url],
            capture_output=True,
            text=True,
            timeout=scaled(30),
            check=False,
        )
    assert (result.returncode, result.stdout) == (1, "")
    assert result.stderr.startswith(f"ServiceUnavailable: cannot connect to {url}: ")


# --- the client when things go wrong ---------------------------------------------------------


async def test_no_server(caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch) -> None:
    reported: list[BaseException] = []
    report_failure = client_example.report_failure

    def recording_report_failure(exc: Any) -> None:
        reported.append(exc)
        report_failure(exc)

    monkeypatch.setattr(client_example, "report_failure", recording_report_failure)
    # A socket that is bound but does not listen: connecting to its port is refused at once.
    with socket.socket() as unused:
        unused.bind(("127.0.0.1", 0))
        url = f"ws://127.0.0.1:{unused.getsockname()[1]}"
        status = await client_example.run(url, scaled(5))
    assert status == 1
    # The client gave up because the connection was refused, not because its timeout passed
    # (a TimeoutError is an OSError too, so it is ruled out by name).
    (failure,) = reported
    assert isinstance(failure, ServiceUnavailable)
    assert isinstance(failure.__cause__, OSError), failure.__cause__
    assert not isinstance(failure.__cause__, TimeoutError), failure.__cause__
    messages = [record.getMessage() for record in caplog.records]
    assert messages[0] == (
        f"no srvwire server answered at {url}: is robot_state_server.py running?"
    )
    assert messages[1].startswith(f"ServiceUnavailable (code -32003): cannot connect to {url}")


async def test_the_server_dies_mid_sequence(
    robot_server: RunningServer, caplog: pytest.LogCaptureFixture
) -> None:
    seen: list[Any] = []

    def kill_after_first(step: Any, response: Any) -> None:
        seen.append(response)
        if len(seen) == 1:
            robot_server.process.send_signal(signal.SIGKILL)
            robot_server.process.wait()

    # A deadline far away: the pending call fails because the connection dropped (a
    # ConnectionLost, not a DeadlineExceeded), so it did not wait for the deadline.
    status = await client_example.run(robot_server.url, scaled(30), on_response=kill_after_first)
    assert status == 1
    assert len(seen) == 1
    failure = caplog.records[-1].getMessage()
    assert failure.startswith("ConnectionLost (code -32003) calling /get_robot_state: "), failure


# --- the server's handlers, in this process ---------------------------------------------------

RobotStateQuery = server_example.RobotStateQuery
RobotCommand = server_example.RobotCommand


async def query(node: Any, kind: str) -> Any:
    return await node.get_robot_state(
        RobotStateQuery.Request(query_type=kind), RobotStateQuery.Response()
    )


async def command(node: Any, kind: str, parameters: list[float] | None = None) -> Any:
    request = RobotCommand.Request(command_type=kind, parameters=parameters or [])
    return await node.execute_robot_command(request, RobotCommand.Response())


@pytest.fixture
def node() -> Any:
    return server_example.RobotStateNode()


async def test_the_calibrate_action_reports_progress_and_succeeds(node: Any) -> None:
    transport = MemoryTransport()
    async with (
        serve(server_example.build_server(node), "127.0.0.1", 0, transport=transport) as running,
        connect(running.url, transport=transport, timeout=scaled(5)) as client,
    ):
        seen: list[Any] = []
        result = await client_example.calibrate(client, scaled(0.1), on_feedback=seen.append)
    assert (result.success, result.message, result.joints_done) == (True, "Robot calibrated", 5)
    assert seen and all(type(fb) is server_example.Calibrate.Feedback for fb in seen)
    assert seen[0].current_joint == "joint_0" and seen[0].progress == 0.0
    assert [fb.progress for fb in seen] == sorted(fb.progress for fb in seen)
    assert (node.state.status, node.state.calibrated) == ("CALIBRATED", True)


async def test_the_calibrate_action_stops_when_cancelled(node: Any) -> None:
    transport = MemoryTransport()
    async with (
        serve(server_example.build_server(node), "127.0.0.1", 0, transport=transport) as running,
        connect(running.url, transport=transport, timeout=scaled(5)) as client,
    ):
        handle = await client.send_goal("/calibrate", {"duration": 60})  # a long one
        first = await anext(handle.feedback())
        assert first.current_joint == "joint_0"
        await handle.cancel()
        outcome = await handle.result()
    assert outcome.status == "canceled"
    assert outcome.result.joints_done == 0
    assert outcome.result.message == "Calibration canceled after 0 of 5 joints"
    assert (node.state.status, node.state.calibrated) == ("STOPPED", False)


async def test_a_calibration_past_its_deadline_leaves_the_robot_stopped(
    node: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The goal's deadline cancels the handler on the server (no cancel request first): the
    # robot must not stay CALIBRATING.
    ended = asyncio.Event()
    calibrate = node.calibrate

    async def watched(goal: Any, handle: Any) -> Any:
        try:
            return await calibrate(goal, handle)
        finally:
            ended.set()

    monkeypatch.setattr(node, "calibrate", watched)
    transport = MemoryTransport()
    async with (
        serve(server_example.build_server(node), "127.0.0.1", 0, transport=transport) as running,
        connect(running.url, transport=transport, timeout=scaled(5)) as client,
    ):
        handle = await client.send_goal("/calibrate", {"duration": 60}, timeout=scaled(0.3))
        await anext(handle.feedback())
        assert node.state.status == "CALIBRATING"
        with pytest.raises(DeadlineExceeded):
            await handle.result()
        await asyncio.wait_for(ended.wait(), scaled(10))
    assert (node.state.status, node.state.calibrated) == ("STOPPED", False)


async def test_a_second_calibration_waits_accepted_for_the_first(node: Any) -> None:
    transport = MemoryTransport()
    async with (
        serve(server_example.build_server(node), "127.0.0.1", 0, transport=transport) as running,
        connect(running.url, transport=transport, timeout=scaled(10)) as client,
    ):
        first = await client.send_goal("/calibrate", {"duration": 60})
        await anext(first.feedback())  # the first is calibrating
        second = await client.send_goal("/calibrate", {"duration": scaled(0.1)})
        await client.call("/get_robot_state", {"query_type": "status"})  # a round trip
        assert second.status == "accepted"  # waiting its turn, not executing
        await first.cancel()
        assert (await first.result()).status == "canceled"
        outcome = await second.result()
    assert (outcome.status, outcome.result.joints_done) == ("succeeded", 5)
    assert (node.state.status, node.state.calibrated) == ("CALIBRATED", True)


async def test_shutting_the_robot_down_stops_a_calibration_with_its_result(node: Any) -> None:
    transport = MemoryTransport()
    running = await serve(server_example.build_server(node), "127.0.0.1", 0, transport=transport)
    async with connect(running.url, transport=transport, timeout=scaled(10)) as client:
        handle = await client.send_goal("/calibrate", {"duration": 60})
        await anext(handle.feedback())
        closing = asyncio.create_task(running.close())
        outcome = await handle.result()  # asked to stop, it says how far it got
        await closing
    assert outcome.status == "canceled"
    assert outcome.result.message == "Calibration canceled after 0 of 5 joints"
    assert (node.state.status, node.state.calibrated) == ("STOPPED", False)


async def test_query_position(node: Any) -> None:
    response = await query(node, "position")
    assert response.success
    assert response.message == "Current joint positions"
    assert response.values == [0.0, 0.0, 0.0, 0.0, 0.0]
    assert response.names == ["joint_0", "joint_1", "joint_2", "joint_3", "joint_4"]


async def test_query_status(node: Any) -> None:
    response = await query(node, "status")
    assert (response.success, response.message) == (True, "Robot status: IDLE")
    assert (response.values, response.names) == ([1.0], ["is_calibrated"])
    node.state.calibrated = False
    node.state.status = "FAULT"
    response = await query(node, "status")
    assert (response.message, response.values) == ("Robot status: FAULT", [0.0])


async def test_query_configuration(node: Any) -> None:
    response = await query(node, "configuration")
    assert response.success
    assert response.values == [5.0, 5.0, 10.0]
    assert response.names == ["joint_count", "max_speed", "max_torque"]


async def test_unknown_query(node: Any) -> None:
    response = await query(node, "battery")
    assert (response.success, response.message) == (False, "Unknown query type: battery")
    assert (response.values, response.names) == ([], [])


async def test_move(node: Any) -> None:
    response = await command(node, "move", [1.0, 2.0, 3.0, 4.0, 5.0])
    assert (response.success, response.execution_time) == (True, 1.0)
    assert node.state.joint_positions == [1.0, 2.0, 3.0, 4.0, 5.0]
    assert node.state.status == "MOVING"


async def test_move_without_parameters(node: Any) -> None:
    response = await command(node, "move")
    assert (response.success, response.message) == (False, "Move command requires parameters")
    assert response.execution_time == 0.0
    assert node.state == server_example.RobotState()


@pytest.mark.parametrize("count", [1, 4, 6])
async def test_move_needs_one_position_per_joint(node: Any, count: int) -> None:
    response = await command(node, "move", [0.5] * count)
    assert not response.success
    assert response.message == (
        f"Move command needs one position per joint: expected 5, got {count}"
    )
    assert node.state == server_example.RobotState()


async def test_stop(node: Any) -> None:
    response = await command(node, "stop")
    assert (response.success, response.message, response.execution_time) == (
        True,
        "Robot stopped",
        0.1,
    )
    assert node.state.status == "STOPPED"


async def test_calibrate(node: Any) -> None:
    node.state.calibrated = False
    response = await command(node, "calibrate")
    assert (response.success, response.execution_time) == (True, 5.0)
    assert (node.state.status, node.state.calibrated) == ("CALIBRATED", True)


async def test_unknown_command(node: Any) -> None:
    response = await command(node, "dance", [1.0])
    assert (response.success, response.message) == (False, "Unknown command type: dance")
    assert node.state == server_example.RobotState()


def test_the_handlers_log_requests_and_responses(
    node: Any, caplog: pytest.LogCaptureFixture
) -> None:
    import asyncio

    caplog.set_level("INFO", logger="robot_state_server")
    asyncio.run(query(node, "status"))
    messages = [record.getMessage() for record in caplog.records]
    assert messages[0] == "query 'status' (target_frame='')"
    assert messages[1].startswith("query 'status' -> ")
    assert "Robot status: IDLE" in messages[1]
