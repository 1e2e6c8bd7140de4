"""The registry and the dispatch of one request to one handler, without sockets."""

from __future__ import annotations

import asyncio
import json
import logging
import threading
import time
from typing import Any

import pytest

from conftest import Bounded, Echo, Subtract, subtract
from srvwire.dispatch import Context, ServiceRegistry, dispatch, normalize_name
from srvwire.errors import (
    DeadlineExceeded,
    InternalError,
    InvalidParams,
    RegistrationError,
    ServiceError,
    ServiceNotFound,
)
from srvwire.loader import load_service
from support import scaled

# --- names ---------------------------------------------------------------------------------------

RULE = "a name is segments of letters, digits and '_', each starting with a letter, joined by '/'"


@pytest.mark.parametrize(
    ("name", "canonical"),
    [
        ("add_two_ints", "/add_two_ints"),
        ("/add_two_ints", "/add_two_ints"),
        ("/robot1/get_robot_state", "/robot1/get_robot_state"),
        ("A/b_2/C", "/A/b_2/C"),
    ],
)
def test_good_names(name: str, canonical: str) -> None:
    assert normalize_name(name) == canonical


@pytest.mark.parametrize(
    ("name", "message"),
    [
        ("", f"service name '' is empty; {RULE}"),
        ("/", f"service name '/' is empty; {RULE}"),
        ("/a/", f"service name '/a/' ends with '/'; {RULE}"),
        ("/a//b", f"service name '/a//b' contains '//'; {RULE}"),
        ("//a", f"service name '//a' contains '//'; {RULE}"),
        ("/1robot", f"service name '/1robot' has the bad segment '1robot'; {RULE}"),
        ("/robot/_x", f"service name '/robot/_x' has the bad segment '_x'; {RULE}"),
        ("/get-state", f"service name '/get-state' has the bad segment 'get-state'; {RULE}"),
        ("rpc.discover", f"service name 'rpc.discover' has the bad segment 'rpc.discover'; {RULE}"),
        ("$/cancel", f"service name '$/cancel' has the bad segment '$'; {RULE}"),
    ],
)
def test_bad_names(name: str, message: str) -> None:
    with pytest.raises(RegistrationError) as caught:
        normalize_name(name)
    assert str(caught.value) == message


# --- registration --------------------------------------------------------------------------------


def test_registration_errors_verbatim() -> None:
    registry = ServiceRegistry()
    registry.add("subtract", Subtract, subtract)
    cases: list[tuple[Any, str]] = [
        (
            lambda: registry.add("/subtract", Echo, subtract),
            "a service named /subtract is already registered (srvwire_tests/srv/Subtract); "
            "remove it first",
        ),
        (
            lambda: registry.remove("/nothing"),
            "no service named /nothing is registered",
        ),
        (
            lambda: registry.add("/x", int, subtract),
            "the type of /x must be a service type with Request and Response models (such as "
            "load_service('example_interfaces/srv/AddTwoInts')), not <class 'int'>",
        ),
        (
            lambda: registry.add("/x", Subtract, 42),
            "the handler for /x must be callable, not int",
        ),
        (
            lambda: registry.add("/x", Subtract, lambda: None),
            "the handler for /x must take (request) or (request, response), plus optionally a "
            "context parameter; it takes 0 required positional parameters",
        ),
        (
            lambda: registry.add("/x", Subtract, lambda a, b, c: None),
            "the handler for /x must take (request) or (request, response), plus optionally a "
            "context parameter; it takes 3 required positional parameters",
        ),
        (
            lambda: registry.add("/x", Subtract, lambda a, *, key: None),
            "the handler for /x has the keyword-only parameter 'key' without a default; srvwire "
            "passes only the request, the response and a context",
        ),
    ]
    for action, message in cases:
        with pytest.raises(RegistrationError) as caught:
            action()
        assert str(caught.value) == message
    assert [entry.name for entry in registry] == ["/subtract"]


def test_handler_shapes_are_read_at_registration() -> None:
    registry = ServiceRegistry()

    async def plain(request: Any) -> Any: ...
    def ros(request: Any, response: Any) -> Any: ...
    def with_context(request: Any, ctx: Context) -> Any: ...
    async def named_context(request: Any, response: Any, context: Any) -> Any: ...
    def optional_extra(request: Any, response: Any = None, *, flag: bool = False) -> Any: ...

    class Callable:
        async def __call__(self, request: Any) -> Any: ...

    shapes = {
        "plain": (plain, (True, False, None)),
        "ros": (ros, (False, True, None)),
        "with_context": (with_context, (False, False, "ctx")),
        "named_context": (named_context, (True, True, "context")),
        "optional_extra": (optional_extra, (False, True, None)),
        "callable": (Callable(), (True, False, None)),
    }
    for name, (handler, expected) in shapes.items():
        entry = registry.add(name, Subtract, handler)
        assert (entry.is_async, entry.takes_response, entry.context_param) == expected, name


