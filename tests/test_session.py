"""The session rules, checked with no event loop and no socket: bytes in, events and bytes out.

A :class:`~srvwire.session.ClientSession` and a :class:`~srvwire.session.ServerSession` are
joined by handing each one's bytes to the other, so a whole conversation runs synchronously.
"""

from __future__ import annotations

import json
from typing import Any

import pytest

from conftest import Echo, Subtract
from srvwire.dispatch import ServiceEntry, ServiceRegistry
from srvwire.errors import (
    Cancelled,
    ErrorCode,
    InvalidRequest,
    ServiceNotFound,
    ServiceUnavailable,
)
from srvwire.models import ModelDecoder
from srvwire.protocol import ErrorResponse, ProtocolViolation, RawReply, Response
from srvwire.session import (
    Call,
    CancelCall,
    ClientSession,
    Dropped,
    Notice,
    NotificationCall,
    ServerSession,
    ServicesChanged,
    Stray,
)
from srvwire.typeregistry import fingerprint, full_definition


def registry() -> ServiceRegistry:
    services = ServiceRegistry()
    services.add("/subtract", Subtract, lambda request: None)
    services.add("/echo", Echo, lambda request: None)
    return services


@pytest.fixture
def server() -> ServerSession[ServiceEntry]:
    return ServerSession(registry(), max_in_flight=3)


def send(server: ServerSession[ServiceEntry], message: Any) -> list[Any]:
    """Hand ``message`` (JSON-encoded unless it is text or bytes) to the server session."""
    data = message if isinstance(message, str | bytes) else json.dumps(message)
    return server.receive(data)


def call(id: Any, method: str = "subtract", params: Any = None) -> dict[str, Any]:
    message: dict[str, Any] = {"jsonrpc": "2.0", "id": id, "method": method}
    if params is not None:
        message["params"] = params
    return message


def note(method: str, params: Any = None) -> dict[str, Any]:
    message: dict[str, Any] = {"jsonrpc": "2.0", "method": method}
    if params is not None:
        message["params"] = params
    return message


def reply_of(data: bytes) -> Any:
    assert isinstance(data, bytes)
    return json.loads(data)


def only(events: list[Any]) -> Any:
    assert len(events) == 1, events
    return events[0]


# --- the server's side ----------------------------------------------------------------------


def test_a_call_is_admitted_and_answered(server: ServerSession[ServiceEntry]) -> None:
    started = only(send(server, call(7, params={"minuend": 5, "_meta": {"timeout": 2.5}})))
    assert type(started) is Call
    # Read in one pass: the params are the service's request, validated, without _meta.
    assert (started.id, started.entry.name, started.params, started.timeout) == (
        7,
        "/subtract",
        Subtract.Request(minuend=5),
        2.5,
    )
    assert server.in_flight == 1 and server.calls == {7: started}
    assert server.answering(started)
    assert reply_of(server.reply(started, b'{"difference":5}')) == {  # type: ignore[arg-type]
        "jsonrpc": "2.0",
        "id": 7,
        "result": {"difference": 5},
    }
    assert server.calls == {} and not server.answering(started)  # $/cancel no longer finds it
    assert server.in_flight == 1  # but it counts until its reply has gone out
    server.sent(started)
    assert server.in_flight == 0


def test_a_failed_call_is_answered_with_its_error(server: ServerSession[ServiceEntry]) -> None:
    started = only(send(server, call("a")))
    answer = reply_of(server.fail(started, Cancelled("stop")))  # type: ignore[arg-type]
    assert answer["id"] == "a"
    assert answer["error"]["code"] == ErrorCode.CANCELLED
    server.sent(started)
    assert server.in_flight == 0


def test_what_is_not_a_service_is_answered_at_once(server: ServerSession[ServiceEntry]) -> None:
    unknown = reply_of(only(send(server, call(1, "subtrakt"))))
    assert unknown["error"]["code"] == ServiceNotFound.code
    assert unknown["error"]["data"]["candidates"] == ["/subtract"]
    discovered = reply_of(only(send(server, call(2, "rpc.discover"))))
    assert [m["name"] for m in discovered["result"]["methods"]] == ["/echo", "/subtract"]
    broken = reply_of(only(send(server, "{not json")))
    assert (broken["id"], broken["error"]["code"]) == (None, ErrorCode.PARSE_ERROR)
    assert server.in_flight == 0


