"""A simulated robot that answers two services and an action: the robot-state tutorial's server.

The robot has five joints, a status word and a calibration flag. Two services expose it:

* ``/get_robot_state`` (``advanced_communication_tutorials/srv/RobotStateQuery``) reports the
  joint positions, the status, or the robot's fixed configuration;
* ``/execute_robot_command`` (``advanced_communication_tutorials/srv/RobotCommand``) moves the
  joints, stops the robot, or calibrates it at once;

and one action, for the task that takes a while:

* ``/calibrate`` (``advanced_communication_tutorials/action/Calibrate``) calibrates the joints
  one by one (5 s in all unless the goal asks otherwise), sends its progress as feedback, and
  stops early when the client cancels it.

Like the ROS original, it also subscribes to ``/joint_states`` (``sensor_msgs/msg/JointState``):
whatever a client publishes there (``joint_state_publisher.py``) becomes the joint positions it
reports.

Run it, then call it with ``robot_command_client.py`` or by hand with ``wscat``::

    python examples/robot_state_server.py              # ws://127.0.0.1:8765
    python examples/robot_state_server.py --port 0     # any free port; the URL is logged

Once it listens it logs ``serving 2 services and 1 action on ws://HOST:PORT`` (with the port it
got), then logs every request and response, and stops cleanly on Ctrl-C or SIGTERM.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
from dataclasses import dataclass, field
from typing import Any

# --8<-- [start:load]
from srvwire.actions import GoalHandle
from srvwire.loader import load_action, load_message, load_service
from srvwire.server import Server

# Service types come from .srv files, exactly as in ROS 2: the name is package/srv/Type.
RobotStateQuery = load_service("advanced_communication_tutorials/srv/RobotStateQuery")
RobotCommand = load_service("advanced_communication_tutorials/srv/RobotCommand")
# An action type comes from an .action file: package/action/Type.
Calibrate = load_action("advanced_communication_tutorials/action/Calibrate")
# Topics carry messages (.msg files): the joint states clients publish.
JointState = load_message("sensor_msgs/msg/JointState")
# --8<-- [end:load]

logger = logging.getLogger("robot_state_server")

JOINT_COUNT = 5
MAX_SPEED = 5.0  # reported by the "configuration" query
MAX_TORQUE = 10.0
CALIBRATION_TIME = 5.0  # seconds, as in the original tutorial, unless a goal asks otherwise


# --8<-- [start:state]
@dataclass
class RobotState:
    """Everything the simulated robot knows about itself."""

    joint_positions: list[float] = field(default_factory=lambda: [0.0] * JOINT_COUNT)
    status: str = "IDLE"
    calibrated: bool = True


# --8<-- [end:state]


class RobotStateNode:
    """The two service handlers, sharing one :class:`RobotState`.

    The handlers use the ROS 2 shape ``handler(request, response) -> response``: srvwire hands
    them an empty response to fill in, so a ROS callback ports line for line. They are
    ``async def``, so they run one at a time on the event loop and never race on the state; a
    plain ``def`` handler would work too, but srvwire runs those in a worker thread.
    """

    def __init__(self, state: RobotState | None = None) -> None:
        self.state = state if state is not None else RobotState()

    # --8<-- [start:query]
    async def get_robot_state(self, request: Any, response: Any) -> Any:
        """Answer ``/get_robot_state``: ``position``, ``status`` or ``configuration``."""
        logger.info("query %r (target_frame=%r)", request.query_type, request.target_frame)
        state = self.state
        if request.query_type == "position":
            response.values = list(state.joint_positions)
            response.names = [f"joint_{i}" for i in range(len(state.joint_positions))]
            response.message = "Current joint positions"
            response.success = True
        elif request.query_type == "status":
            response.values = [1.0 if state.calibrated else 0.0]
            response.names = ["is_calibrated"]
            response.message = f"Robot status: {state.status}"
            response.success = True
        elif request.query_type == "configuration":
            response.values = [float(JOINT_COUNT), MAX_SPEED, MAX_TORQUE]
            response.names = ["joint_count", "max_speed", "max_torque"]
            response.message = "Robot configuration"
            response.success = True
        else:
            # An unknown query is an answer, not an error: success=False says why.
            response.message = f"Unknown query type: {request.query_type}"
            response.success = False
        logger.info("query %r -> %s", request.query_type, response)
        return response

    # --8<-- [end:query]

    # --8<-- [start:command]
    async def execute_robot_command(self, request: Any, response: Any) -> Any:
        """Carry out ``/execute_robot_command``: ``move``, ``stop`` or ``calibrate``."""
        logger.info(
            "command %r with parameters %s (target_frame=%r)",
            request.command_type,
            request.parameters,
            request.target_frame,
        )
        state = self.state
        if request.command_type == "move":
            if not request.parameters:
                response.message = "Move command requires parameters"
                response.success = False
            elif len(request.parameters) != len(state.joint_positions):
                # One target per joint, no more and no fewer: a robot should not guess.
                response.message = (
                    f"Move command needs one position per joint: "
                    f"expected {len(state.joint_positions)}, got {len(request.parameters)}"
                )
                response.success = False
            else:
                state.joint_positions = list(request.parameters)
                state.status = "MOVING"
                response.execution_time = 1.0
                response.message = "Moving to the requested joint positions"
                response.success = True
        elif request.command_type == "stop":
            state.status = "STOPPED"
            response.execution_time = 0.1
            response.message = "Robot stopped"
            response.success = True
        elif request.command_type == "calibrate":
            state.status = "CALIBRATED"
            state.calibrated = True
            response.execution_time = 5.0
            response.message = "Robot calibrated"
            response.success = True
        else:
            response.message = f"Unknown command type: {request.command_type}"
            response.success = False
        logger.info("command %r -> %s", request.command_type, response)
        return response

    # --8<-- [end:command]

    # --8<-- [start:calibrate]
    async def calibrate(self, goal: Any, handle: GoalHandle) -> Any:
        """Run the ``/calibrate`` action: one joint after the other, with progress feedback.

        Each joint takes an equal share of ``goal.duration`` (``CALIBRATION_TIME`` when 0).
        A cancellation stops it between joints; the result says how far it got, and reports
        the time of the joints done (the simulated robot's, as the services report theirs).
        """
        duration = goal.duration if goal.duration > 0 else CALIBRATION_TIME
        joints = len(self.state.joint_positions)
        logger.info("calibrating %d joints over %g s", joints, duration)
        self.state.status = "CALIBRATING"
        self.state.calibrated = False
        done = 0
        try:
            for joint in range(joints):
                progress = {"current_joint": f"joint_{joint}", "progress": joint / joints}
                await handle.feedback(progress)
                try:  # the joint's share of the time, unless the client cancels first
                    await asyncio.wait_for(handle.cancelled(), duration / joints)
                except TimeoutError:
                    done += 1
                    continue
                break  # cancelled
        except asyncio.CancelledError:  # the goal's deadline passed: stopped where it was
            self.state.status = "STOPPED"
            raise
        if done == joints:
            self.state.status, self.state.calibrated = "CALIBRATED", True
            message = "Robot calibrated"
        else:
            self.state.status = "STOPPED"
            message = f"Calibration canceled after {done} of {joints} joints"
        logger.info("calibrate -> %s", message)
        return {
            "success": done == joints,
            "message": message,
            "execution_time": duration * done / joints,
            "joints_done": done,
        }

    # --8<-- [end:calibrate]

    # --8<-- [start:joint_states]
    def on_joint_states(self, msg: Any) -> None:
        """Keep the joint positions a publisher reports on ``/joint_states``, as the ROS
        original's subscription does. A plain ``def`` runs on the event loop as each message
        arrives, in order: keep it quick."""
        if len(msg.position) != JOINT_COUNT:
            logger.warning(
                "ignoring a joint state with %d positions; the robot has %d joints",
                len(msg.position),
                JOINT_COUNT,
            )
            return
        self.state.joint_positions = list(msg.position)
        logger.debug("joint states %s", msg.position)

    # --8<-- [end:joint_states]


# --8<-- [start:server]
def build_server(node: RobotStateNode | None = None) -> Server:
    """Create a srvwire server offering the robot's two services and its action."""
    node = node if node is not None else RobotStateNode()
    server = Server()
    server.add_service("/get_robot_state", RobotStateQuery, node.get_robot_state)
    server.add_service("/execute_robot_command", RobotCommand, node.execute_robot_command)
    # One robot, one calibration at a time: a second goal is accepted and waits its turn.
    server.add_action("/calibrate", Calibrate, node.calibrate, max_concurrency=1)
    # Clients publish joint states; a late subscriber (srvwire topic echo) gets the latest one.
    joint_states_qos = {"depth": 1, "durability": "transient_local"}
    server.subscription("/joint_states", JointState, qos=joint_states_qos)(node.on_joint_states)
    return server


# --8<-- [end:server]


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to listen on; 0.0.0.0 for every interface (default: %(default)s, "
        "this machine only)",
    )
    parser.add_argument(
        "--port",
        type=int,
        default=8765,
        help="port to listen on; 0 picks a free one (default: %(default)s)",
    )
    return parser.parse_args(argv)


# --8<-- [start:main]
def main(argv: list[str] | None = None) -> int:
    """Serve the robot until Ctrl-C or SIGTERM."""
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    server = build_server()
    # run() logs "serving 2 services and 1 action on ws://HOST:PORT" once it listens, then
    # blocks until Ctrl-C or SIGTERM and shuts down gracefully: calls in flight may finish.
    server.run(args.host, args.port)
    return 0


# --8<-- [end:main]


if __name__ == "__main__":
    raise SystemExit(main())
