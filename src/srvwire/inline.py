"""Run a coroutine's first step inline, and finish it only if it has to wait.

Most calls never wait: a handler that computes its answer, a send that fits in the socket's
buffer. For them, what an ``await`` costs is small, but what is armed *around* the await in
case it waits (a deadline timer, a task of its own) is not. :func:`first_step` runs a
coroutine up to its first suspension, synchronously; if it finished, there was nothing to
guard. If it suspended, the caller arms its guard and awaits :func:`finish`, which hands
what the coroutine yielded to the running task and drives the rest of it, exactly as
``await coroutine`` would have from the start.

Invariants:

* **Same task, same behaviour.** Both halves run in the task that called :func:`first_step`,
  so ``asyncio.current_task()``, cancellation and ``Task.cancelling()`` see what they would
  see with a plain ``await``. An exception from the first step propagates from
  :func:`first_step`; a cancellation of the task while the coroutine waits is thrown into it.
* **An optional context.** Given a :class:`contextvars.Context`, every step of the coroutine
  runs in it, so a coroutine that sets context variables leaves the caller's context alone.
"""

from __future__ import annotations

import contextvars
import types
from collections.abc import Coroutine, Generator
from typing import Any, TypeVar

__all__ = ["Pending", "finish", "first_step"]

T = TypeVar("T")


class Pending:
    """A coroutine suspended at its first step, and what it yielded to its task."""

    __slots__ = ("context", "coroutine", "yielded")

    def __init__(
        self,
        coroutine: Coroutine[Any, Any, Any],
        yielded: Any,
        context: contextvars.Context | None,
    ) -> None:
        self.coroutine = coroutine
        self.yielded = yielded
        self.context = context


def first_step(
    coroutine: Coroutine[Any, Any, T], context: contextvars.Context | None = None
) -> T | Pending:
    """Run ``coroutine`` until it finishes or first suspends; return its result or a Pending.

    A result that is itself a :class:`Pending` would be ambiguous; no srvwire coroutine
    returns one.
    """
    try:
        if context is None:
            yielded = coroutine.send(None)
        else:
            yielded = context.run(coroutine.send, None)
    except StopIteration as stop:
        result: T = stop.value
        return result
    return Pending(coroutine, yielded, context)


@types.coroutine
def finish(pending: Pending) -> Generator[Any, Any, Any]:
    """Await the rest of a coroutine that :func:`first_step` left suspended; return its result."""
    coroutine = pending.coroutine
    context = pending.context
    yielded = pending.yielded
    while True:
        try:
            sent = yield yielded
        except GeneratorExit:
            coroutine.close()
            raise
        except BaseException as exc:
            step: Any = coroutine.throw
            argument: Any = exc
        else:
            step = coroutine.send
            argument = sent
        try:
            yielded = step(argument) if context is None else context.run(step, argument)
        except StopIteration as stop:
            return stop.value
