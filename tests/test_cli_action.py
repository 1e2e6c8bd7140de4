"""``srvwire action``: list, info and send_goal against a real server."""

from __future__ import annotations

import asyncio
import re
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
from support import Lines, interruptible, scaled, serve_goal_server, start_interruptible
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


def test_calling_an_action_is_a_usage_error_that_names_send_goal(
    capsys: pytest.CaptureFixture[str], url: str
) -> None:
    capsys.readouterr()
    code = main(["call", "/fibonacci", "{order: 3}", "--url", url])
    err = capsys.readouterr().err
    assert code == ExitCode.USAGE
    assert err == (
        "srvwire: error: /fibonacci is the action example_interfaces/action/Fibonacci, not a "
        "service: use srvwire action send_goal /fibonacci\n"
    )
    code = main(["call", "/fibonacci", "example_interfaces/action/Fibonacci", "--url", url])
    err = capsys.readouterr().err
    assert code == ExitCode.USAGE
    assert err == (
        "srvwire: error: example_interfaces/action/Fibonacci is an action type, not a service "
        "type: send it a goal with srvwire action send_goal /fibonacci\n"
    )


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
        rest, err = process.communicate(timeout=scaled(30))
    finally:
        process.kill()
        process.communicate()  # reaps it and closes its pipes
    assert process.returncode == ExitCode.INTERRUPTED, err
    assert err == ""
    # /forever's cancel_grace is 0: the server stopped the handler, and the goal ended so.
    assert rest.endswith("\nGoal finished with status: CANCELED\n"), rest
    assert CANCELLED.wait(scaled(5))  # the server's handler saw the cancellation


# --- Ctrl-C against a server in a process of its own -------------------------------------------


@pytest.fixture
def goal_server() -> Iterator[tuple[str, Lines]]:
    """``srvwire serve tests/servers/goal_server.py`` in a process: its URL and its output."""
    with serve_goal_server() as served:
        yield served


class SendGoal:
    """``srvwire action send_goal /patient`` in a process, which Ctrl-C reaches as from a
    terminal; its stdout is read as it comes."""

    def __init__(self, url: str, order: int) -> None:
        command = ["-m", "srvwire", "action", "send_goal", "/patient"]
        self.process = start_interruptible(
            *command, f"{{order: {order}}}", "--url", url, "--timeout", "600"
        )
        assert self.process.stdout is not None
        self.out = Lines(self.process.stdout)

    def ctrl_c(self) -> None:
        self.process.send_signal(signal.SIGINT)

    def end(self) -> tuple[int, str, str]:
        """Wait for it to exit (its deadline is 600 s: a backstop of one minute); return
        its exit code, stdout and stderr."""
        assert self.process.stderr is not None
        try:
            code = self.process.wait(timeout=scaled(60))
        finally:
            self.process.kill()
            self.process.wait()
            out = self.out.close()
            err = self.process.stderr.read()
            self.process.stderr.close()
        return code, out, err


def test_ctrl_c_asks_the_handler_to_stop_and_prints_how_the_goal_ended(
    goal_server: tuple[str, Lines],
) -> None:
    url, served = goal_server
    command = SendGoal(url, 1)
    try:
        served.expect("started 1")
        command.out.expect("Goal accepted with ID: ")
        command.ctrl_c()
        served.expect("cancel requested 1")  # the handler saw cancel_requested, not a cut
    finally:
        code, out, err = command.end()
    assert (code, err) == (ExitCode.INTERRUPTED, "")
    assert re.fullmatch(
        r"Sending goal:\n    order: 1\n\nGoal accepted with ID: [-0-9a-f]{36}\n"
        r"\nCanceling goal \(Ctrl-C again to stop waiting\)\.\.\.\n"
        r"\nResult:\n    sequence:\n    - 7\n"  # the handler's own result
        r"\nGoal finished with status: CANCELED\n",
        out,
    ), out


def test_a_second_ctrl_c_stops_waiting_for_a_goal_that_goes_on(
    goal_server: tuple[str, Lines],
) -> None:
    url, served = goal_server
    command = SendGoal(url, 2)
    try:
        served.expect("started 2")
        command.out.expect("Goal accepted with ID: ")
        command.ctrl_c()
        command.out.expect("Canceling goal (Ctrl-C again to stop waiting)...")
        served.expect("cancel requested 2")  # and the handler goes on
        command.ctrl_c()  # ends the command, not its deadline (600 s)
    finally:
        code, out, err = command.end()
    assert (code, err) == (ExitCode.INTERRUPTED, "srvwire: error: interrupted\n"), out
    assert "Result:" not in out
    served.expect("cut 2")  # the connection's end stopped the handler


@pytest.mark.parametrize(
    ("values", "code", "said"),
    [
        ("{order: x}", ExitCode.INVALID_PARAMS, "(checked by the client; nothing was sent)"),
        ("{order: 60}", ExitCode.SERVICE_FAILED, "GoalRejected: GOAL_REJECTED (-32007)"),
    ],
)
def test_a_goal_that_was_not_accepted_prints_only_the_error(
    capsys: pytest.CaptureFixture[str], url: str, values: str, code: int, said: str
) -> None:
    got, out, err = run(capsys, url, "send_goal", "/fibonacci", values)
    assert (got, out) == (code, "")
    assert said in err
    got, out, err = run(capsys, url, "send_goal", "/no_such_action", "{}")
    assert (got, out) == (ExitCode.SERVICE_NOT_FOUND, "")
    assert "no service named /no_such_action" in err
