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
* **A deadline for what waits.** :func:`finish_within` is :func:`finish` under a deadline,
  what the client arms around a send held by backpressure: a bare ``loop.call_later`` timer
  that cancels the task, a few times cheaper than ``asyncio.timeout``. When the deadline
  passed, it raises :class:`Expired` (a ``TimeoutError``), whatever the coroutine did with its
  cancellation, unless something else cancelled the task too, which then stays a
  cancellation. (The server's call runner, :class:`srvwire.serving.CallRunner`, arms its own
  timer, since its deadline is a cancellation with a reason.)
"""

from __future__ import annotations

import asyncio
import contextvars
import types
from collections.abc import Coroutine, Generator
from typing import Any

__all__ = ["Expired", "Pending", "finish", "finish_within", "first_step"]


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
    coroutine: Coroutine[Any, Any, Any], context: contextvars.Context | None = None
) -> Pending | None:
    """Run ``coroutine`` until it finishes or first suspends; return None or a Pending.

    For coroutines run for what they do: one that finishes in its first step has its result
    dropped (srvwire's return None), since it is stepped as a ``for`` loop steps an iterator,
    which raises no ``StopIteration`` when it ends (``send`` raises one, which costs about a
    third of a small coroutine's run). One that waits returns its result from :func:`finish`.
    Any other kind of coroutine (a generator-based one, an object with ``send``) is stepped by
    its ``send``.
    """
    if type(coroutine) is types.CoroutineType:
        steps = coroutine.__await__()
        yielded = next(steps, _DONE) if context is None else context.run(next, steps, _DONE)
        if yielded is _DONE:
            return None
    else:
        try:
            if context is None:
                yielded = coroutine.send(None)
            else:
                yielded = context.run(coroutine.send, None)
        except StopIteration:
            return None
    return Pending(coroutine, yielded, context)


_DONE = object()  # what first_step's ``next`` returns once the coroutine has finished


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


class Expired(TimeoutError):
    """The deadline of :func:`finish_within` passed before the coroutine finished."""


async def finish_within(pending: Pending, delay: float) -> Any:
    """:func:`finish` ``pending``, cancelling it after ``delay`` seconds; raise Expired then.

    The cancellation the deadline requested is always taken back. A coroutine that swallowed it
    and returned, or turned it into a TimeoutError, still raises :class:`Expired`: its caller
    is gone. Must run in a task.
    """
    task = asyncio.current_task()
    if task is None:
        raise RuntimeError("a deadline needs to run inside a task")
    cancelling = task.cancelling()
    fired = False

    def fire() -> None:
        nonlocal fired
        fired = True
        task.cancel()

    handle = asyncio.get_running_loop().call_later(delay, fire)
    try:
        result = await finish(pending)
    except asyncio.CancelledError:
        handle.cancel()
        if fired and task.uncancel() <= cancelling:
            raise Expired from None  # the deadline's was the only cancellation
        raise
    except BaseException as exc:
        handle.cancel()
        if fired:
            task.uncancel()
            if isinstance(exc, TimeoutError):
                raise Expired from exc
        raise
    handle.cancel()
    if fired:  # the coroutine swallowed its cancellation and finished: too late all the same
        task.uncancel()
        raise Expired
    return result
