"""Reading a reply, without I/O: one ``decode`` per reply, whichever way it arrived.

:func:`peek_reply` must recognise what srvwire servers write and nothing that could mean something
else. A :class:`RawReply` validates its result text in one pass (``ModelDecoder.from_json``) and,
when that is refused, parses the whole message as :func:`parse_replies` does: a message that opens
as the response to a call but is not that response is a :class:`ProtocolViolation`. A
:class:`Response` decodes its parsed result (``ModelDecoder.from_data``); an
:class:`ErrorResponse` raises its error.

A topic's ``$/message`` is read the same way: :meth:`ClientSession.receive` recognises one as a
srvwire server writes it by its opening and hands it over as a :class:`TopicMessage` whose
``decode`` validates the message member in one pass, and parses the whole message when that is
refused; one that is not the ``$/message`` its opening says is a :class:`ProtocolViolation`.

For every part of every type srvwire bundles and of ROS 2's test corpus, the one pass and the
parsed reply (or ``$/message``) must give equal instances for random valid payloads, and refuse
the same wrong documents with errors at the same places, of the same types. They disagree in one
place, pinned below: pydantic-core reads an integer literal beyond the range of a double as
infinity in a float field when it validates JSON text (as it reads ``1e400``), and refuses the
Python int that parsing makes of it. A raw reply reads such a result as infinity; everything
else it decodes must be exactly what the parsed reply gives.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from typing import Any

import pytest
from hypothesis import given, settings, strategies as st
from pydantic import ValidationError

import test_conformance as conformance
from conftest import Subtract
from srvwire.errors import InvalidRequest, ParseError, ServiceError
from srvwire.idl import ArrayKind, MessageSpec
from srvwire.loader import InterfaceLoader, bundled_interfaces, load_message
from srvwire.models import Message, ModelDecoder
from srvwire.protocol import (
    ErrorResponse,
    ProtocolViolation,
    RawJSON,
    RawReply,
    Response,
    decode_json,
    parse_replies,
    peek_reply,
)
from srvwire.session import ClientSession, Notice, TopicMessage
from srvwire.topics import Outbox, QoS, Topic

# --- recognising a response by its opening ------------------------------------------------------


def test_what_srvwire_servers_write_is_recognised() -> None:
    message = Response(42, RawJSON(b'{"sum":3}')).serialize().decode()
    assert peek_reply(message) == RawReply(42, message, len('{"jsonrpc":"2.0","id":42,"result":'))
    raw = peek_reply(message)
    assert raw is not None and raw.result == '{"sum":3}'
    text = Response(7, [1, "ハ"]).serialize().decode()
    raw = peek_reply(text)
    assert raw is not None and (raw.id, raw.result) == (7, '[1,"ハ"]')
    largest = peek_reply('{"jsonrpc":"2.0","id":999999999999999999,"result":null}')
    assert largest is not None and largest.id == 10**18 - 1


@pytest.mark.parametrize(
    "message",
    [
        '{"jsonrpc": "2.0", "id": 1, "result": {}}',  # blanks: not how srvwire writes it
        '{"id":1,"jsonrpc":"2.0","result":{}}',  # another order
        '{"jsonrpc":"2.0","id":0,"result":{}}',  # no call of this client has id 0
        '{"jsonrpc":"2.0","id":-1,"result":{}}',
        '{"jsonrpc":"2.0","id":01,"result":{}}',  # not JSON
        '{"jsonrpc":"2.0","id":1.0,"result":{}}',
        '{"jsonrpc":"2.0","id":1e0,"result":{}}',
        '{"jsonrpc":"2.0","id":"1","result":{}}',
        '{"jsonrpc":"2.0","id":\u0661,"result":{}}',  # an Arabic-Indic one: int() would take it
        '{"jsonrpc":"2.0","id":1000000000000000000,"result":{}}',  # more digits than an id has
        '{"jsonrpc":"2.0","id":1,"result":{}} ',  # something after the final brace
        '{"jsonrpc":"2.0","id":1,"result":{}}\n',
        '{"jsonrpc":"2.0","id":1,"result":',
        '{"jsonrpc":"2.0","id":1,"error":{"code":1,"message":"m"}}',
        '{"jsonrpc":"2.0","method":"$/services","params":{"services":[]}}',
        '[{"jsonrpc":"2.0","id":1,"result":{}}]',
        '{"jsonrpc":"2.0","id":1,"result" :{}}',
        '{"jsonrpc":"1.0","id":1,"result":{}}',
    ],
)
def test_nothing_else_is_recognised(message: str) -> None:
    assert peek_reply(message) is None


def raw(message: str) -> RawReply:
    recognised = peek_reply(message)
    assert recognised is not None, message
    return recognised


# --- decoding a reply -----------------------------------------------------------------------------


def decoding(message: str) -> Callable[[], Message]:
    """Decode ``message`` as the reply to a Subtract call."""
    return lambda: raw(message).decode(ModelDecoder(Subtract.Response))


Errors = list[tuple[tuple[int | str, ...], str]]


def errors_of(exc: ValidationError) -> Errors:
    return [(error["loc"], error["type"]) for error in exc.errors()]


class Recording:
    """A :class:`ModelDecoder` that notes which of its two ways each decode took."""

    def __init__(self, model: type[Message]) -> None:
        self.decoder = ModelDecoder(model)
        self.calls: list[str] = []

    def from_json(self, text: str) -> Message:
        self.calls.append("from_json")
        return self.decoder.from_json(text)

    def from_data(self, data: Any) -> Message:
        self.calls.append("from_data")
        return self.decoder.from_data(data)


@pytest.mark.parametrize(
    ("message", "result"),
    [
        ('{"jsonrpc":"2.0","id":3,"result":{"sum":3}}', {"sum": 3}),
        ('{"jsonrpc":"2.0","id":3,"result":1,"x":2}', 1),  # more members: ignored, as always
        ('{"jsonrpc":"2.0","id":3,"result":1,"result":2}', 2),  # the last one counts
        ('{"jsonrpc":"2.0","id":3,"result":[1.5],"id":3}', [1.5]),  # the same id again
        ('{"jsonrpc":"2.0","id":3,"result":{} }', {}),
    ],
)
def test_a_raw_reply_parses_as_any_reply_does(message: str, result: object) -> None:
    assert raw(message).parse() == Response(3, result)
    assert raw(message).decode() == result
    assert parse_replies(message) == [Response(3, result)]


def test_a_result_is_validated_in_one_pass_and_else_from_the_parsed_reply() -> None:
    decoder = Recording(Subtract.Response)
    fits = raw('{"jsonrpc":"2.0","id":3,"result":{"difference":2}}')
    assert fits.decode(decoder) == Subtract.Response(difference=2)
    assert decoder.calls == ["from_json"]
    # What follows the result is only seen by the full parse: the last 'result' counts.
    decoder.calls.clear()
    twice = raw('{"jsonrpc":"2.0","id":3,"result":{"difference":1},"result":{"difference":2}}')
    assert twice.decode(decoder) == Subtract.Response(difference=2)
    assert decoder.calls == ["from_json", "from_data"]


def test_a_result_that_does_not_fit_is_refused_as_the_parsed_reply_refuses_it() -> None:
    decoder = ModelDecoder(Subtract.Response)
    with pytest.raises(ValidationError) as in_one_pass:
        raw('{"jsonrpc":"2.0","id":3,"result":{"difference":"x"}}').decode(decoder)
    with pytest.raises(ValidationError) as from_data:
        Response(3, {"difference": "x"}).decode(decoder)
    assert (
        errors_of(in_one_pass.value)
        == errors_of(from_data.value)
        == [(("difference",), "int_type")]
    )


@pytest.mark.parametrize(
    ("message", "error"),
    [
        (
            '{"jsonrpc":"2.0","id":3,"result":{},"error":{"code":1,"message":"m"}}',
            "Invalid reply: both 'result' and 'error'",
        ),
        (
            '{"jsonrpc":"2.0","id":3,"result":{},"method":"$/services","params":{}}',
            "Invalid reply: both 'result' and 'method'",
        ),
        (
            '{"jsonrpc":"2.0","id":3,"result":{},"id":4}',
            "Invalid reply: 'id' given twice (3 and 4)",
        ),
        (
            '{"jsonrpc":"2.0","id":3,"result":{},"id":"3"}',
            "Invalid reply: 'id' given twice (3 and '3')",
        ),
        (
            '{"jsonrpc":"2.0","id":3,"result":{},"id":3.0}',
            "Invalid reply: 'id' given twice (3 and 3.0)",
        ),
        (
            '{"jsonrpc":"2.0","id":3,"result":{},"jsonrpc":"1.0"}',
            "Invalid reply: 'jsonrpc' must be exactly \"2.0\"",
        ),
    ],
)
def test_a_raw_reply_that_is_not_the_response_it_opens_as_is_refused(
    message: str, error: str
) -> None:
    # With a decoder too: its result ({}) would fit, but the one pass never hides what follows.
    for decode in (raw(message).parse, raw(message).decode, decoding(message)):
        with pytest.raises(ProtocolViolation) as caught:
            decode()
        assert type(caught.value.error) is InvalidRequest
        assert caught.value.error.message == error
        assert str(caught.value) == error


@pytest.mark.parametrize(
    ("message", "error"),
    [
        (
            '{"jsonrpc":"2.0","id":3,"result":{]}',
            "Parse error: key must be a string at line 1 column 35",
        ),
        (
            '{"jsonrpc":"2.0","id":3,"result":1,x}',
            "Parse error: key must be a string at line 1 column 36",
        ),
        (
            '{"jsonrpc":"2.0","id":3,"result":"\\ud800"}',
            "Parse error: unexpected end of hex escape at line 1 column 41",
        ),
    ],
)
def test_a_raw_reply_that_is_not_json_is_a_parse_error(message: str, error: str) -> None:
    for decode in (raw(message).parse, raw(message).decode, decoding(message)):
        with pytest.raises(ProtocolViolation) as caught:
            decode()
        assert type(caught.value.error) is ParseError
        assert caught.value.error.message == error
        assert str(caught.value) == error


def test_a_response_decodes_its_parsed_result() -> None:
    decoder = ModelDecoder(Subtract.Response)
    assert Response(1, {"difference": 2}).decode() == {"difference": 2}
    assert Response(1, {"difference": 2}).decode(decoder) == Subtract.Response(difference=2)
    (reply,) = parse_replies('{"jsonrpc":"2.0","id":1,"result":{"difference":-4}}')
    assert isinstance(reply, Response)
    assert reply.decode(decoder) == Subtract.Response(difference=-4)


def test_an_error_reply_raises_the_error_it_carries() -> None:
    error = ServiceError(42, "out of paper", {"tray": 2})
    for decoder in (None, ModelDecoder(Subtract.Response)):
        with pytest.raises(ServiceError) as caught:
            ErrorResponse(9, error).decode(decoder)
        assert caught.value is error
    (reply,) = parse_replies(ErrorResponse(9, error).serialize())
    assert isinstance(reply, ErrorResponse)
    with pytest.raises(ServiceError) as caught:
        reply.decode(ModelDecoder(Subtract.Response))
    assert (caught.value.code, caught.value.message) == (42, "out of paper")
    assert caught.value.data == {"tray": 2}


# --- a topic's $/message ------------------------------------------------------------------------

String = load_message("std_msgs/msg/String")


def published(text: str, subscription: int = 7, skipped: int = 0) -> str:
    """``text`` as the message of a ``$/message``, written by a server's outbox (the topic's
    message number ``skipped + 1``, the ``skipped`` before it unseen by this subscriber)."""
    chatter = Topic("/chatter", None, QoS())
    for _ in range(skipped):
        chatter.publish(b"{}")
    outbox = Outbox()
    outbox.subscribe(subscription, chatter, QoS())
    chatter.publish(text.encode())
    subscribed, message = outbox.next(), outbox.next()
    assert subscribed is not None and message is not None
    return message.decode()


def recognised(message: str) -> TopicMessage:
    (event,) = ClientSession[object]().receive(message)
    assert type(event) is TopicMessage and event.start > 0, message
    return event


def read_topic(message: str) -> TopicMessage:
    """Read ``message`` as the client's session does, recognised or parsed."""
    (event,) = ClientSession[object]().receive(message)
    assert type(event) is TopicMessage, message
    return event