def test_past_the_in_flight_limit_a_call_is_refused(server: ServerSession[ServiceEntry]) -> None:
    held = [only(send(server, call(i))) for i in range(3)]
    refused = reply_of(only(send(server, call(3))))
    assert refused["error"]["code"] == ErrorCode.RESOURCE_EXHAUSTED
    assert refused["error"]["data"]["limit"] == 3
    server.reply(held[0], b"{}")
    assert type(only(send(server, call(3)))) is bytes  # its reply has not gone out yet
    server.sent(held[0])
    assert type(only(send(server, call(4)))) is Call


def test_an_id_in_flight_cannot_be_used_again(server: ServerSession[ServiceEntry]) -> None:
    first = only(send(server, call(1)))
    for again in (1, 1.0):
        duplicate = reply_of(only(send(server, call(again))))
        assert duplicate["error"]["code"] == ErrorCode.INVALID_REQUEST
        assert "already used" in duplicate["error"]["message"]
    server.reply(first, b"{}")  # written, so the id is free again
    assert type(only(send(server, call(1)))) is Call


def test_cancel_names_a_call_by_its_id(server: ServerSession[ServiceEntry]) -> None:
    one = only(send(server, call(1)))
    text = only(send(server, call("1")))
    for wrong in (True, "01", None, [1], {"a": 1}):
        assert send(server, note("$/cancel", {"id": wrong})) == [], wrong
    assert only(send(server, note("$/cancel", {"id": 1.0}))).call is one  # the same number
    cancel = only(send(server, note("$/cancel", {"id": 1})))
    assert type(cancel) is CancelCall and cancel.call is one
    assert isinstance(cancel.error, Cancelled)
    assert only(send(server, note("$/cancel", {"id": "1"}))).call is text
    assert send(server, note("$/cancel", {"id": 99})) == []
    assert send(server, note("$/cancel", ["bad"])) == []


def test_cancel_as_a_request_is_acknowledged(server: ServerSession[ServiceEntry]) -> None:
    running = only(send(server, call(1)))
    cancel, ack = send(server, call(2, "$/cancel", {"id": 1}))
    assert cancel.call is running
    assert reply_of(ack) == {"jsonrpc": "2.0", "id": 2, "result": None}


@pytest.mark.parametrize(
    ("params", "path", "problem", "kind"),
    [
        (None, "id", "missing", "missing"),
        ({}, "id", "missing", "missing"),
        ({"call": 1}, "id", "missing", "missing"),
        ([1], "", "must be an object, not an array", "dict_type"),
        ({"id": None}, "id", "must be a string or a number, not null", "id_type"),
        ({"id": True}, "id", "must be a string or a number, not a boolean", "id_type"),
        ({"id": [1]}, "id", "must be a string or a number, not an array", "id_type"),
    ],
)
def test_a_cancel_request_without_an_id_is_answered_invalid_params(
    server: ServerSession[ServiceEntry], params: Any, path: str, problem: str, kind: str
) -> None:
    """A ``$/cancel`` request that names no call gets INVALID_PARAMS with the field's path;
    sent as a notification, it gets nothing, as every notification; the call goes on."""
    running = only(send(server, call(1)))
    assert reply_of(only(send(server, call(2, "$/cancel", params)))) == {
        "jsonrpc": "2.0",
        "id": 2,
        "error": {
            "code": ErrorCode.INVALID_PARAMS,
            "message": 'invalid params: $/cancel needs the id of the call to cancel: {"id": 7}',
            "data": {
                "status": "INVALID_PARAMS",
                "errors": [{"path": path, "message": problem, "type": kind}],
            },
        },
    }
    assert send(server, note("$/cancel", params)) == []
    assert server.calls == {1: running}


