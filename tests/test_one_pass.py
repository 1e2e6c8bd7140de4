"""Reading a call in one pass on the server: the same answers as the full parse, always.

The server first offers each single request to its registry's ``read_call``
(:class:`~srvwire.models.CallReader`), which validates the whole message, envelope and params,
in one pass of pydantic-core; what it refuses is parsed in full and validated from the parsed
data, as it always was. So the one pass may refuse more than it must, never read anything
differently: for every part of every bundled type and of ROS 2's test corpus, a request it
reads is equal to what the full parse builds, with the same fields set, and a request the full
parse refuses, it refuses too. Through a real connection, on every transport, a server answers
every kind of message byte for byte as it does with the one pass turned off.
"""

from __future__ import annotations

import json
import math
from typing import Any

import pytest
from hypothesis import given, settings, strategies as st
from pydantic import ValidationError

import test_conformance as conformance
import test_decode as decoding
from conftest import Subtract, build, open_wire
from srvwire.dispatch import ServiceRegistry
from srvwire.errors import InvalidParams
from srvwire.loader import InterfaceLoader
from srvwire.models import CallReader, Message, validate_python, validate_wire
from srvwire.protocol import ReadRequest, Request, parse_incoming
from srvwire.server import Server, serve
from srvwire.transports.base import Transport

loader = conformance.loader  # the corpus, as the package test_msgs, in a temporary folder

LOOK_SRV = """\
int64 a
float64 b
string c
uint8[] d
float32 x
---
string seen
"""
Look = build(LOOK_SRV, "Look")


def envelope(params: str, id: str = "7", method: str = "/s") -> str:
    return f'{{"jsonrpc":"2.0","id":{id},"method":"{method}","params":{params}}}'


def in_full(cls: type[Message], text: str) -> Message | list[tuple[Any, ...]] | None:
    """What the full parse makes of a request: the validated params, the errors, or None when
    it is not a request with params by name at all."""
    (item,) = parse_incoming(text).items
    if type(item) is not Request or type(item.params) is not dict:
        return None
    try:
        return validate_wire(cls, item.params)
    except ValidationError as exc:
        return decoding.errors_of(exc)


def read(reader: CallReader, text: str) -> Message | None:
    result = reader.read(text)
    return None if result is None else result[2]  # type: ignore[no-any-return]


# --- the one pass and the full parse agree on every type ---------------------------------------


@pytest.mark.parametrize(("source", "name", "index"), decoding.PARTS, ids=decoding.PART_IDS)
def test_random_valid_requests_read_alike_in_one_pass_and_in_full(
    loader: InterfaceLoader, source: str, name: str, index: int
) -> None:
    interfaces, cls = decoding.part(loader, source, name, index)
    reader = CallReader({"/s": cls})
    in_one_pass = 0

    @settings(max_examples=10, deadline=None)
    @given(conformance.payloads(interfaces, cls.spec), st.booleans(), st.booleans())
    def check(payload: dict[str, Any], as_written_by_json: bool, meta: bool) -> None:
        nonlocal in_one_pass
        instance = cls.model_validate(payload)
        params = json.dumps(payload) if as_written_by_json else instance.model_dump_json()
        if meta:  # the deadline first, as srvwire's client writes it
            params = '{"_meta":{"timeout":2.5}' + ("," + params[1:] if params != "{}" else "}")
        text = envelope(params)
        expected = in_full(cls, text)
        assert isinstance(expected, cls) and conformance.same(expected, instance)
        result = reader.read(text)
        if result is None:
            return
        in_one_pass += 1
        id, method, request, timeout = result
        assert (id, method, timeout) == (7, "/s", 2.5 if meta else None)
        assert type(request) is cls and conformance.same(request, expected)
        assert request.model_fields_set == expected.model_fields_set
        assert request.__pydantic_extra__ is expected.__pydantic_extra__ is None
        assert list(request.__dict__) == list(expected.__dict__)  # no _meta left among them

    check()
    assert in_one_pass > 0  # what srvwire writes is read in one pass


@pytest.mark.parametrize(("source", "name", "index"), decoding.PARTS, ids=decoding.PART_IDS)
def test_wrong_requests_are_left_to_the_full_parse(
    loader: InterfaceLoader, source: str, name: str, index: int
) -> None:
    interfaces, cls = decoding.part(loader, source, name, index)
    reader = CallReader({"/s": cls})
    for document in decoding.documents(interfaces, cls.spec):
        for params in (document, '{"_meta":{"timeout":1},' + document[1:]):
            text = envelope(params)
            expected = in_full(cls, text)
            result = read(reader, text)
            if not isinstance(expected, cls):  # refused, or not params by name
                assert result is None, text
            elif result is not None:
                assert conformance.same(result, expected), text
                assert result.model_fields_set == expected.model_fields_set, text