def test_a_message_as_srvwire_servers_write_it_is_read_up_to_its_message() -> None:
    message = published('{"data":"x"}', subscription=12, skipped=2)
    event = recognised(message)
    assert (event.id, event.seq, event.dropped) == (12, 3, 0)
    assert event.message[event.start : -2] == '{"data":"x"}'
    decoder = Recording(String)
    assert event.decode(decoder) == String(data="x")
    assert decoder.calls == ["from_json"]
    assert event.parse() == TopicMessage(12, 3, 0, {"data": "x"})


@pytest.mark.parametrize(
    ("message", "expected"),
    [
        # More members after the message: ignored, as the full parse ignores them.
        (
            '{"jsonrpc":"2.0","method":"$/message","params":{"subscription":7,"seq":1,'
            '"dropped":0,"message":{"data":"x"},"note":"later"}}',
            TopicMessage(7, 1, 0, {"data": "x"}),
        ),
        # The message member twice: the last one counts.
        (
            '{"jsonrpc":"2.0","method":"$/message","params":{"subscription":7,"seq":1,'
            '"dropped":0,"message":{"data":"x"},"message":{"data":"y"}}}',
            TopicMessage(7, 1, 0, {"data": "y"}),
        ),
        # The same seq again is the same seq.
        (
            '{"jsonrpc":"2.0","method":"$/message","params":{"subscription":7,"seq":1,'
            '"dropped":0,"message":{"data":"x"},"seq":1}}',
            TopicMessage(7, 1, 0, {"data": "x"}),
        ),
    ],
)
def test_what_follows_the_message_is_read_by_the_full_parse(
    message: str, expected: TopicMessage
) -> None:
    event = recognised(message)
    decoder = Recording(String)
    assert event.decode(decoder) == String.model_validate(expected.message)
    assert decoder.calls == ["from_json", "from_data"]
    assert event.parse() == expected


