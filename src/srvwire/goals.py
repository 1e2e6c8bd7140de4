"""The rules of an action's goal on the wire, without I/O: its states, its notifications, and
the keep-latest feedback a connection owes.

A goal is one JSON-RPC request to the action's name; its reply is the outcome
``{"status": "succeeded"|"canceled"|"aborted", "result": {...}}``, or an error (a refused goal
is ``GOAL_REJECTED``). Between the two the server sends ``$/goal`` notifications (the goal's
state: ``accepted``, ``executing``, ``canceling``) and ``$/feedback`` notifications, each
naming the call by its request id.

Invariants:

* **A goal's states follow ROS's**: ``accepted`` then ``executing``, ``canceling`` once a
  cancellation was asked for, and one final state, the reply's. :func:`advance` refuses a
  step back.
* **Feedback is keep-latest per goal.** :class:`FeedbackOutbox` holds at most one feedback
  message per goal: a newer one replaces the one not sent yet, so a goal that reports faster
  than its client reads costs one message of memory, not a queue. Goals are served
  round-robin, so one busy goal cannot starve another. ``seq`` counts every feedback the
  handler gave, so a gap shows how many were replaced.
* **Feedback never goes ahead of control.** The outbox is only data: the connection's writer
  (:class:`srvwire.serving.Writer`) takes it in turn with topic data, behind every reply and
  control message, and not while the connection is past its budget; a goal's pending
  feedback is dropped when its outcome is written (the result supersedes it).
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from typing import Any, Literal

from srvwire.protocol import encode_json

__all__ = [
    "FEEDBACK_METHOD",
    "FINAL_STATES",
    "GOAL_METHOD",
    "GOAL_STATES",
    "FeedbackOutbox",
    "GoalNews",
    "GoalState",
    "advance",
    "feedback_notification",
    "goal_news",
    "goal_notification",
]

GOAL_METHOD = "$/goal"
"""The notification that says a goal's state changed."""
FEEDBACK_METHOD = "$/feedback"
"""The notification that carries a goal's latest feedback."""

GoalState = Literal[
    "pending", "accepted", "executing", "canceling", "succeeded", "canceled", "aborted"
]
"""ROS's goal states, and ``pending`` for a goal not accepted yet (a client's view)."""

GOAL_STATES: tuple[str, ...] = (
    "pending",
    "accepted",
    "executing",
    "canceling",
    "succeeded",
    "canceled",
    "aborted",
)
FINAL_STATES = frozenset({"succeeded", "canceled", "aborted"})


def advance(current: str, new: str) -> str:
    """Return the state a goal in ``current`` is in after hearing ``new``.

    A final state stays; a state earlier than the current one is ignored (``executing``
    cannot undo ``canceling``); an unknown state is ignored.
    """
    if current in FINAL_STATES or new not in GOAL_STATES:
        return current
    if new in FINAL_STATES or GOAL_STATES.index(new) > GOAL_STATES.index(current):
        return new
    return current


def goal_notification(call: Any, goal_id: str, status: str) -> bytes:
    """The ``$/goal`` notification for the goal of the call ``call``."""
    return (
        b'{"jsonrpc":"2.0","method":"$/goal","params":{"call":'
        + encode_json(call).encode()
        + b',"goal_id":'
        + encode_json(goal_id).encode()
        + b',"status":'
        + encode_json(status).encode()
        + b"}}"
    )


def feedback_notification(call: Any, seq: int, feedback: bytes) -> bytes:
    """The ``$/feedback`` notification: ``feedback`` is the message's JSON, written once."""
    return (
        b'{"jsonrpc":"2.0","method":"$/feedback","params":{"call":'
        + encode_json(call).encode()
        + b',"seq":'
        + str(seq).encode()
        + b',"feedback":'
        + feedback
        + b"}}"
    )


@dataclass(frozen=True, slots=True)
class GoalNews:
    """A ``$/goal`` or ``$/feedback`` notification, read: for the goal of the call ``call``.

    For ``$/goal``, ``status`` and ``goal_id`` are set; for ``$/feedback``, ``seq`` and
    ``feedback`` (the parsed message, decoded by whoever knows its type).
    """

    call: int
    status: str | None = None
    goal_id: str | None = None
    seq: int = 0
    feedback: Any = None


def goal_news(method: str, params: Any) -> GoalNews | None:
    """Read a ``$/goal`` or ``$/feedback`` notification; None when it is malformed."""
    if type(params) is not dict:
        return None
    call = params.get("call")
    if type(call) is not int:
        return None
    if method == GOAL_METHOD:
        status, goal_id = params.get("status"), params.get("goal_id")
        if not (isinstance(status, str) and isinstance(goal_id, str)):
            return None
        return GoalNews(call, status=status, goal_id=goal_id)
    seq = params.get("seq")
    if type(seq) is not int or "feedback" not in params:
        return None
    return GoalNews(call, seq=seq, feedback=params["feedback"])


class FeedbackOutbox:
    """The feedback one connection owes its goals: at most one message per goal, keep-latest.

    :meth:`put` replaces what a goal had not sent yet; :meth:`take` hands out the oldest
    waiting goal's message (round-robin: a goal whose message was taken waits behind the
    others when it puts again, and one that replaces a message keeps its turn);
    :meth:`discard` forgets a goal whose outcome is written.
    """

    __slots__ = ("_slots", "replaced")

    def __init__(self) -> None:
        self._slots: OrderedDict[Any, bytes] = OrderedDict()
        self.replaced = 0
        """How many feedback messages were replaced before they were sent (never sent)."""

    def __len__(self) -> int:
        return len(self._slots)

    def __contains__(self, call: object) -> bool:
        """Whether ``call`` has feedback waiting to be sent."""
        return call in self._slots

    def put(self, call: Any, message: bytes) -> bool:
        """Keep ``message`` as ``call``'s next feedback; return whether the outbox was empty."""
        slots = self._slots
        was_empty = not slots
        if call in slots:
            self.replaced += 1
        slots[call] = message  # an update keeps its turn: it does not wait behind others
        return was_empty

    def take(self) -> tuple[Any, bytes] | None:
        """Return the next goal to send for and its message (the longest-waiting), or None."""
        if not self._slots:
            return None
        return self._slots.popitem(last=False)

    def discard(self, call: Any) -> None:
        """Forget the feedback ``call`` had not sent: its outcome is written."""
        self._slots.pop(call, None)