def test_lookup_with_and_without_the_slash_and_close_names() -> None:
    registry = ServiceRegistry()
    registry.add("/robot1/get_state", Subtract, subtract)
    registry.add("/robot2/get_state", Subtract, subtract)
    entry = registry.get("robot1/get_state")
    assert entry is not None and entry is registry.get("/robot1/get_state")
    assert "robot2/get_state" in registry and "robot3" not in registry and len(registry) == 2
    with pytest.raises(ServiceNotFound) as caught:
        registry.resolve("robot3/get_state")
    assert str(caught.value) == (
        "SERVICE_NOT_FOUND (-32601) [/robot3/get_state]: no service named /robot3/get_state; "
        "did you mean /robot2/get_state, /robot1/get_state?"
    )
    assert caught.value.data == {"candidates": ["/robot2/get_state", "/robot1/get_state"]}
    with pytest.raises(ServiceNotFound) as caught:
        registry.resolve("/zzz")
    assert caught.value.message == "no service named /zzz"
    assert caught.value.data == {"candidates": []}


def test_a_name_is_looked_up_in_one_dictionary_in_either_spelling() -> None:
    registry = ServiceRegistry()
    entry = registry.add("robot1/get_state", Subtract, subtract)
    # The bound get of a dict: a call looks a service up without a Python step of its own.
    assert type(registry.get) is type({}.get)
    assert registry.get("/robot1/get_state") is entry and registry.get("robot1/get_state") is entry
    for other in ("//robot1/get_state", "robot1", "/robot1/get_state/", "", "/"):
        assert registry.get(other) is None, other
    registry.remove("robot1/get_state")
    assert registry.get("/robot1/get_state") is None and registry.get("robot1/get_state") is None
    assert registry.add("/robot1/get_state", Echo, subtract) is registry.get("robot1/get_state")


def test_services_are_listed_sorted() -> None:
    registry = ServiceRegistry()
    registry.add("/b", Echo, subtract)
    registry.add("/a", Subtract, subtract)
    assert registry.services() == [
        ("/a", "srvwire_tests/srv/Subtract"),
        ("/b", "srvwire_tests/srv/Echo"),
    ]


def test_discovery_document() -> None:
    registry = ServiceRegistry()
    state = load_service("advanced_communication_tutorials/srv/RobotStateQuery")
    registry.add("/robot1/get_robot_state", state, subtract)
    registry.add("/subtract", Subtract, subtract)
    doc = registry.discover()
    assert doc["openrpc"] == "1.3.2"
    assert doc["info"]["title"] == "srvwire"
    assert [m["name"] for m in doc["methods"]] == ["/robot1/get_robot_state", "/subtract"]
    method = doc["methods"][0]
    assert method["paramStructure"] == "by-name"
    assert [p["name"] for p in method["params"]] == ["query_type", "target_frame"]
    assert all(p["required"] is False for p in method["params"])
    assert method["params"][0]["schema"]["type"] == "string"
    assert method["params"][0]["description"].startswith("Which state to report")
    assert method["result"]["name"] == "response"
    assert set(method["result"]["schema"]["properties"]) == {
        "success",
        "message",
        "values",
        "names",
    }
    assert method["x-srvwire-type"] == "advanced_communication_tutorials/srv/RobotStateQuery"
    assert method["x-srvwire-srv"] == state.text
    assert method["x-srvwire-request-schema"]["additionalProperties"] is False
    assert registry.discover_json() is registry.discover_json()  # cached
    registry.remove("/subtract")
    assert '"/subtract"' not in registry.discover_json()


def test_nested_schemas_are_inlined(ros_interfaces: Any) -> None:
    registry = ServiceRegistry()
    registry.add("/arrays", ros_interfaces.load_service("ros_test_interfaces/srv/Arrays"), subtract)
    text = registry.discover_json()
    assert "$ref" not in text and "$defs" not in text
    (method,) = registry.discover()["methods"]
    nested = {p["name"]: p["schema"] for p in method["params"]}["basic_types_values"]
    assert nested["type"] == "array" and nested["items"]["type"] == "object"
    assert "uint64_value" in nested["items"]["properties"]


# --- dispatch -------------------------------------------------------------------------------------


