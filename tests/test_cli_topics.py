"""``srvwire topic``: list, info, echo, pub and hz against a real server, through main()."""

from __future__ import annotations

import re
from collections.abc import Iterator
from typing import Any

import pytest

from srvwire.cli import main
from srvwire.cli.common import ExitCode
from srvwire.loader import load_message
from srvwire.server import Server
from test_cli import run, start_in_thread

JointState = load_message("sensor_msgs/msg/JointState")
String = load_message("std_msgs/msg/String")


class Robot:
    """A server with a topic it publishes (kept for late subscribers) and one it takes."""

    def __init__(self) -> None:
        self.server = Server(grace_period=0)
        self.chatter = self.server.topic(
            "/chatter", String, qos={"depth": 5, "durability": "transient_local"}
        )
        for n in range(5):
            self.chatter.publish(String(data=f"hello {n}"))
        self.received: list[Any] = []
        self.server.subscription("/joint_states", JointState)(self.received.append)


@pytest.fixture(scope="module")
def robot() -> Iterator[Robot]:
    robot = Robot()
    url, stop = start_in_thread(robot.server)
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("SRVWIRE_URL", url)
        yield robot
    stop()


def test_help_lists_the_topic_command(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = run(capsys, "--help")
    assert code == ExitCode.OK and "    topic " in out
    for verb in ("list", "info", "echo", "pub", "hz"):
        code, out, err = run(capsys, "topic", verb, "--help")
        assert code == ExitCode.OK and err == "" and "usage: srvwire topic " + verb in out


def test_list(capsys: pytest.CaptureFixture[str], robot: Robot) -> None:
    assert run(capsys, "topic", "list") == (0, "/chatter\n/joint_states\n", "")
    assert run(capsys, "topic", "list", "-t") == (
        0,
        "/chatter [std_msgs/msg/String]\n/joint_states [sensor_msgs/msg/JointState]\n",
        "",
    )
    assert run(capsys, "topic", "list", "-c") == (0, "2\n", "")


def test_info(capsys: pytest.CaptureFixture[str], robot: Robot) -> None:
    assert run(capsys, "topic", "info", "chatter") == (
        0,
        "Type: std_msgs/msg/String\nQoS: depth 5, reliable, transient_local\n"
        "Clients may publish: no\n",
        "",
    )
    code, out, err = run(capsys, "topic", "info", "/nothing")
    assert (code, out) == (ExitCode.SERVICE_NOT_FOUND, "")
    assert err == (
        "srvwire: error: ServiceNotFound: SERVICE_NOT_FOUND (-32601) [/nothing]: the server "
        "has no topic named /nothing (topics: /chatter, /joint_states)\n"
    )


def test_echo_prints_yaml_then_dashes(capsys: pytest.CaptureFixture[str], robot: Robot) -> None:
    assert run(capsys, "topic", "echo", "/chatter", "--once") == (0, "data: hello 0\n---\n", "")
    code, out, err = run(capsys, "topic", "echo", "/chatter", "-n", "2", "--qos-depth", "2")
    assert (code, out, err) == (0, "data: hello 3\n---\ndata: hello 4\n---\n", "")
    code, out, _ = run(
        capsys, "topic", "echo", "/chatter", "std_msgs/msg/String", "-n", "1", "--json"
    )
    assert (code, out) == (0, '{"data": "hello 0"}\n')


def test_echo_of_a_topic_that_is_not_there(
    capsys: pytest.CaptureFixture[str], robot: Robot
) -> None:
    code, out, err = run(capsys, "topic", "echo", "/nothing", "--once")
    assert (code, out) == (ExitCode.SERVICE_NOT_FOUND, "")
    assert "no topic named /nothing" in err


def test_pub_publishes_and_the_server_takes_it(
    capsys: pytest.CaptureFixture[str], robot: Robot
) -> None:
    code, out, err = run(
        capsys, "topic", "pub", "/joint_states", "{name: [joint_0], position: [0.5]}", "--once"
    )
    assert (code, err) == (0, "")
    assert out.splitlines()[:2] == [
        "publisher: beginning loop",
        "publishing #1: sensor_msgs.msg.JointState(header=std_msgs.msg.Header("
        "stamp=builtin_interfaces.msg.Time(sec=0, nanosec=0), frame_id=''), name=['joint_0'], "
        "position=[0.5], velocity=[], effort=[])",
    ]
    assert robot.received[-1].position == [0.5]  # acknowledged: the server has it
    code, out, err = run(
        capsys,
        "topic",
        "pub",
        "/joint_states",
        "sensor_msgs/msg/JointState",
        "{}",
        "-t",
        "3",
        "-r",
        "1000",
    )
    assert code == 0 and out.count("publishing #") == 3


@pytest.mark.parametrize(
    ("argv", "exit_code", "error"),
    [
        (
            ["/joint_states", "{position: [high]}", "--once"],
            ExitCode.INVALID_PARAMS,
            "srvwire: error: InvalidParams: INVALID_PARAMS (-32602) [/joint_states]: invalid "
            "message for /joint_states: message.position[0]: Input should be a valid number "
            '(data: {"errors": [{"path": "message.position[0]", "message": "Input should be a '
            'valid number", "type": "float_type"}]})\n',
        ),
        (
            ["/chatter", "{data: hi}", "--once"],
            ExitCode.OTHER_RPC_ERROR,
            "srvwire: error: PermissionDenied: PERMISSION_DENIED (-32006) [/chatter]: the "
            "server does not take "
            "messages on /chatter; only subscribe to it\n",
        ),
        (["/joint_states", "[1, 2]", "--once"], ExitCode.USAGE, None),
    ],
)
def test_pub_refused(
    capsys: pytest.CaptureFixture[str],
    robot: Robot,
    argv: list[str],
    exit_code: int,
    error: str | None,
) -> None:
    code, _, err = run(capsys, "topic", "pub", *argv)
    assert code == exit_code, err
    if error is not None:
        assert err == error


def test_hz_measures_the_rate(capsys: pytest.CaptureFixture[str], robot: Robot) -> None:
    code, out, err = run(capsys, "topic", "hz", "/chatter", "-n", "5")
    assert (code, err) == (0, "")
    assert re.fullmatch(
        r"average rate: (?:[0-9.]+|inf)\n\tmin: [0-9.]+s max: [0-9.]+s std dev: [0-9.]+s "
        r"window: 5\n",
        out,
    ), out


def test_main_returns_usage_for_a_bad_qos(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["topic", "echo", "/chatter", "--qos-reliability", "sometimes"]) == ExitCode.USAGE