def test_an_integer_beyond_a_double_in_a_float_field_reads_as_infinity_both_ways() -> None:
    # As 1e400 does: one rule for a number too large for a double, however it is written.
    cls = Look.Request
    reader = CallReader({"/s": cls})
    for literal, infinity in ((decoding.BEYOND_DOUBLE, math.inf), ("-1e400", -math.inf)):
        text = envelope(f'{{"b": {literal}}}')
        assert read(reader, text) == in_full(cls, text) == cls(b=infinity)
        batch = "-" + decoding.BEYOND_DOUBLE  # the full parse, which a batch takes, alike
        assert in_full(cls, envelope(f'{{"b": {batch}}}')) == cls(b=-math.inf)
    text = envelope(f'{{"c": "{decoding.BEYOND_DOUBLE}"}}')
    assert read(reader, text) == in_full(cls, text) == cls(c=decoding.BEYOND_DOUBLE)
    # In an integer field, it is out of range both ways.
    subtract = CallReader({"/s": Subtract.Request})
    assert read(subtract, envelope(f'{{"minuend": {decoding.BEYOND_DOUBLE}}}')) is None
    assert read(subtract, envelope('{"minuend": 5}')) == Subtract.Request(minuend=5)


@pytest.mark.parametrize(
    "text",
    [
        '{"jsonrpc":"2.0","method":"/s","params":{}}',  # a notification
        '[{"jsonrpc":"2.0","id":1,"method":"/s","params":{}}]',  # a batch
        '{"jsonrpc":"2.0","id":1,"method":"/other","params":{}}',
        '{"jsonrpc":"2.0","id":1,"method":"$/cancel","params":{"id":1}}',
        '{"jsonrpc":"2.0","id":1,"method":"rpc.discover"}',
        '{"jsonrpc":"2.0","id":1,"method":"/s"}',  # no params
        '{"jsonrpc":"2.0","id":1,"method":"/s","params":[1, 2]}',
        '{"jsonrpc":"2.0","id":1.5,"method":"/s","params":{}}',
        '{"jsonrpc":"2.0","id":null,"method":"/s","params":{}}',
        '{"jsonrpc":"2.0","id":true,"method":"/s","params":{}}',
        '{"jsonrpc":"1.0","id":1,"method":"/s","params":{}}',
        '{"jsonrpc":"2.0","id":1,"method":"/s","params":{"nope":1}}',
        '{"jsonrpc":"2.0","id":1,"method":"/s","params":{"_meta":{},"nope":1}}',
        '{"jsonrpc":"2.0","id":1,"method":"/s","params":{}',  # not JSON
        '{"jsonrpc":"2.0","id":1,"method":"/s","params":{}} x',
    ],
)
def test_what_is_not_a_plain_call_is_not_read_in_one_pass(text: str) -> None:
    assert CallReader({"/s": Subtract.Request}).read(text) is None


def test_a_class_srvwire_did_not_build_is_not_read_in_one_pass() -> None:
    from pydantic import BaseModel

    class Mine(BaseModel):
        a: int = 0

    assert CallReader({"/s": Mine}).read(envelope('{"a": 1}')) is None


def test_a_message_class_written_by_hand_is_not_read_in_one_pass() -> None:
    # JSON mode reads text into a strict date, bytes or enum field, and extra members into a
    # class that allows them, where the full parse refuses or keeps them: only the classes
    # srvwire builds, as it built them, are read in one pass.
    import datetime
    import enum
    from typing import Annotated

    from pydantic import ConfigDict, Strict

    class Color(enum.Enum):
        red = "red"

    class Mine(Message):
        d: Annotated[datetime.date, Strict()] = datetime.date(2000, 1, 1)
        b: Annotated[bytes, Strict()] = b""
        e: Annotated[Color, Strict()] = Color.red

    class Loose(Message):
        model_config = ConfigDict(extra="allow")
        a: int = 0

    class Changed(Subtract.Request):  # type: ignore[misc, valid-type]
        minuend: Annotated[datetime.date, Strict()] = datetime.date(2000, 1, 1)

    for params, model in [
        ('{"d": "2020-01-02"}', Mine),
        ('{"b": "abc"}', Mine),
        ('{"e": "red"}', Mine),
        ('{"a": 1, "z": 2}', Loose),
        ('{"minuend": "2020-01-02"}', Changed),
    ]:
        assert CallReader({"/s": model}).read(envelope(params)) is None, (model, params)
    with pytest.raises(ValidationError):
        validate_python(Mine, {"d": "2020-01-02"})
    nested = build("string s\n---\nbool ok\n", "Nested")
    assert CallReader({"/s": nested.Request}).read(envelope('{"s": "x"}')) is not None