def context(deadline: float | None = None) -> Context:
    return Context(service="/t", request_id=1, peer=("127.0.0.1", 1), deadline=deadline)


async def run(handler: Any, params: Any, srv: Any = Subtract, ctx: Context | None = None) -> str:
    registry = ServiceRegistry()
    entry = registry.add("/t", srv, handler)
    return (await dispatch(entry, params, ctx or context())).decode()


async def test_by_name_by_position_and_defaults() -> None:
    assert await run(subtract, {"minuend": 42, "subtrahend": 23}) == '{"difference":19}'
    assert await run(subtract, [42, 23]) == '{"difference":19}'
    assert await run(subtract, [42]) == '{"difference":42}'
    assert await run(subtract, None) == '{"difference":0}'


async def test_every_handler_shape_answers() -> None:
    async def plain(request: Any) -> Any:
        return Subtract.Response(difference=1)

    def ros_returns(request: Any, response: Any) -> Any:
        response.difference = 2
        return response

    async def ros_mutates(request: Any, response: Any) -> None:
        response.difference = 3

    def as_dict(request: Any) -> Any:
        return {"difference": 4}

    async def with_context(request: Any, ctx: Context) -> Any:
        return {"difference": 5 if ctx.service == "/t" and ctx.request_id == 1 else 0}

    def empty(request: Any) -> None:
        return None

    for handler, expected in [
        (plain, 1),
        (ros_returns, 2),
        (ros_mutates, 3),
        (as_dict, 4),
        (with_context, 5),
    ]:
        assert await run(handler, {}) == f'{{"difference":{expected}}}'
    assert await run(empty, {}, load_service("std_srvs/srv/Empty")) == "{}"


async def test_sync_handlers_run_off_the_event_loop() -> None:
    loop_thread = threading.get_ident()
    seen: list[int] = []

    def handler(request: Any) -> Any:
        seen.append(threading.get_ident())
        return {"difference": 0}

    await run(handler, {})
    assert seen and seen[0] != loop_thread


async def test_too_many_positional_params() -> None:
    with pytest.raises(InvalidParams) as caught:
        await run(subtract, [1, 2, 3])
    assert caught.value.message == (
        "invalid params for /t: 3 positional params, but the request has 2 fields"
    )
    assert caught.value.errors == [
        {"path": "[2]", "message": "expected at most 2 params", "type": "too_long"}
    ]


async def test_invalid_params_point_at_the_fields() -> None:
    with pytest.raises(InvalidParams) as caught:
        await run(
            subtract, {"small": 256, "values": [1, 2, "x"], "name": "toolong", "zz": 1}, Bounded
        )
    assert caught.value.message == (
        "invalid params for /t: small: Input should be less than or equal to 255 (and 3 more)"
    )
    assert [(e["path"], e["type"]) for e in caught.value.errors] == [
        ("small", "less_than_equal"),
        ("values[2]", "int_type"),
        ("name", "string_too_long"),
        ("zz", "extra_forbidden"),
    ]


async def test_a_handler_that_raises_is_internal_and_logged(
    caplog: pytest.LogCaptureFixture,
) -> None:
    def broken(request: Any) -> Any:
        raise ZeroDivisionError("secret detail")

    with caplog.at_level(logging.ERROR, "srvwire.server"), pytest.raises(InternalError) as caught:
        await run(broken, {})
    assert caught.value.message == "handler for /t raised an exception"
    assert caught.value.data is None
    (record,) = caplog.records
    assert record.getMessage() == "handler for /t raised an exception (request id 1)"
    assert record.exc_info is not None and record.exc_info[0] is ZeroDivisionError


async def test_a_handler_own_timeout_error_is_internal_not_deadline() -> None:
    async def times_out(request: Any) -> Any:
        raise TimeoutError

    with pytest.raises(InternalError):
        await run(times_out, {}, ctx=context(time.monotonic() + scaled(10)))


async def test_service_errors_pass_through() -> None:
    async def refuses(request: Any) -> Any:
        raise ServiceError(7, "out of paper", {"tray": 2})

    with pytest.raises(ServiceError) as caught:
        await run(refuses, {})
    assert (caught.value.code, caught.value.message, caught.value.data) == (
        7,
        "out of paper",
        {"tray": 2},
    )
    assert caught.value.service == "/t"