@pytest.mark.parametrize(
    "message",
    [
        # Written otherwise than a srvwire server writes it: parsed by the session at once.
        '{"jsonrpc":"2.0","method":"$/message","params":{"subscription":7,"seq":1,'
        '"message":{"data":"x"}}}',
        '{"jsonrpc": "2.0", "method": "$/message", "params": {"subscription": 7, "seq": 1, '
        '"dropped": 0, "message": {"data": "x"}}}',
        '{"method":"$/message","jsonrpc":"2.0","params":{"message":{"data":"x"},"seq":1,'
        '"subscription":7}}',
        '{"jsonrpc":"2.0","method":"$/message","params":{"subscription":7,"seq":1,'
        '"dropped":0,"message":{"data":"x"}},"extra":[1]}',
    ],
)
def test_a_message_written_otherwise_is_parsed_at_once(message: str) -> None:
    event = read_topic(message)
    assert event == TopicMessage(7, 1, 0, {"data": "x"})
    decoder = Recording(String)
    assert event.decode(decoder) == String(data="x")
    assert decoder.calls == ["from_data"]


@pytest.mark.parametrize(
    ("message", "error"),
    [
        (
            '{"jsonrpc":"2.0","method":"$/message","params":{"subscription":7,"seq":1,'
            '"dropped":0,"message":{"data":"x"},"seq":2}}',
            "Invalid $/message: 'subscription', 'seq' or 'dropped' given twice",
        ),
        (
            '{"jsonrpc":"2.0","method":"$/message","params":{"subscription":7,"seq":1,'
            '"dropped":0,"message":{"data":"x"},"subscription":8}}',
            "Invalid $/message: 'subscription', 'seq' or 'dropped' given twice",
        ),
        (
            '{"jsonrpc":"2.0","method":"$/message","params":{"subscription":7,"seq":1,'
            '"dropped":0,"message":{"data":"x"}},"method":"$/other","params":{}}',
            "Invalid $/message: 'method' given twice",
        ),
        (
            '{"jsonrpc":"2.0","method":"$/message","params":{"subscription":7,"seq":1,'
            '"dropped":0,"message":{"data":"x"},"seq":"1"}}',
            "$/message needs integers 'seq' and 'dropped', and 'message'",
        ),
        (
            '{"jsonrpc":"2.0","method":"$/message","params":{"subscription":7,"seq":1,'
            '"dropped":0,"message":{"data":"x"} and more}}',
            "Parse error: ",
        ),
    ],
)
def test_a_message_that_is_not_the_one_its_opening_says_is_refused(
    message: str, error: str
) -> None:
    # Its message ({"data": "x"}) would fit, but the one pass never hides what follows it.
    event = recognised(message)
    for decode in (event.parse, lambda: event.decode(ModelDecoder(String))):
        with pytest.raises(ProtocolViolation) as caught:
            decode()
        assert caught.value.error.message.startswith(error)
        assert type(caught.value.error) is (ParseError if "Parse" in error else InvalidRequest)