def test_a_class_with_a_validator_of_its_own_is_left_to_the_full_parse() -> None:
    # Its validator may fail its own way (not a ValidationError): the full parse meets that
    # where it always did (dispatch answers INTERNAL), and the one pass never runs it.
    from typing import Annotated

    from pydantic import AfterValidator

    def boom(value: int) -> int:
        raise KeyError(value)

    class Odd(Message):
        a: Annotated[int, AfterValidator(boom)] = 0

    assert CallReader({"/s": Odd}).read(envelope('{"a": 1}')) is None
    with pytest.raises(KeyError):
        validate_python(Odd, {"a": 1})


def test_the_registry_reads_a_call_and_its_meta_in_one_pass() -> None:
    services = ServiceRegistry()
    services.add("/subtract", Subtract, lambda request: None)
    text = envelope('{"_meta":{"timeout":3},"minuend":2}', id='"x"', method="subtract")
    assert services.read_call(text) == ("x", "subtract", Subtract.Request(minuend=2), 3.0)
    # A bad _meta is the full parse's to answer.
    assert services.read_call(text.replace('{"timeout":3}', '{"timeout":-3}')) is None
    assert services.read_call(text.replace('{"timeout":3}', "[]")) is None
    # A change of services is seen at the next call.
    services.remove("/subtract")
    assert services.read_call(text) is None
    services.add("/subtract", Subtract, lambda request: None)
    assert services.read_call(text) is not None
    # What a handler gets is validated once: a request read in one pass is passed as it is.
    entry = services.get("/subtract")
    assert entry is not None
    request = Subtract.Request(minuend=2)
    assert entry.validate(request) is request
    with pytest.raises(InvalidParams):
        entry.validate({"minuend": "2"})


# --- through a real connection: the same answers with the one pass and without ----------------

B309 = decoding.BEYOND_DOUBLE
MESSAGES: list[str | bytes] = [
    # read in one pass
    '{"jsonrpc":"2.0","id":1,"method":"/look","params":{"_meta":{"timeout":5},"a":1,"c":"x"}}',
    '{"jsonrpc":"2.0","id":"s2","method":"look","params":{"a":2}}',
    '{"jsonrpc":"2.0","id":3,"method":"/look","params":{"_meta":{"timeout":5,"later":true}}}',
    '{"jsonrpc":"2.0","id":4,"method":"/look","params":{"_meta":{},"b":3}}',
    '{"jsonrpc":"2.0","id":5,"method":"/look","params":{"d":"AAE=","x":1.5}}',
    '{"jsonrpc":"2.0","id":6,"method":"/look","params":{"d":[0,1,255],"a":1,"a":2}}',
    '{"jsonrpc":"2.0","id":7,"method":"/look","params":{"_meta":{"timeout":0}}}',
    '{"jsonrpc":"2.0","id":8,"method":"/look","params":{"b":NaN,"c":"\\u00e9"},"x":1}',
    b'{"jsonrpc":"2.0","id":9,"method":"/look","params":{"c":"bytes"}}',
    '{"jsonrpc":"2.0","id":10,"method":"/subtract","params":{"minuend":5,"subtrahend":2}}',
    # a number too large for a double: infinity, as the full parse reads it too
    f'{{"jsonrpc":"2.0","id":28,"method":"/look","params":{{"b":{B309}}}}}',
    f'{{"jsonrpc":"2.0","id":29,"method":"/look","params":{{"c":"{B309}"}}}}',
    # left to the full parse
    '{"jsonrpc":"2.0","id":11,"method":"/look","params":{"a":"x"}}',
    '{"jsonrpc":"2.0","id":12,"method":"/look","params":{"zzz":1}}',
    '{"jsonrpc":"2.0","id":13,"method":"/look","params":{"_meta":5}}',
    '{"jsonrpc":"2.0","id":14,"method":"/look","params":{"_meta":{"timeout":-1}}}',
    '{"jsonrpc":"2.0","id":15,"method":"/look","params":{"_meta":{"timeout":true}}}',
    '{"jsonrpc":"2.0","id":16,"method":"/look","params":{"_meta":{"timeout":1e400}}}',
    '{"jsonrpc":"2.0","id":17.5,"method":"/look","params":{}}',
    '{"jsonrpc":"2.0","id":null,"method":"/look","params":{}}',
    '{"jsonrpc":"1.0","id":19,"method":"/look","params":{}}',
    '{"jsonrpc":"2.0","id":20,"method":"/look","params":[4, 2.5]}',
    '{"jsonrpc":"2.0","id":21,"method":"/look"}',
    '{"jsonrpc":"2.0","id":22,"method":"/nowhere","params":{}}',
    '{"jsonrpc":"2.0","method":"/look","params":{"a":1}}',
    '{"jsonrpc":"2.0","method":"/look","params":{"_meta":{"timeout":-1}}}',
    '[{"jsonrpc":"2.0","id":25,"method":"/look","params":{"a":1}},'
    '{"jsonrpc":"2.0","id":26,"method":"/look","params":{"a":"x"}},'
    '{"jsonrpc":"2.0","method":"/look","params":{}}]',
    '{"jsonrpc":"2.0","id":27,"method":"/look","params":{',
    '{"jsonrpc":"2.0","id":30,"method":"/look","params":{"c":"\\ud800"}}',
    '{"jsonrpc":"2.0","id":31,"method":"$/cancel","params":{"id":1}}',
    '{"jsonrpc":"2.0","id":32,"method":"/look","params":{"x":1e39}}',
    '{"jsonrpc":"2.0","id":33,"method":"/subtract","params":{"minuend":5.0}}',
]
ONE_PASS = 12  # the first twelve are read in one pass


