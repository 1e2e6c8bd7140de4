"""Running a coroutine's first step inline, and finishing it in the same task."""

from __future__ import annotations

import asyncio
import contextvars
import types
from collections.abc import Coroutine, Generator
from typing import Any

import pytest

from srvwire.inline import Expired, Pending, finish, finish_within, first_step

tag: contextvars.ContextVar[str] = contextvars.ContextVar("tag", default="outside")


async def answers(value: int) -> int:
    return value * 2


async def waits_for(future: asyncio.Future[int]) -> int:
    return await future + 1


async def test_a_coroutine_that_does_not_wait_finishes_in_its_first_step() -> None:
    done: list[int] = []

    async def records(value: int) -> None:
        done.append(await answers(value))

    assert first_step(records(21)) is None
    assert done == [42]


async def test_a_generator_based_coroutine_is_stepped_too() -> None:
    future: asyncio.Future[int] = asyncio.get_running_loop().create_future()
    done: list[int] = []

    @types.coroutine
    def generator_based(wait: bool) -> Generator[Any, Any, None]:
        done.append((yield from future) if wait else 0)

    assert first_step(generator_based(False)) is None
    steps = first_step(generator_based(True))
    assert isinstance(steps, Pending) and steps.yielded is future
    future.set_result(7)
    await finish(steps)
    assert done == [0, 7]


async def test_a_first_step_that_yields_none_is_not_taken_for_the_end() -> None:
    done: list[str] = []

    async def yields_none_first() -> None:
        await asyncio.sleep(0)  # yields None to its task
        done.append("finished")

    steps = first_step(yields_none_first())
    assert isinstance(steps, Pending) and steps.yielded is None
    await finish(steps)
    assert done == ["finished"]


async def test_a_coroutine_that_waits_is_finished_in_the_same_task() -> None:
    future: asyncio.Future[int] = asyncio.get_running_loop().create_future()
    tasks: list[asyncio.Task[Any] | None] = []

    async def notes_its_task() -> int:
        tasks.append(asyncio.current_task())
        value = await future
        tasks.append(asyncio.current_task())
        return value

    steps = first_step(notes_its_task())
    assert isinstance(steps, Pending) and steps.yielded is future
    asyncio.get_running_loop().call_soon(future.set_result, 7)
    assert await finish(steps) == 7
    assert tasks == [asyncio.current_task()] * 2


async def test_an_exception_in_the_first_step_propagates() -> None:
    async def fails() -> None:
        raise ValueError("no")

    with pytest.raises(ValueError, match="no"):
        first_step(fails())


async def test_an_exception_after_waiting_propagates() -> None:
    future: asyncio.Future[int] = asyncio.get_running_loop().create_future()
    steps = first_step(waits_for(future))
    assert isinstance(steps, Pending)
    future.set_exception(KeyError("later"))
    with pytest.raises(KeyError, match="later"):
        await finish(steps)


async def cancelled_while_waiting(coroutine: Coroutine[Any, Any, Any]) -> asyncio.Task[Any]:
    """Run ``coroutine`` by first_step and finish in a task; cancel the task once it waits."""
    entered = asyncio.Event()

    async def runner() -> Any:
        steps = first_step(coroutine)
        assert isinstance(steps, Pending)
        entered.set()
        return await finish(steps)

    task = asyncio.create_task(runner())
    await entered.wait()
    task.cancel()
    return task


async def test_cancelling_the_task_while_it_waits_is_thrown_into_the_coroutine() -> None:
    outcome: list[str] = []

    async def handles_cancellation() -> str:
        try:
            await asyncio.Event().wait()
        except asyncio.CancelledError:
            outcome.append("cancelled inside")
            raise
        return "never"

    task = await cancelled_while_waiting(handles_cancellation())
    with pytest.raises(asyncio.CancelledError):
        await task
    assert outcome == ["cancelled inside"]


async def test_a_coroutine_may_catch_its_cancellation_and_return() -> None:
    async def recovers() -> str:
        try:
            await asyncio.Event().wait()
        except asyncio.CancelledError:
            return "recovered"
        return "never"

    task = await cancelled_while_waiting(recovers())
    assert await task == "recovered"


async def test_every_step_runs_in_the_given_context() -> None:
    future: asyncio.Future[None] = asyncio.get_running_loop().create_future()
    seen: list[str] = []

    async def sets_and_reads() -> str:
        seen.append(tag.get())
        tag.set("inside")
        await future
        seen.append(tag.get())
        return tag.get()

    context = contextvars.copy_context()
    steps = first_step(sets_and_reads(), context)
    assert tag.get() == "outside"  # the first step did not touch this task's context
    assert isinstance(steps, Pending)
    future.set_result(None)
    assert await finish(steps) == "inside"
    assert seen == ["outside", "inside"] and tag.get() == "outside"
    assert context[tag] == "inside"


async def test_sleep_zero_yields_once_and_finishes() -> None:
    async def yields_once() -> str:
        await asyncio.sleep(0)
        return "done"

    steps = first_step(yields_once())
    assert isinstance(steps, Pending) and steps.yielded is None
    assert await finish(steps) == "done"


# --- finish_within: finish under a deadline ------------------------------------------------


def waiting_forever(recovers: bool = False) -> Pending:
    """A coroutine suspended on an event nobody sets; it may swallow its cancellation."""

    async def waits() -> str:
        try:
            await asyncio.Event().wait()
        except asyncio.CancelledError:
            if not recovers:
                raise
        return "swallowed"

    steps = first_step(waits())
    assert isinstance(steps, Pending)
    return steps


async def test_a_passed_deadline_raises_expired_and_takes_its_cancellation_back() -> None:
    task = asyncio.current_task()
    assert task is not None
    with pytest.raises(Expired):
        await finish_within(waiting_forever(), 0.01)
    assert task.cancelling() == 0
    assert issubclass(Expired, TimeoutError)


async def test_a_coroutine_that_swallows_the_deadline_still_expires() -> None:
    with pytest.raises(Expired):
        await finish_within(waiting_forever(recovers=True), 0.01)


async def test_a_coroutine_done_in_time_returns_and_leaves_no_timer_behind() -> None:
    future: asyncio.Future[int] = asyncio.get_running_loop().create_future()
    steps = first_step(waits_for(future))
    assert isinstance(steps, Pending)
    asyncio.get_running_loop().call_soon(future.set_result, 1)
    assert await finish_within(steps, 0.05) == 2
    done = asyncio.Event()
    asyncio.get_running_loop().call_later(0.1, done.set)
    await done.wait()  # past the deadline: the disarmed timer cancels nothing
    task = asyncio.current_task()
    assert task is not None and task.cancelling() == 0


async def test_a_cancellation_other_than_the_deadlines_stays_a_cancellation() -> None:
    async def runner() -> Any:
        return await finish_within(waiting_forever(), 0.01)

    task = asyncio.create_task(runner())
    await asyncio.sleep(0)  # let it start waiting
    task.cancel()  # before the deadline
    with pytest.raises(asyncio.CancelledError):
        await task
