"""Topics and an action from a plain script: srvwire's blocking client, no asyncio.

Publishes the robot's joint states, reads them back as a subscriber, then calibrates the
robot with the ``/calibrate`` action, printing its feedback. Start ``robot_state_server.py``
first::

    python examples/robot_state_server.py
    python examples/sync_topics.py --url ws://localhost:8765

It exits with status 0, or with status 1 naming the error when something failed.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

import srvwire

JointState: Any = srvwire.load_message("sensor_msgs/msg/JointState")  # fields known at run time
JOINTS = [f"joint_{i}" for i in range(5)]


# --8<-- [start:script]
def run(url: str, timeout: float = 5.0, duration: float = 1.0) -> None:
    """Publish joint states, read them back, and calibrate the robot, printing as it goes."""
    with srvwire.sync.connect(url, timeout=timeout) as client:
        client.wait_for_topic("/joint_states")
        state = JointState(name=JOINTS, position=[0.1, 0.2, 0.3, 0.4, 0.5])
        client.publish("/joint_states", state, ack=True)  # returns once the server took it

        # The robot keeps the latest joint state for late subscribers (transient_local).
        # Leaving the loop ends the subscription; no message waits more than `timeout`.
        for msg in client.subscribe("/joint_states", JointState, message_timeout=timeout):
            print(f"joint states: {msg.position}")  # a typed message: fields, not dict keys
            break

        goal = client.send_goal("/calibrate", {"duration": duration})
        for feedback in goal.feedback():  # the latest feedback each time, until the goal ends
            print(f"calibrating {feedback.current_joint} ({feedback.progress:.0%})")
        outcome = goal.result()
        print(f"{outcome.status}: {outcome.result.message}")


# --8<-- [end:script]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--url", default="ws://localhost:8765", help="the robot server's URL")
    parser.add_argument("--timeout", type=float, default=5.0, help="seconds allowed per wait")
    args = parser.parse_args(argv)
    try:
        run(args.url, args.timeout)
    except srvwire.RPCError as exc:
        print(f"{type(exc).__name__}: {exc.message}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