def look_server() -> Server:
    srv = Server()

    async def look(request: Any) -> Any:
        seen = request.model_dump(exclude_unset=True)
        return {"seen": f"{seen!r} extra={request.__pydantic_extra__!r}"}

    srv.add_service("/look", Look, look)

    async def subtract(request: Any) -> Any:  # on the loop: answered in the order read
        return {"difference": request.minuend - request.subtrahend}

    srv.add_service("/subtract", Subtract, subtract)
    return srv


async def answers(running: Any) -> list[list[Any]]:
    """Send every message, each followed by a marker call; return what came back before each
    marker's reply: the message's answers (none for a notification)."""
    wire = await open_wire(running)
    try:
        outcomes = []
        for index, message in enumerate(MESSAGES):
            await wire.send(message)
            marker = f"marker {index}"
            await wire.send({"jsonrpc": "2.0", "id": marker, "method": "/subtract", "params": {}})
            got = []
            while True:
                reply = await wire.recv_reply()
                if isinstance(reply, dict) and reply.get("id") == marker:
                    break
                got.append(reply)
            outcomes.append(got)
        return outcomes
    finally:
        await wire.ws.close()


async def test_every_message_is_answered_alike_with_and_without_the_one_pass(
    transport: Transport, monkeypatch: pytest.MonkeyPatch
) -> None:
    read_call = CallReader.read
    taken: list[str | bytes] = []

    def recording(self: CallReader, data: str | bytes) -> ReadRequest | None:
        request = read_call(self, data)
        if request is not None and not str(request[0]).startswith("marker"):
            taken.append(data if isinstance(data, str) else bytes(data).decode())
        return request

    monkeypatch.setattr(CallReader, "read", recording)
    async with serve(look_server(), "127.0.0.1", 0, transport=transport) as running:
        with_one_pass = await answers(running)
    sent_as_text = [m if isinstance(m, str) else m.decode() for m in MESSAGES[:ONE_PASS]]
    assert taken == sent_as_text

    monkeypatch.setattr(CallReader, "read", lambda self, data: None)
    async with serve(look_server(), "127.0.0.1", 0, transport=transport) as running:
        in_full_only = await answers(running)
    assert with_one_pass == in_full_only
    # And they are the answers these messages have always had.
    seen = [outcome[0]["result"]["seen"] if outcome else None for outcome in with_one_pass[:3]]
    assert seen == [
        "{'a': 1, 'c': 'x'} extra=None",
        "{'a': 2} extra=None",
        "{} extra=None",
    ]
    assert with_one_pass[6][0]["error"]["data"]["status"] == "DEADLINE_EXCEEDED"
    assert with_one_pass[10][0]["result"]["seen"] == "{'b': inf} extra=None"
    assert with_one_pass[13][0]["error"]["data"]["errors"][0]["path"] == "zzz"
    assert with_one_pass[24:26] == [[], []]  # notifications
