"""``srvwire action``: list, info and send_goal against a real server."""

from __future__ import annotations

import asyncio
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from typing import Any

import pytest

from srvwire import GoalHandle, GoalRejected, load_action, load_service
from srvwire.cli import ExitCode, main
from srvwire.server import Server
from support import scaled
from test_cli import start_in_thread

Fibonacci = load_action("example_interfaces/action/Fibonacci")


CANCELLED = threading.Event()  # set by /forever's handler when its client asks to cancel


@pytest.fixture(scope="module")
def url() -> Iterator[str]:
    server = Server(grace_period=0)

    @server.action("/fibonacci", Fibonacci, accept=lambda goal: goal.order < 50)
    async def fibonacci(goal: Any, handle: GoalHandle) -> Any:
        if goal.order == 13:
            raise GoalRejected("thirteen brings bad luck")
        sequence = [0, 1]
        for _ in range(goal.order - 1):
            sequence.append(sequence[-1] + sequence[-2])
            await handle.feedback({"sequence": sequence})  # returns once it went out
        if goal.order == 0:
            handle.abort()
        return {"sequence": sequence}

    @server.action("/forever", Fibonacci, cancel_grace=0)
    async def forever(goal: Any, handle: GoalHandle) -> Any:
        await handle.feedback({"sequence": [0]})
        await handle.cancelled()
        CANCELLED.set()
        await asyncio.Event().wait()  # only the grace period's end stops it

    server.add_service("/trigger", load_service("std_srvs/srv/Trigger"), lambda request: None)
    address, stop = start_in_thread(server)
    yield address
    stop()


def run(capsys: pytest.CaptureFixture[str], url: str, *argv: str) -> tuple[int, str, str]:
    capsys.readouterr()
    code = main(["action", *argv, "--url", url, "--timeout", "5"])
    out, err = capsys.readouterr()
    return code, out, err


def test_action_list_shows_only_actions(capsys: pytest.CaptureFixture[str], url: str) -> None:
    assert run(capsys, url, "list") == (ExitCode.OK, "/fibonacci\n/forever\n", "")
    code, out, _ = run(capsys, url, "list", "-t")
    assert code == ExitCode.OK
    assert out == (
        "/fibonacci [example_interfaces/action/Fibonacci]\n"
        "/forever [example_interfaces/action/Fibonacci]\n"
    )
    assert run(capsys, url, "list", "-c") == (ExitCode.OK, "2\n", "")
    capsys.readouterr()
    assert main(["service", "list", "--url", url]) == ExitCode.OK
    assert capsys.readouterr().out == "/trigger\n"


def test_action_info(capsys: pytest.CaptureFixture[str], url: str) -> None:
    code, out, err = run(capsys, url, "info", "fibonacci")
    assert (code, err) == (ExitCode.OK, "")
    assert out.startswith("Action: /fibonacci\nType: example_interfaces/action/Fibonacci\n\n")
    assert out.endswith(Fibonacci.text.rstrip("\n") + "\n")
    code, _, err = run(capsys, url, "info", "/fibonaci")
    assert code == ExitCode.SERVICE_NOT_FOUND
    assert "did you mean /fibonacci?" in err


def test_send_goal_with_feedback(capsys: pytest.CaptureFixture[str], url: str) -> None:
    code, out, err = run(capsys, url, "send_goal", "/fibonacci", "{order: 3}", "--feedback")
    assert (code, err) == (ExitCode.OK, "")
    head, rest = out.split("\nGoal accepted with ID: ", 1)
    assert head == "Sending goal:\n    order: 3\n"
    goal_id, rest = rest.split("\n", 1)
    assert len(goal_id) == 36
    # Each feedback went out before the next was given: the last one is always there.
    assert rest.endswith(
        "\nFeedback:\n    sequence:\n    - 0\n    - 1\n    - 1\n    - 2\n"
        "\nResult:\n    sequence:\n    - 0\n    - 1\n    - 1\n    - 2\n"
        "\nGoal finished with status: SUCCEEDED\n"
    )


def test_send_goal_with_the_type_and_without_feedback(
    capsys: pytest.CaptureFixture[str], url: str
) -> None:
    code, out, _ = run(
        capsys, url, "send_goal", "/fibonacci", "example_interfaces/action/Fibonacci", "{order: 1}"
    )
    assert code == ExitCode.OK
    assert "Feedback:" not in out
    assert out.endswith(
        "\nResult:\n    sequence:\n    - 0\n    - 1\n\nGoal finished with status: SUCCEEDED\n"
    )


@pytest.mark.parametrize(
    ("values", "code", "said"),
    [
        ("{order: 0}", ExitCode.SERVICE_FAILED, "Goal finished with status: ABORTED"),
        ("{order: 60}", ExitCode.SERVICE_FAILED, "GoalRejected: GOAL_REJECTED (-32007)"),
        ("{order: 13}", ExitCode.SERVICE_FAILED, "thirteen brings bad luck"),
        ("{order: x}", ExitCode.INVALID_PARAMS, "order"),
        ("[1, 2]", ExitCode.USAGE, "expected a YAML mapping"),
    ],
)
def test_send_goal_exit_codes(
    capsys: pytest.CaptureFixture[str], url: str, values: str, code: int, said: str
) -> None:
    got, out, err = run(capsys, url, "send_goal", "/fibonacci", values)
    assert got == code, out + err
    assert said in out + err


def test_send_goal_past_its_deadline(capsys: pytest.CaptureFixture[str], url: str) -> None:
    capsys.readouterr()
    code = main(["action", "send_goal", "/forever", "{}", "--url", url, "--timeout", "0.3"])
    assert code == ExitCode.DEADLINE_EXCEEDED


def test_send_goal_to_a_service_is_a_usage_error(
    capsys: pytest.CaptureFixture[str], url: str
) -> None:
    code, _, err = run(capsys, url, "send_goal", "/trigger", "{}")
    assert code == ExitCode.USAGE
    assert "/trigger is the service std_srvs/srv/Trigger, not an action: use srvwire call" in err


def interruptible() -> None:
    """In a child before it runs the command: SIGINT to its default action."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_ctrl_c_cancels_the_goal_on_the_server(url: str) -> None:
    command = [sys.executable, "-m", "srvwire", "action", "send_goal", "/forever", "{}"]
    process = subprocess.Popen(
        [*command, "--feedback", "--url", url, "--timeout", "30"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        # Ctrl-C as a terminal delivers it: a shell starts a background job (the suite run
        # with `&` from a script) with SIGINT ignored, and its children inherit that, so
        # Python would not raise KeyboardInterrupt and the goal would run to its deadline.
        preexec_fn=interruptible,
    )
    try:
        assert process.stdout is not None
        line = process.stdout.readline()
        while line and line != "Feedback:\n":  # the goal is running
            line = process.stdout.readline()
        process.send_signal(signal.SIGINT)
        # A backstop, not a measure: closing may wait for the server's close frame, within
        # websockets' close_timeout (10 s), on a loaded machine.
        _, err = process.communicate(timeout=scaled(30))
    finally:
        process.kill()
        process.communicate()  # reaps it and closes its pipes
    assert process.returncode == ExitCode.INTERRUPTED, err
    assert err == "srvwire: error: interrupted\n"
    assert CANCELLED.wait(scaled(5))  # the server's handler saw the cancellation