def test_a_cancel_request_for_a_call_not_in_flight_is_acknowledged(
    server: ServerSession[ServiceEntry],
) -> None:
    for id in (99, "1", 1.5):
        assert reply_of(only(send(server, call(2, "$/cancel", {"id": id})))) == {
            "jsonrpc": "2.0",
            "id": 2,
            "result": None,
        }


@pytest.mark.parametrize("method", ["$/nope", "rpc.nope", "$/subscribe", ""])
def test_a_method_that_is_no_service_name_is_not_found_as_it_was_sent(
    server: ServerSession[ServiceEntry], method: str
) -> None:
    """A protocol method the server does not have (``$/…``, ``rpc.…``: here, topics are
    off), or an empty one, is named as sent, without the ``/`` a service name takes."""
    refused = reply_of(only(send(server, call(1, method))))
    assert refused["error"]["code"] == ErrorCode.SERVICE_NOT_FOUND
    assert refused["error"]["message"] == f'no method named "{method}"'
    assert refused["error"]["data"] == {"status": "SERVICE_NOT_FOUND", "candidates": []}


@pytest.mark.parametrize(("method", "named"), [("subtrakt", "/subtrakt"), ("/", "/")])
def test_a_service_name_not_found_is_named_with_its_slash(
    server: ServerSession[ServiceEntry], method: str, named: str
) -> None:
    refused = reply_of(only(send(server, call(1, method))))
    assert refused["error"]["message"].startswith(f"no service named {named}")


def test_a_call_that_cannot_be_named_is_still_found_at_shutdown(
    server: ServerSession[ServiceEntry],
) -> None:
    anonymous = only(send(server, call(None)))
    named = only(send(server, call(5)))
    assert server.anonymous == {anonymous}
    error = ServiceUnavailable("going away")
    assert {c.call for c in server.cancel_all(error)} == {anonymous, named}
    assert server.in_flight == 2  # they still answer
    assert reply_of(server.fail(anonymous, error))["id"] is None  # type: ignore[arg-type]
    server.sent(anonymous)
    assert server.in_flight == 1
    assert [c.call for c in server.cancel_all(None)] == [named]
    assert server.calls == {} and server.anonymous == set() and server.in_flight == 0


def test_a_closing_session_answers_unavailable(server: ServerSession[ServiceEntry]) -> None:
    server.close()
    refused = reply_of(only(send(server, call(1))))
    assert refused["error"]["code"] == ErrorCode.UNAVAILABLE
    assert reply_of(only(send(server, call(2, "rpc.discover"))))["error"]["code"] == (
        ErrorCode.UNAVAILABLE
    )
    assert send(server, note("subtract")) == []  # a notification is dropped silently


def test_a_notification_counts_until_it_is_done(server: ServerSession[ServiceEntry]) -> None:
    running = only(send(server, note("echo", {"text": "hi", "_meta": {"timeout": 1}})))
    assert type(running) is NotificationCall
    assert (running.params, running.timeout, running.in_batch) == ({"text": "hi"}, 1, False)
    assert server.in_flight == 1
    server.done(running)
    assert server.in_flight == 0
    assert send(server, note("nothing_here")) == []


def test_a_notification_that_cannot_run_is_dropped(server: ServerSession[ServiceEntry]) -> None:
    bad_meta = only(send(server, note("echo", {"_meta": {"timeout": -1}})))
    assert type(bad_meta) is Dropped and not bad_meta.busy
    assert "_meta.timeout" in bad_meta.reason
    for i in range(3):
        send(server, call(i))
    busy = only(send(server, note("echo")))
    assert type(busy) is Dropped and busy.busy
    assert server.in_flight == 3


def test_a_batch_is_answered_once_in_order(server: ServerSession[ServiceEntry]) -> None:
    events = send(
        server,
        [call(1), {"jsonrpc": "2.0"}, note("echo"), call(2, "nope"), call(3, "echo")],
    )
    first, notification, third = events
    assert type(first) is Call and type(third) is Call
    assert type(notification) is NotificationCall and notification.in_batch
    assert server.reply(third, b'{"text":"3"}') is None  # the batch waits for its first call
    answer = json.loads(server.reply(first, b"{}"))  # type: ignore[arg-type]
    assert [item["id"] for item in answer] == [1, None, 2, 3]
    assert answer[1]["error"]["code"] == ErrorCode.INVALID_REQUEST
    assert answer[2]["error"]["code"] == ErrorCode.SERVICE_NOT_FOUND
    assert answer[3]["result"] == {"text": "3"}