def test_a_message_that_does_not_fit_is_refused_as_the_parsed_one_is() -> None:
    decoder = Recording(String)
    with pytest.raises(ValidationError) as recognised_:
        recognised(published('{"data":5}')).decode(decoder)
    assert decoder.calls == ["from_json", "from_data"]
    with pytest.raises(ValidationError) as parsed_:
        TopicMessage(7, 1, 0, {"data": 5}).decode(decoder)
    assert errors_of(recognised_.value) == errors_of(parsed_.value) == [(("data",), "string_type")]
    assert str(recognised_.value) == str(parsed_.value)


@pytest.mark.parametrize("field", ["subscription", "seq", "dropped"])
def test_a_message_whose_opening_has_a_number_with_a_leading_zero_is_not_json(
    field: str,
) -> None:
    # 07 is no JSON number: such an opening is not taken at its word, and the whole text,
    # read in full, is refused as the parse error it is.
    numbers = {"subscription": "7", "seq": "1", "dropped": "0"}
    numbers[field] = "0" + numbers[field]
    params = ",".join(f'"{name}":{number}' for name, number in numbers.items())
    opening = '{"jsonrpc":"2.0","method":"$/message","params":{'
    text = opening + params + ',"message":{"data":"x"}}}'
    with pytest.raises(ProtocolViolation) as caught:
        ClientSession[object]().receive(text)
    assert type(caught.value.error) is ParseError


