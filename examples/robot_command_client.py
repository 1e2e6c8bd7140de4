"""Drive the simulated robot: the robot-state tutorial's client, on srvwire.

It waits until the server offers both services, then runs a short sequence — ask for the joint
positions, the status and the configuration; move; ask for the positions again; stop;
calibrate; ask for the status — and logs every answer. Then it sends the ``/calibrate``
action a goal and logs its progress as the feedback comes, then its result. Start
``robot_state_server.py`` first::

    python examples/robot_state_server.py
    python examples/robot_command_client.py --url ws://localhost:8765
    python examples/robot_command_client.py --calibration-time 1   # a quicker calibration

It exits with status 0 when every call got an answer (even a ``success=False`` one) and with
status 1, naming the error, when a call failed: no server, a lost connection, a deadline.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from srvwire.client import Client, connect
from srvwire.errors import RPCError, ServiceUnavailable

STATE_SERVICE = "/get_robot_state"
COMMAND_SERVICE = "/execute_robot_command"
CALIBRATE_ACTION = "/calibrate"
DEFAULT_URL = "ws://localhost:8765"

logger = logging.getLogger("robot_command_client")


@dataclass(frozen=True)
class Step:
    """One call of the demo sequence: which service, and the request's fields."""

    service: str
    request: dict[str, Any]

    def describe(self) -> str:
        """Say what this step asks for, e.g. ``query position`` or ``command move [...]``."""
        if self.service == STATE_SERVICE:
            return f"query {self.request['query_type']}"
        parameters = self.request.get("parameters")
        return f"command {self.request['command_type']}" + (f" {parameters}" if parameters else "")


# --8<-- [start:sequence]
def demo_sequence() -> list[Step]:
    """The calls the tutorial makes, in order."""

    def query(kind: str) -> Step:
        return Step(STATE_SERVICE, {"query_type": kind})

    def command(kind: str, parameters: list[float] | None = None) -> Step:
        return Step(COMMAND_SERVICE, {"command_type": kind, "parameters": parameters or []})

    return [
        query("position"),
        query("status"),
        query("configuration"),
        command("move", [1.0, 0.5, -0.5, 0.0, 0.3]),
        query("position"),
        command("stop"),
        command("calibrate"),
        query("status"),
    ]


# --8<-- [end:sequence]


def describe_response(step: Step, response: Any) -> str:
    """Render a response on one line: the verdict, the message, and the readings or the time."""
    verdict = "ok" if response.success else "refused"
    if step.service == STATE_SERVICE:
        readings = ", ".join(
            f"{name}={value}" for name, value in zip(response.names, response.values, strict=True)
        )
        return f"{verdict}: {response.message}" + (f" [{readings}]" if readings else "")
    return f"{verdict}: {response.message} (took {response.execution_time} s)"


def log_response(step: Step, response: Any) -> None:
    """The default way to report an answer: one INFO line per step."""
    logger.info("%-40s -> %s", step.describe(), describe_response(step, response))


# --8<-- [start:run]
async def run_sequence(
    client: Client,
    steps: list[Step],
    on_response: Callable[[Step, Any], object] = log_response,
) -> None:
    """Make each call in turn, each under the client's deadline; a failed call raises."""
    for step in steps:
        response = await client.call(step.service, step.request)
        on_response(step, response)


async def run(
    url: str,
    timeout: float = 5.0,  # noqa: ASYNC109 - the client's deadline for every call
    on_response: Callable[[Step, Any], object] = log_response,
    calibration_time: float = 5.0,
) -> int:
    """Wait for the robot's services at ``url``, run the demo sequence, then calibrate with
    the action; return the exit code.

    ``timeout`` bounds connecting, the wait for the services, and each call. ``on_response``
    is called with each step and its response as it arrives (the default logs it).
    ``calibration_time`` is how long the calibration goal asks to take (0: no action goal).
    """
    try:
        client = await connect(url, timeout=timeout, open_timeout=timeout)
    except ServiceUnavailable as exc:  # nothing listens at url, or it is not a srvwire server
        logger.error("no srvwire server answered at %s: is robot_state_server.py running?", url)
        report_failure(exc)
        return 1
    async with client:
        try:
            # The server announces its services as soon as we connect; this returns at once
            # when both are there, and gives up after `timeout` seconds otherwise.
            for service in (STATE_SERVICE, COMMAND_SERVICE):
                await client.wait_for_service(service, timeout=timeout)
            await run_sequence(client, demo_sequence(), on_response)
            if calibration_time > 0:
                await client.wait_for_service(CALIBRATE_ACTION, timeout=timeout)
                await calibrate(client, calibration_time)
        except RPCError as exc:  # every failure srvwire reports is one of these
            report_failure(exc)
            return 1
    return 0


# --8<-- [end:run]


# --8<-- [start:calibrate]
async def calibrate(
    client: Client, duration: float, on_feedback: Callable[[Any], object] | None = None
) -> Any:
    """Send ``/calibrate`` a goal, report each feedback, and return the result.

    The goal's deadline covers the whole calibration, with room to spare.
    """
    handle = await client.send_goal(CALIBRATE_ACTION, {"duration": duration}, timeout=duration + 5)
    logger.info("%-40s -> accepted", f"action calibrate ({duration:g} s)")
    async for feedback in handle.feedback():  # the latest each time: a slow reader skips
        if on_feedback is not None:
            on_feedback(feedback)
        else:
            logger.info(
                "  calibrating %s: %3.0f%% done", feedback.current_joint, 100 * feedback.progress
            )
    outcome = await handle.result()
    result = outcome.result  # a Calibrate.Result
    logger.info(
        "%-40s -> %s: %s (%d joints done)",
        "action calibrate",
        outcome.status,
        result.message,
        result.joints_done,
    )
    return result


# --8<-- [end:calibrate]


def report_failure(exc: RPCError) -> None:
    """Log a failure as ``<ErrorClass> (code <n>) calling <service>: <message>``."""
    where = f" calling {exc.service}" if exc.service else ""
    logger.error("%s (code %d)%s: %s", type(exc).__name__, exc.code, where, exc.message)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument(
        "--url", default=DEFAULT_URL, help="the server's WebSocket URL (default: %(default)s)"
    )
    parser.add_argument(
        "--timeout",
        type=float,
        default=5.0,
        help="seconds allowed for connecting, for the services to appear, and for each call "
        "(default: %(default)s)",
    )
    parser.add_argument(
        "--calibration-time",
        type=float,
        default=5.0,
        help="seconds the /calibrate goal asks the robot to take; 0 skips the action "
        "(default: %(default)s)",
    )
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    """Run the demo sequence against the server at ``--url``; return the exit code."""
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    return asyncio.run(run(args.url, args.timeout, calibration_time=args.calibration_time))


if __name__ == "__main__":
    raise SystemExit(main())