def test_a_call_is_answered_once_whatever_its_handler_does_later(
    server: ServerSession[ServiceEntry],
) -> None:
    # Cancelled while its handler runs on, a call is answered then; the handler's late result
    # or failure writes nothing, in a batch too, and the call counts until the runner says so.
    single = only(send(server, call(1)))
    assert reply_of(server.fail(single, Cancelled("stop")))["error"]["code"] == (  # type: ignore[arg-type]
        ErrorCode.CANCELLED
    )
    assert not server.answering(single)
    assert server.reply(single, b'{"difference":1}') is None
    assert server.fail(single, ServiceUnavailable("late")) is None
    first, second = send(server, [call(2), call(3, "echo")])
    assert server.fail(first, Cancelled("stop")) is None  # the batch waits for its second
    assert server.fail(first, ServiceUnavailable("late")) is None
    assert server.reply(first, b"{}") is None
    answer = json.loads(server.reply(second, b'{"text":"3"}'))  # type: ignore[arg-type]
    assert [item["id"] for item in answer] == [2, 3]
    assert answer[0]["error"]["code"] == ErrorCode.CANCELLED
    assert server.in_flight == 3
    for answered in (single, first, second):
        server.sent(answered)
    assert server.in_flight == 0


def test_one_call_batches_count_in_flight_like_single_calls(
    server: ServerSession[ServiceEntry],
) -> None:
    # The limit is 3: three one-call batches fill it, whatever comes next is refused.
    started = [only(send(server, [call(i)])) for i in range(3)]
    assert all(type(c) is Call for c in started) and server.in_flight == 3
    (refused,) = json.loads(only(send(server, [call(3)])))
    assert (refused["id"], refused["error"]["code"]) == (3, ErrorCode.RESOURCE_EXHAUSTED)
    assert reply_of(only(send(server, call(4))))["error"]["code"] == ErrorCode.RESOURCE_EXHAUSTED
    assert json.loads(server.reply(started[0], b"{}"))[0]["id"] == 0  # type: ignore[arg-type]
    assert server.in_flight == 3  # until its reply has been sent
    server.sent(started[0])
    assert server.in_flight == 2


def test_a_batch_without_calls_to_run(server: ServerSession[ServiceEntry]) -> None:
    answered = json.loads(only(send(server, [call(1, "nope"), 5])))
    assert [item["id"] for item in answered] == [1, None]
    assert send(server, [note("nope"), note("$/cancel", {"id": 1})]) == []
    assert reply_of(only(send(server, [])))["error"]["code"] == ErrorCode.INVALID_REQUEST


def test_a_cancel_in_the_same_batch_reaches_its_call(server: ServerSession[ServiceEntry]) -> None:
    started, cancel = send(server, [call(1), note("$/cancel", {"id": 1})])
    assert cancel.call is started


def test_the_announcement_lists_every_service(server: ServerSession[ServiceEntry]) -> None:
    # Each with the fingerprint of its type's full definition (typeregistry.fingerprint).
    echo, subtract = (fingerprint(full_definition(srv) or {}) for srv in (Echo, Subtract))
    assert json.loads(server.announcement()) == {
        "jsonrpc": "2.0",
        "method": "$/services",
        "params": {
            "services": [
                {"name": "/echo", "type": "srvwire_tests/srv/Echo", "fingerprint": echo},
                {
                    "name": "/subtract",
                    "type": "srvwire_tests/srv/Subtract",
                    "fingerprint": subtract,
                },
            ]
        },
    }
    assert echo != subtract and len(echo) == 16


