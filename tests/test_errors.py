"""The error table: every code has a class, and every class survives the trip over the wire."""

from __future__ import annotations

import pytest

from srvwire import errors
from srvwire.errors import (
    ConnectionLost,
    DeadlineExceeded,
    ErrorCode,
    InterfaceNotFoundError,
    InterfaceSyntaxError,
    InvalidParams,
    RPCError,
    ServiceError,
    ServiceUnavailable,
    error_class_for_code,
    error_from_code,
)


@pytest.mark.parametrize("code", list(ErrorCode))
def test_every_code_has_a_class_that_round_trips(code: ErrorCode) -> None:
    cls = error_class_for_code(code)
    assert cls.code == code
    assert cls.status == code.name
    sent = cls("it failed", {"detail": 1}, service="/svc")
    wire = sent.to_error_object()
    assert wire == {
        "code": int(code),
        "message": "it failed",
        "data": {"status": code.name, "detail": 1},
    }
    received = error_from_code(wire["code"], wire["message"], wire["data"], service="/svc")
    assert type(received) is cls
    assert (received.code, received.message, received.data) == (code, "it failed", {"detail": 1})
    assert received.service == "/svc"


def test_every_rpc_error_class_is_in_the_table() -> None:
    classes = {
        value
        for value in vars(errors).values()
        if isinstance(value, type) and issubclass(value, RPCError)
    }
    mapped = {error_class_for_code(code) for code in ErrorCode}
    # The base, the application error and the client-only subclass are the three extras.
    assert classes - mapped == {RPCError, ServiceError, ConnectionLost}


def test_application_error_round_trips_with_its_own_data() -> None:
    sent = ServiceError(4001, "gripper jammed", {"joint": 3})
    wire = sent.to_error_object()
    assert wire == {"code": 4001, "message": "gripper jammed", "data": {"joint": 3}}
    received = error_from_code(4001, "gripper jammed", {"joint": 3}, service="/grip")
    assert isinstance(received, ServiceError)
    assert (received.code, received.data) == (4001, {"joint": 3})
    assert str(received) == "application error (4001) [/grip]: gripper jammed"


@pytest.mark.parametrize("code", [-32000, -32768, -32050])
def test_service_error_refuses_reserved_codes(code: int) -> None:
    with pytest.raises(ValueError, match="reserves"):
        ServiceError(code, "no")


def test_unknown_reserved_code_becomes_the_base_class() -> None:
    received = error_from_code(-32099, "server specific")
    assert type(received) is RPCError
    assert received.code == -32099


def test_deadline_exceeded_is_a_timeout_error() -> None:
    assert issubclass(DeadlineExceeded, TimeoutError)
    assert issubclass(ConnectionLost, ServiceUnavailable)


def test_invalid_params_exposes_field_errors() -> None:
    error = InvalidParams("bad", {"errors": [{"path": "a.b", "message": "m", "type": "t"}]})
    assert error.errors == [{"path": "a.b", "message": "m", "type": "t"}]
    assert InvalidParams("bad").errors == []


def test_messages_are_built_from_attributes() -> None:
    syntax = InterfaceSyntaxError("expected a type", path="pkg/srv/X.srv", line=3, column=1)
    assert str(syntax) == "pkg/srv/X.srv:3:1: expected a type"
    assert str(InterfaceSyntaxError("m", path=None, line=1, column=2)) == "<string>:1:2: m"
    missing = InterfaceNotFoundError("pkg/Nope", "no type 'pkg/Nope'", candidates=("pkg/Nop",))
    assert str(missing) == "no type 'pkg/Nope' (did you mean: pkg/Nop?)"
    assert str(DeadlineExceeded("no answer in 1s", service="/s")) == (
        "DEADLINE_EXCEEDED (-32001) [/s]: no answer in 1s"
    )
