"""A srvwire server with one action, ``/patient``, that says what stopped each goal.

Served by ``srvwire serve tests/servers/goal_server.py --port 0``. Its handler prints
``started <order>`` once it runs, then waits for the client's cancellation:

* ``order`` 1 answers a cancellation as a robot that stops cleanly does: it prints
  ``cancel requested <order>`` and returns ``{sequence: [7]}`` (so the goal ends
  ``canceled`` with that result);
* ``order`` 2 prints ``cancel requested <order>`` too, but goes on, so only the end of the
  connection (or the grace of 60 s) stops it.

A handler stopped by the server instead (its connection closed) prints ``cut <order>``.
"""

from __future__ import annotations

import asyncio
from typing import Any

from srvwire import GoalHandle, load_action
from srvwire.server import Server

Fibonacci = load_action("example_interfaces/action/Fibonacci")

server = Server(grace_period=0)


@server.action("/patient", Fibonacci, cancel_grace=60)
async def patient(goal: Any, handle: GoalHandle) -> Any:
    print(f"started {goal.order}", flush=True)
    try:
        await handle.cancelled()
        print(f"cancel requested {goal.order}", flush=True)
        if goal.order == 2:
            await asyncio.Event().wait()  # never set
    except asyncio.CancelledError:
        print(f"cut {goal.order}", flush=True)
        raise
    return {"sequence": [7]}