def test_the_client_reads_the_fingerprints_and_does_without(
    server: ServerSession[ServiceEntry],
) -> None:
    client: ClientSession[str] = ClientSession()
    (announced,) = client.receive(server.announcement())
    assert announced.fingerprints == {
        "/echo": fingerprint(full_definition(Echo) or {}),
        "/subtract": fingerprint(full_definition(Subtract) or {}),
    }
    older = json.dumps(  # a server from before fingerprints
        {
            "jsonrpc": "2.0",
            "method": "$/services",
            "params": {"services": [{"name": "/a", "type": "p/srv/A"}]},
        }
    )
    (plain,) = client.receive(older)
    assert (plain.services, plain.fingerprints) == ({"/a": "p/srv/A"}, {})


# --- the client's side ----------------------------------------------------------------------


def test_requests_get_fresh_ids_and_carry_the_deadline() -> None:
    client: ClientSession[str] = ClientSession()
    first_id, first = client.request("/subtract", '{"minuend":3}', 1.5, "first")
    second_id, second = client.request("rpc.discover", None, None, "second")
    assert (first_id, second_id) == (1, 2)
    assert json.loads(first) == {
        "jsonrpc": "2.0",
        "id": 1,
        "method": "/subtract",
        "params": {"_meta": {"timeout": 1.5}, "minuend": 3},
    }
    assert json.loads(second) == {"jsonrpc": "2.0", "id": 2, "method": "rpc.discover"}
    assert client.pending == {1: "first", 2: "second"}


def test_params_as_bytes_are_written_as_the_same_params_as_text() -> None:
    # The time left is sent to the microsecond either way (from bytes, with six decimals).
    client: ClientSession[str] = ClientSession()
    for params in ('{"minuend":3}', "{}", '{"a":"%d"}'):
        text_id, as_text = client.request("/subtract", params, 1.4999996, "text")
        bytes_id, as_bytes = client.request("/subtract", params.encode(), 1.4999996, "bytes")
        assert b'"timeout":1.5}' in as_text and b'"timeout":1.500000}' in as_bytes
        assert json.loads(as_bytes) == {**json.loads(as_text), "id": bytes_id}
        assert json.loads(as_text)["id"] == text_id
    # Not an object written compactly, or no deadline: written the long way, all the same.
    _, spaced = client.request("/subtract", b'{ "minuend": 3 }', 1.5, "spaced")
    assert json.loads(spaced)["params"] == {"_meta": {"timeout": 1.5}, "minuend": 3}
    _, bare = client.request("/subtract", b'{"minuend":3}', None, "bare")
    assert json.loads(bare)["params"] == {"minuend": 3}
    with pytest.raises(ValueError):
        client.request("/subtract", b"[3]", 1.5, "not an object")
    assert "not an object" not in client.pending.values()


def test_a_reply_reaches_its_waiter_unparsed() -> None:
    client: ClientSession[str] = ClientSession()
    id, _ = client.request("/subtract", "{}", 1.0, "waiter")
    ((waiter, raw),) = client.receive(Response(id, {"difference": 2}).serialize().decode())
    assert waiter == "waiter" and type(raw) is RawReply
    assert raw.decode() == {"difference": 2}
    assert raw.decode(ModelDecoder(Subtract.Response)) == Subtract.Response(difference=2)
    assert client.pending == {}


def test_a_reply_that_does_not_fit_its_type_is_read_in_full() -> None:
    client: ClientSession[str] = ClientSession()
    id, _ = client.request("/subtract", "{}", 1.0, "waiter")
    ((_, raw),) = client.receive(f'{{"jsonrpc":"2.0","id":{id},"result":{{"difference":"x"}}}}')
    with pytest.raises(ValueError, match="difference"):
        raw.decode(ModelDecoder(Subtract.Response))
    twice = RawReply(1, '{"jsonrpc":"2.0","id":1,"result":{},"id":2}', 29)
    with pytest.raises(ProtocolViolation, match="'id' given twice"):
        twice.decode(ModelDecoder(Subtract.Response))
    method = RawReply(1, '{"jsonrpc":"2.0","id":1,"result":{},"method":"x"}', 29)
    with pytest.raises(ProtocolViolation, match="both 'result' and 'method'"):
        method.decode()


def test_an_error_reply_raises_its_error() -> None:
    client: ClientSession[str] = ClientSession()
    id, _ = client.request("/x", "{}", 1.0, "waiter")
    ((_, reply),) = client.receive(ErrorResponse(id, ServiceNotFound("no")).serialize())
    with pytest.raises(ServiceNotFound, match="no"):
        reply.decode()