def test_a_method_that_only_begins_as_message_does_is_not_a_message() -> None:
    session = ClientSession[object]()
    text = '{"jsonrpc":"2.0","method":"$/messages","params":{"subscription":7,"seq":1}}'
    assert session.receive(text) == [Notice("$/messages", {"subscription": 7, "seq": 1})]


# --- the one pass and the parsed reply agree on every type -----------------------------------

loader = conformance.loader  # the corpus, as the package test_msgs, in a temporary folder

BUNDLED = InterfaceLoader([bundled_interfaces()])
KINDS = conformance.PART_NAMES  # "msg" -> [""], "srv" -> ["_Request", "_Response"], ...
PARTS = [
    *(("corpus", name, index) for name, index in conformance.PARTS),
    *(
        ("bundled", name, index)
        for name in BUNDLED.types()
        for index in range(len(KINDS[name.split("/")[1]]))
    ),
]
PART_IDS = [name + KINDS[name.split("/")[1]][index] for _, name, index in PARTS]

Outcome = Message | Errors  # an instance, or where and why validation failed

# An integer literal a double cannot hold: it rounds to infinity.
BEYOND_DOUBLE = "1" + "0" * 309


def outcome(decode: Callable[[], Message]) -> Outcome:
    try:
        return decode()
    except ValidationError as exc:
        return errors_of(exc)


def one_pass(decoder: ModelDecoder[Message], text: str) -> Outcome:
    """What validating the JSON ``text`` straight into the type makes of it."""
    return outcome(lambda: decoder.from_json(text))


def parsed(decoder: ModelDecoder[Message], text: str) -> Outcome:
    """What validating ``text`` parsed first makes of it: a reply read by :func:`parse_replies`."""
    return outcome(lambda: Response(1, decode_json(text)).decode(decoder))


