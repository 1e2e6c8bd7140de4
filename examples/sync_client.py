"""Drive the simulated robot from a plain script: srvwire's blocking client, no asyncio.

The same calls as ``robot_command_client.py``, written the way an rclpy or httpx user writes a
script. Start ``robot_state_server.py`` first::

    python examples/robot_state_server.py
    python examples/sync_client.py --url ws://localhost:8765

It prints one line per answer and exits with status 0, or with status 1 naming the error when
a call failed (no server, a lost connection, a deadline).
"""

from __future__ import annotations

import argparse
import sys
from concurrent.futures import ThreadPoolExecutor

import srvwire


# --8<-- [start:script]
def run(url: str, timeout: float = 5.0) -> None:
    """Query the robot, move it, and read its joints back from several threads at once."""
    with srvwire.sync.connect(url, timeout=timeout) as client:
        client.wait_for_service("/get_robot_state")
        state = client.call("/get_robot_state", {"query_type": "position"})
        print(f"{state.message}: {state.values}")  # a typed response: fields, not dict keys

        move = client.proxy("/execute_robot_command")  # fields as keywords
        done = move(command_type="move", parameters=[1.0, 0.5, -0.5, 0.0, 0.3])
        print(f"{done.message} (takes {done.execution_time} s)")

        # One connection serves every thread; their calls run at the same time.
        with ThreadPoolExecutor(max_workers=3) as pool:
            answers = pool.map(
                lambda kind: client.call("/get_robot_state", {"query_type": kind}),
                ["position", "status", "configuration"],
            )
            for answer in answers:
                print(f"{answer.message}: {dict(zip(answer.names, answer.values, strict=True))}")


# --8<-- [end:script]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--url", default="ws://localhost:8765", help="the robot server's URL")
    parser.add_argument("--timeout", type=float, default=5.0, help="seconds allowed per call")
    args = parser.parse_args(argv)
    # --8<-- [start:errors]
    try:
        run(args.url, args.timeout)
    except srvwire.RPCError as exc:  # the async client's errors, raised the same way
        print(f"{type(exc).__name__}: {exc.message}", file=sys.stderr)
        return 1
    # --8<-- [end:errors]
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