def test_replies_nobody_waits_for_are_strays() -> None:
    client: ClientSession[str] = ClientSession()
    late = client.receive(Response(41, 1).serialize())
    unreadable = client.receive(ErrorResponse(None, InvalidRequest("bad")).serialize())
    assert [type(e) for e in (*late, *unreadable)] == [Stray, Stray]


def test_services_are_announced_by_canonical_name() -> None:
    client: ClientSession[str] = ClientSession()
    message = {"jsonrpc": "2.0", "method": "$/services", "params": {"services": []}}
    message["params"] = {"services": [{"name": "a", "type": "p/srv/A"}]}
    (changed,) = client.receive(json.dumps(message))
    assert changed == ServicesChanged({"/a": "p/srv/A"})
    # Other notifications are handed on, parsed, to whoever follows their method.
    later = {"jsonrpc": "2.0", "method": "$/goal", "params": {"call": 1}}
    assert client.receive(json.dumps(later)) == [Notice("$/goal", {"call": 1})]


@pytest.mark.parametrize(
    ("message", "error"),
    [
        ("{", "Parse error"),
        ('{"jsonrpc":"1.0","id":1,"result":1}', "'jsonrpc' must be exactly"),
        ('{"jsonrpc":"2.0","method":"$/services","params":{}}', "needs params"),
        (
            '{"jsonrpc":"2.0","method":"$/services","params":{"services":[1]}}',
            "entries need a string",
        ),
    ],
)
def test_what_is_not_json_rpc_is_a_violation(message: str, error: str) -> None:
    client: ClientSession[str] = ClientSession()
    with pytest.raises(ProtocolViolation, match=error):
        client.receive(message)


def test_giving_up_on_a_call_writes_its_cancel_once() -> None:
    client: ClientSession[str] = ClientSession()
    id, _ = client.request("/x", "{}", 1.0, "waiter")
    assert json.loads(client.cancel(id) or b"") == {
        "jsonrpc": "2.0",
        "method": "$/cancel",
        "params": {"id": id},
    }
    assert client.cancel(id) is None
    assert client.receive(Response(id, 1).serialize()) == [Stray(Response(id, 1))]


def test_a_lost_connection_hands_back_every_waiter() -> None:
    client: ClientSession[str] = ClientSession()
    client.request("/x", "{}", 1.0, "a")
    client.request("/x", "{}", 1.0, "b")
    assert client.lost() == ["a", "b"]
    assert client.pending == {}


# --- a conversation -------------------------------------------------------------------------


def test_a_session_pair_talks_with_no_loop(server: ServerSession[ServiceEntry]) -> None:
    client: ClientSession[str] = ClientSession()
    (services,) = client.receive(server.announcement())
    assert type(services) is ServicesChanged and "/subtract" in services.services
    _, request = client.request("/subtract", '{"minuend":9,"subtrahend":4}', 3.0, "mine")
    started = only(server.receive(request))
    assert started.params == Subtract.Request(minuend=9, subtrahend=4)
    difference = started.params.minuend - started.params.subtrahend
    answer = server.reply(started, json.dumps({"difference": difference}).encode())
    ((waiter, reply),) = client.receive(answer.decode())  # type: ignore[union-attr]
    assert waiter == "mine"
    assert reply.decode(ModelDecoder(Subtract.Response)).difference == 5
    # A call the client gives up on is cancelled on the server.
    id, request = client.request("/subtract", "{}", 3.0, "later")
    started = only(server.receive(request))
    cancel = only(server.receive(client.cancel(id) or b""))
    assert cancel.call is started
    late = server.fail(started, cancel.error)  # type: ignore[arg-type]
    assert type(only(client.receive(late or b""))) is Stray


def test_a_violation_anywhere_in_a_batch_leaves_every_call_pending() -> None:
    client: ClientSession[str] = ClientSession()
    id, _ = client.request("/x", "{}", 1.0, "caller")
    batch = (
        f'[{{"jsonrpc":"2.0","id":{id},"result":{{}}}},'
        '{"jsonrpc":"2.0","method":"$/services","params":{}}]'
    )
    with pytest.raises(ProtocolViolation):
        client.receive(batch)
    assert client.lost() == ["caller"]  # to be failed with the connection, not to wait