def read(decoder: ModelDecoder[Message], text: str) -> Outcome:
    """What the client makes of ``text`` as the result of a reply a srvwire server wrote."""
    reply = raw(Response(1, RawJSON(text)).serialize().decode())
    return outcome(lambda: reply.decode(decoder))


def read_message(decoder: ModelDecoder[Message], text: str) -> Outcome:
    """What the client makes of ``text`` as a topic's message, published by a srvwire server."""
    event = recognised(published(text))
    return outcome(lambda: event.decode(decoder))


def same_outcome(a: Outcome, b: Outcome) -> bool:
    if isinstance(a, list) or isinstance(b, list):
        return a == b
    return conformance.same(a, b)


def part(
    corpus: InterfaceLoader, source: str, name: str, index: int
) -> tuple[InterfaceLoader, type[Message]]:
    """The loader a part comes from (the corpus or the bundled types), and the part's class."""
    interfaces = corpus if source == "corpus" else BUNDLED
    return interfaces, conformance.class_parts(interfaces, name)[index]


@pytest.mark.parametrize(("source", "name", "index"), PARTS, ids=PART_IDS)
def test_random_valid_instances_decode_alike_in_one_pass_and_parsed(
    loader: InterfaceLoader, source: str, name: str, index: int
) -> None:
    interfaces, cls = part(loader, source, name, index)
    decoder = ModelDecoder(cls)

    @settings(max_examples=30, deadline=None)
    @given(conformance.payloads(interfaces, cls.spec), st.booleans())
    def decode(payload: dict[str, Any], as_written_by_json: bool) -> None:
        instance = cls.model_validate(payload)
        # As a srvwire server writes it, or as Python's json module does (NaN and Infinity
        # as tokens, and strings escaped to ASCII).
        text = json.dumps(payload) if as_written_by_json else instance.model_dump_json()
        expected = parsed(decoder, text)
        assert isinstance(expected, cls)
        assert conformance.same(expected, instance)
        assert same_outcome(one_pass(decoder, text), expected)
        recording = Recording(cls)
        assert same_outcome(read(recording, text), expected)
        assert recording.calls == ["from_json"]  # in one pass, never parsed
        recording = Recording(cls)
        assert same_outcome(read_message(recording, text), expected)
        assert recording.calls == ["from_json"]

    decode()


# --- documents that are wrong ----------------------------------------------------------------

HOSTILE = [
    # wrong types
    "null",
    "true",
    "false",
    '"x"',
    '""',
    "{}",
    "[]",
    '["x"]',
    "[null]",
    "[true]",
    "[{}]",
    "[[]]",
    # numbers of every kind where others are expected
    "0",
    "-1",
    "1.0",
    "1.5",
    "-0.0",
    "[1.5]",
    "[0, 255]",
    "[256]",
    "[-1]",
    "[0, 1, 2, 3]",
    "[" + ", ".join(["0"] * 40) + "]",
    # out of range, and the 64-bit extremes
    "128",
    "-129",
    "256",
    "65536",
    str(2**31),
    str(2**32),
    str(2**63 - 1),
    str(2**63),
    str(-(2**63)),
    str(-(2**63) - 1),
    str(2**64 - 1),
    str(2**64),
    str(-(2**64)),
    str(10**30),
    str(2**1023),
    "1e308",
    "3.4028234663852886e38",
    "3.402823466385289e38",
    "1e39",
    "1e400",
    "-1e400",
    "1e-400",
    # the non-finite tokens
    "NaN",
    "Infinity",
    "-Infinity",
    "[NaN]",
    "[Infinity, -Infinity]",
    # base64 where a byte array is expected, right and wrong
    '"AAE="',
    '"AAEC/w=="',
    '"AA"',
    '"not base64!"',
    # strings at and beyond bounds, and not ASCII
    '"' + "x" * 300 + '"',
    '"ハロー"',
    '"\\u00e9\\ud83d\\ude00"',
]
# Integers too large for a double: see test_an_integer_beyond_a_double_reads_as_infinity.
KNOWN = [BEYOND_DOUBLE, "-" + BEYOND_DOUBLE, f"[{BEYOND_DOUBLE}]"]
# Fewer values inside nested messages, where the paths multiply (MultiNested nests 9 x 32 fields).
NESTED_HOSTILE = ["null", '"x"', "[]", "{}", "-1", "1.5", "[1.5]", str(2**64), "NaN", '"AAE="']