@pytest.mark.parametrize(
    ("result", "reason"),
    [
        ({"difference": "many"}, "difference: Input should be a valid integer"),
        ({"nope": 1}, "nope: Extra inputs are not permitted"),
        (None, "expected Subtract_Response or a dict"),
        (Echo.Response(text="x"), "expected Subtract_Response or a dict"),
        (42, "expected Subtract_Response or a dict"),
    ],
)
async def test_an_invalid_return_is_internal_with_the_reason_logged(
    caplog: pytest.LogCaptureFixture, result: Any, reason: str
) -> None:
    async def handler(request: Any) -> Any:
        return result

    with caplog.at_level(logging.ERROR, "srvwire.server"), pytest.raises(InternalError) as caught:
        await run(handler, {})
    assert caught.value.message == "handler for /t returned an invalid response"
    (record,) = caplog.records
    assert record.getMessage() == (
        f"handler for /t returned {type(result).__name__}, which is not a valid "
        f"srvwire_tests/srv/Subtract response: {reason}"
    )


async def test_an_expired_deadline_does_not_run_the_handler() -> None:
    ran: list[bool] = []

    def handler(request: Any) -> Any:
        ran.append(True)

    with pytest.raises(DeadlineExceeded):
        await run(handler, {}, ctx=context(time.monotonic()))
    assert not ran


async def test_cancelling_the_task_marks_the_context() -> None:
    started = asyncio.Event()

    async def hangs(request: Any) -> Any:
        started.set()
        await asyncio.Event().wait()

    ctx = context()
    task = asyncio.create_task(run(hangs, {}, ctx=ctx))
    await started.wait()
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task
    assert ctx.cancelled and ctx.time_remaining() is None


@pytest.mark.parametrize("deadline", [None, scaled(10)])
async def test_a_cancellation_nobody_asked_for_is_internal_and_logged(
    deadline: float | None, caplog: pytest.LogCaptureFixture
) -> None:
    # The handler awaits a future something else cancelled: CancelledError, but this task is
    # not being cancelled. Letting it through would end the call without any reply.
    async def awaits_a_cancelled_future(request: Any) -> Any:
        future: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        future.cancel()
        await future

    ctx = context(None if deadline is None else time.monotonic() + deadline)
    with caplog.at_level(logging.ERROR, "srvwire.server"), pytest.raises(InternalError) as caught:
        await run(awaits_a_cancelled_future, {}, ctx=ctx)
    assert caught.value.message == "handler for /t raised an exception"
    (record,) = caplog.records
    assert record.exc_info is not None and record.exc_info[0] is asyncio.CancelledError
    assert not ctx.cancelled


async def test_a_sync_handler_raising_a_cancellation_is_internal() -> None:
    def raises(request: Any) -> Any:
        raise asyncio.CancelledError

    with pytest.raises(InternalError):
        await run(raises, {})


async def test_a_subclass_of_the_response_model_is_written_with_its_own_fields() -> None:
    class Annotated(Subtract.Response):  # type: ignore[name-defined,misc]
        note: str = "extra"

    async def handler(request: Any) -> Any:
        return Annotated(difference=4)

    assert json.loads(await run(handler, [6, 2])) == {"difference": 4, "note": "extra"}


async def test_an_async_handler_may_return_any_awaitable_with_or_without_a_deadline() -> None:
    # A function marked as a coroutine function (inspect.markcoroutinefunction, Python 3.12+)
    # may return a future rather than a coroutine; registered as async, it is awaited either way.
    import dataclasses

    def returns_a_future(request: Any) -> Any:
        future = asyncio.get_running_loop().create_future()
        future.set_result({"text": request.text})
        return future

    registry = ServiceRegistry()
    registry.add("/future", Echo, returns_a_future)
    entry = registry.get("/future")
    assert entry is not None
    marked = dataclasses.replace(entry, is_async=True)
    for deadline in (None, time.monotonic() + scaled(30)):
        context = Context(service="/future", deadline=deadline)
        assert await dispatch(marked, {"text": "hi"}, context) == b'{"text":"hi"}'


def test_a_context_whose_deadline_fired_has_no_time_left_whatever_the_clock_says() -> None:
    # uvloop runs a timer up to a millisecond early: the deadline's timer has fired, so the
    # time left is none, though the clock is a little short of the deadline.
    ctx = Context(service="/s", request_id=1, deadline=time.monotonic() + scaled(60))
    assert (ctx.time_remaining() or 0.0) > 0
    ctx._mark_cancelled(DeadlineExceeded("the deadline passed", service="/s"))
    assert ctx.cancelled and ctx.time_remaining() == 0.0
    cancelled = Context(service="/s", request_id=2, deadline=time.monotonic() + scaled(60))
    cancelled._mark_cancelled()  # cancelled otherwise: the deadline is still ahead
    assert (cancelled.time_remaining() or 0.0) > 0
