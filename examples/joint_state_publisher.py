"""Publish the robot's joint states on ``/joint_states``, as ROS's joint_state_publisher does.

Each message is a ``sensor_msgs/msg/JointState`` with the five joints' names and positions,
which ``robot_state_server.py`` keeps as its state. Run it beside the server::

    python examples/joint_state_publisher.py                 # 10 Hz, until Ctrl-C
    python examples/joint_state_publisher.py --count 3       # three messages, then stop

A topic is one-way and never waits for an answer: ``publish`` returns once the message is
written, however many subscribe (the server, and ``srvwire topic echo /joint_states``).
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import math
from typing import Any

from srvwire import connect, load_message

JointState = load_message("sensor_msgs/msg/JointState")

logger = logging.getLogger("joint_state_publisher")

JOINTS = [f"joint_{i}" for i in range(5)]


def joint_state(step: int) -> Any:
    """The joint state at ``step``: each joint swinging gently, a little out of phase."""
    positions = [round(0.5 * math.sin(step / 10 + i), 3) for i in range(len(JOINTS))]
    return JointState.model_validate({"name": JOINTS, "position": positions})


async def publish(url: str, rate: float, count: int | None) -> None:
    # --8<-- [start:publish]
    async with connect(url) as client:
        await client.wait_for_topic("/joint_states")  # woken by the server's $/topics
        step = 0
        while count is None or step < count:
            message = joint_state(step)
            await client.publish("/joint_states", message)
            logger.info("published joint states %s", message.position)
            step += 1
            if count is None or step < count:
                await asyncio.sleep(1 / rate)
        # Ask once that the server has them all: a call on the same connection is answered
        # after every message sent before it was read.
        state = await client.call("/get_robot_state", {"query_type": "position"})
        logger.info("the robot now reports %s", state.values)
    # --8<-- [end:publish]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--url", default="ws://localhost:8765", help="the robot's server")
    parser.add_argument("--rate", type=float, default=10.0, help="messages a second")
    parser.add_argument("--count", type=int, help="stop after this many messages")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        asyncio.run(publish(args.url, args.rate, args.count))
    except KeyboardInterrupt:
        pass
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