def field_documents(
    interfaces: InterfaceLoader, spec: MessageSpec, hostile: list[str], depth: int
) -> list[str]:
    """One document per field and hostile value, into nested messages ``depth`` levels deep.

    Every field is optional, so ``{"field": value}`` tries ``value`` on that field alone.
    """
    documents = []
    for field in spec.fields:
        key = json.dumps(field.name)
        values = [*hostile, *KNOWN]
        if not field.type.is_primitive and depth > 0:
            nested = interfaces.message_spec(field.type.qualified_name)
            inner = field_documents(interfaces, nested, NESTED_HOSTILE, depth - 1)
            if field.type.array is ArrayKind.NONE:
                values += inner
            else:
                values += [f"[{document}]" for document in inner]
        documents += [f"{{{key}: {value}}}" for value in values]
    return documents


def documents(interfaces: InterfaceLoader, spec: MessageSpec) -> list[str]:
    """Wrong documents for ``spec``: hostile values in every field, and wrong as a whole."""
    whole = [*HOSTILE, '{"not_a_field": 1}', '{"not_a_field": NaN}']
    if spec.fields:
        first = json.dumps(spec.fields[0].name)
        whole += [f'{{{first}: "x", {first}: "y"}}', f'{{{first}: "x", "not_a_field": 1}}']
    return whole + field_documents(interfaces, spec, HOSTILE, depth=1)


@pytest.mark.parametrize(("source", "name", "index"), PARTS, ids=PART_IDS)
def test_wrong_documents_are_refused_alike_in_one_pass_and_parsed(
    loader: InterfaceLoader, source: str, name: str, index: int
) -> None:
    interfaces, cls = part(loader, source, name, index)
    decoder = ModelDecoder(cls)
    refused = 0
    for document in documents(interfaces, cls.spec):
        expected = parsed(decoder, document)
        refused += isinstance(expected, list)
        assert same_outcome(one_pass(decoder, document), expected), document
        # A raw reply decodes what validates in one pass, and parses the rest in full.
        recording = Recording(cls)
        assert same_outcome(read(recording, document), expected), document
        ways = ["from_json", "from_data"] if isinstance(expected, list) else ["from_json"]
        assert recording.calls == ways, document
        # So does a topic's message.
        recording = Recording(cls)
        assert same_outcome(read_message(recording, document), expected), document
        assert recording.calls == ways, document
    assert refused > 0


def test_an_integer_beyond_a_double_reads_as_infinity() -> None:
    # pydantic-core turns a JSON integer too large for an int64 into a float (pydantic-core
    # PR 1685) without checking the range: infinity, as a float literal such as 1e400. Parsing
    # makes it a Python int, which a float field refuses in Python mode as soon as float() of
    # it overflows; validate_wire then reads the data again as JSON, so both ways agree.
    response = BUNDLED.load_service("advanced_communication_tutorials/srv/RobotStateQuery").Response
    decoder = ModelDecoder(response)
    for literal, infinity in ((BEYOND_DOUBLE, math.inf), ("-" + BEYOND_DOUBLE, -math.inf)):
        document = f'{{"values": [1.5, {literal}, {literal}]}}'
        expected = response(values=[1.5, infinity, infinity])
        assert one_pass(decoder, document) == parsed(decoder, document) == expected
        assert read(decoder, document) == expected
        # What else is wrong is still said, as it is without the integer.
        wrong = f'{{"values": [{literal}, "x"]}}'
        assert one_pass(decoder, wrong) == parsed(decoder, wrong) == [(("values", 1), "float_type")]
        assert one_pass(decoder, '{"values": [1e400]}') == parsed(decoder, '{"values": [1e400]}')
    # One less than the first integer that rounds to infinity still decodes alike.
    largest = 2**1024 - 2**970 - 1
    document = f'{{"values": [{largest}]}}'
    assert one_pass(decoder, document) == parsed(decoder, document)
    assert parsed(decoder, document) == response(values=[float(largest)])