def test_a_batch_longer_than_the_limit_is_one_invalid_request() -> None:
    limited: ServerSession[ServiceEntry] = ServerSession(registry(), max_batch=3)
    assert [type(e) for e in limited.receive(json.dumps([call(i) for i in range(3)]))] == [Call] * 3
    refused = reply_of(only(limited.receive(json.dumps([note("echo")] * 4))))
    assert (refused["id"], refused["error"]["code"]) == (None, ErrorCode.INVALID_REQUEST)
    assert refused["error"]["message"] == (
        "Invalid Request: a batch of 4 messages; at most 3 are read in one batch"
    )
    assert limited.in_flight == 3  # the refused batch started nothing


def test_discovery_is_answered_once_per_batch(server: ServerSession[ServiceEntry]) -> None:
    answers = json.loads(only(send(server, [call(1, "rpc.discover"), call(2, "rpc.discover")])))
    assert "methods" in answers[0]["result"]
    assert answers[1]["error"]["code"] == ErrorCode.INVALID_REQUEST
    assert answers[1]["error"]["message"] == (
        "Invalid Request: rpc.discover is answered once per batch"
    )
    assert "methods" in reply_of(only(send(server, call(3, "rpc.discover"))))["result"]


# --- scopes and expired credentials -------------------------------------------------------------


def scoped_registry() -> ServiceRegistry:
    services = registry()
    services.add("/arm", Subtract, lambda request: None, scopes={"robot:write", "robot:arm"})
    return services


def test_a_call_without_every_scope_is_denied_before_its_params_are_read() -> None:
    session: ServerSession[ServiceEntry] = ServerSession(
        scoped_registry(), scopes=frozenset({"robot:write"})
    )
    reply = reply_of(only(send(session, call(1, "/arm", {"minuend": "not a number"}))))
    assert reply["error"] == {
        "code": -32006,
        "message": "permission denied: /arm needs the scope robot:arm, which this "
        "connection's identity does not hold",
        "data": {"status": "PERMISSION_DENIED", "missing_scopes": ["robot:arm"]},
    }
    assert session.in_flight == 0
    dropped = only(send(session, note("/arm")))
    assert isinstance(dropped, Dropped) and dropped.reason.startswith("permission denied")
    allowed: ServerSession[ServiceEntry] = ServerSession(
        scoped_registry(), scopes=frozenset({"robot:write", "robot:arm", "more"})
    )
    assert isinstance(only(send(allowed, call(1, "/arm"))), Call)


def test_discovery_and_announcement_list_only_what_the_connection_may_call() -> None:
    services = scoped_registry()
    plain: ServerSession[ServiceEntry] = ServerSession(services)
    names = [s["name"] for s in json.loads(plain.announcement())["params"]["services"]]
    assert names == ["/echo", "/subtract"]
    document = reply_of(only(send(plain, call(1, "rpc.discover"))))["result"]
    assert [m["name"] for m in document["methods"]] == ["/echo", "/subtract"]
    full: ServerSession[ServiceEntry] = ServerSession(
        services, scopes=frozenset({"robot:write", "robot:arm"})
    )
    document = reply_of(only(send(full, call(1, "rpc.discover"))))["result"]
    assert [m["name"] for m in document["methods"]] == ["/arm", "/echo", "/subtract"]
    assert services.services() == services.services(frozenset({"robot:write", "robot:arm"}))


def test_expired_credentials_answer_unauthenticated_and_drop_notifications() -> None:
    session = ServerSession(registry())
    running = only(send(session, call(1)))
    session.expire()
    reply = reply_of(only(send(session, call(2, "/echo"))))
    assert reply["error"]["code"] == -32005
    assert reply["error"]["message"] == (
        "the credentials of this connection expired; reconnect with fresh ones"
    )
    assert isinstance(only(send(session, note("/echo"))), Dropped)
    assert session.answering(running)  # a call already admitted still answers
