"""Large float arrays end to end: written whole in one pass, read back exactly, limits kept.

A reply is written by :func:`srvwire.models.reply_writer`, the envelope and the result in one
pass; these check that what it writes is byte for byte what the two-step writing gave, in every
``inf_nan`` mode and for every kind of id, and that a 100 000-value array with non-finite
values crosses real connections both ways in every mode.
"""

from __future__ import annotations

import json
import math
import warnings
from typing import Any

import pytest
from pydantic import ValidationError
from pydantic_core import PydanticSerializationError

from srvwire.client import connect
from srvwire.errors import ConnectionLost
from srvwire.idl import TypeSpec
from srvwire.loader import InterfaceLoader
from srvwire.models import (
    INF_NAN_MODES,
    InfNan,
    Message,
    ModelDecoder,
    build_message,
    build_service,
    json_writer,
    reply_writer,
)
from srvwire.parser import parse_message, parse_service
from srvwire.protocol import (
    WHOLE_REPLY_SIZE,
    ProtocolViolation,
    RawReply,
    Response,
    peek_reply,
    write_response,
)
from srvwire.server import Server, serve
from srvwire.transports.base import Transport
from support import scaled
from test_bundled_interfaces import ON_DISK, SEARCH_PATH, load, parts_of, sample

SAMPLES_SRV = """\
# Send samples, get them back scaled, beside a nested reading.
float64[] samples
float64 scale
---
float64[] values
float32[] narrow
Reading first
Reading[] rest
"""

READING_MSG = """\
float64 value
string label
"""

COUNT = 100_000
BIG = 16 * 2**20  # both ends' max_message_size: the replies here are about 2 MB

Reading = build_message(parse_message(READING_MSG, "srvwire_tests", "Reading"))


def _resolve(type_: TypeSpec) -> type[Message]:
    assert type_.name == "Reading"
    return Reading


Samples: Any = build_service(parse_service(SAMPLES_SRV, "srvwire_tests", "Samples"), _resolve)

IDS: list[Any] = [0, 1, -7, 2**70, "a", 'q"\\é\U0001f600', None, 2.5]


def samples(count: int) -> list[float]:
    """``count`` full-precision floats with every non-finite value at the ends and the middle."""
    values = [i / 7.0 + 0.1 for i in range(count)]
    for at, value in ((0, math.nan), (1, math.inf), (count // 2, -math.inf), (count - 1, math.nan)):
        values[at] = value
    return values


def same_floats(got: list[float], expected: list[float], mode: InfNan) -> bool:
    """Whether ``got`` is ``expected`` read back in ``mode`` (``null`` makes every one nan)."""
    if len(got) != len(expected):
        return False
    for a, b in zip(got, expected, strict=True):
        if math.isfinite(b):
            if a != b:
                return False
        elif mode == "null" or math.isnan(b):
            if not math.isnan(a):
                return False
        elif a != b:
            return False
    return True


def response(count: int) -> Any:
    values = samples(count)
    return Samples.Response(
        values=values,
        narrow=[math.inf, -1.5, math.nan],
        first={"value": math.inf, "label": "é"},
        rest=[{"value": v, "label": str(i)} for i, v in enumerate(values[:3])],
    )


# --- the writer -----------------------------------------------------------------------------------


@pytest.mark.parametrize("mode", [None, *INF_NAN_MODES])
def test_a_reply_written_in_one_pass_is_the_two_step_reply_byte_for_byte(
    mode: InfNan | None,
) -> None:
    model = Samples.Response
    for value in (model(), response(1_000)):
        for strict in (False, True):
            whole = reply_writer(model, mode, strict=strict)
            result = json_writer(model, mode, strict=strict)
            for id in IDS:
                assert whole(id, value) == write_response(id, result(value)), (id, strict)


@pytest.mark.parametrize("name", ON_DISK)
def test_every_bundled_type_is_written_whole_and_read_whole_as_in_two_steps(name: str) -> None:
    # Byte arrays, nested messages, fixed and bounded arrays, constants: whatever a type holds.
    loader = InterfaceLoader(SEARCH_PATH)
    for part in parts_of(load(name)):
        decoder = ModelDecoder(part)
        for value in (part(), part.model_validate(sample(part, loader))):
            for mode in (None, "null"):
                written = reply_writer(part, mode, strict=True)(9, value)
                assert written == write_response(9, json_writer(part, mode)(value))
            read = peek_reply(written.decode())
            assert read is not None
            assert decoder.from_reply(read.message, 9) == decoder.from_json(read.result) == value


def test_a_reply_written_in_one_pass_reaches_nested_messages_in_the_mode() -> None:
    value = response(4)
    written = reply_writer(Samples.Response, "constants")(3, value).decode()
    assert written.startswith('{"jsonrpc":"2.0","id":3,"result":{"values":[NaN,Infinity,')
    assert '"first":{"value":Infinity,"label":"é"}' in written
    assert '"rest":[{"value":NaN,"label":"0"},{"value":Infinity,"label":"1"}' in written
    assert '"narrow":[Infinity,-1.5,NaN]' in written
    with pytest.raises(ValueError, match="inf_nan must be one of strings, null, constants"):
        reply_writer(Samples.Response, "none")  # type: ignore[arg-type]


def test_a_strict_reply_writer_refuses_a_value_that_does_not_fit_for_any_id() -> None:
    value = Samples.Response(values=[1.0])
    value.values.append("x")
    strict = reply_writer(Samples.Response, strict=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # goes in front of srvwire's filter: put back behind it
        for id in (1, "one"):
            with pytest.raises(PydanticSerializationError, match="Expected `float`"):
                strict(id, value)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        lenient = reply_writer(Samples.Response)(1, value)
    assert b'"values":[1.0,"x"]' in lenient  # not strict: written, with pydantic's warning
    assert [str(w.message).splitlines()[0] for w in caught] == ["Pydantic serializer warnings:"]


# --- the reader ---------------------------------------------------------------------------------


class Counting:
    """A :class:`ModelDecoder` that notes which of its ways each decode took."""

    def __init__(self) -> None:
        self.decoder = ModelDecoder(Samples.Response)
        self.calls: list[str] = []

    def from_json(self, text: str) -> Any:
        self.calls.append("from_json")
        return self.decoder.from_json(text)

    def from_data(self, data: Any) -> Any:
        self.calls.append("from_data")
        return self.decoder.from_data(data)

    def from_reply(self, message: str, id: int) -> Any:
        self.calls.append("from_reply")
        return self.decoder.from_reply(message, id)


def large_reply(id: int = 5, after: str = "") -> RawReply:
    text = reply_writer(Samples.Response)(id, response(COUNT)).decode()
    assert len(text) >= WHOLE_REPLY_SIZE
    recognised = peek_reply(text[:-1] + after + "}")
    assert recognised is not None
    return recognised


def test_a_large_reply_is_validated_whole_and_a_small_one_from_its_result() -> None:
    decoder = Counting()
    got = large_reply().decode(decoder)
    assert same_floats(got.values, samples(COUNT), "strings")
    assert got == large_reply().parse().decode(ModelDecoder(Samples.Response))
    small = peek_reply(reply_writer(Samples.Response)(5, response(10)).decode())
    assert small is not None
    assert same_floats(small.decode(decoder).values, samples(10), "strings")
    assert decoder.calls == ["from_reply", "from_json"]


@pytest.mark.parametrize(
    ("after", "values", "ways"),
    [
        # more members: ignored, as the full parse ignores them (which the envelope leaves to it)
        (',"x":2', COUNT, ["from_reply", "from_data"]),
        (',"id":5', COUNT, ["from_reply"]),  # the same id again
        (',"result":{"values":[1.5]}', 1, ["from_reply"]),  # the last one counts, as parsed
    ],
)
def test_a_large_reply_that_is_not_only_its_envelope_reads_as_the_full_parse_reads_it(
    after: str, values: int, ways: list[str]
) -> None:
    decoder = Counting()
    got = large_reply(after=after).decode(decoder)
    assert len(got.values) == values
    assert got == large_reply(after=after).parse().decode(ModelDecoder(Samples.Response))
    assert decoder.calls == ways


@pytest.mark.parametrize(
    ("after", "error"),
    [
        (',"id":6', "Invalid reply: 'id' given twice (5 and 6)"),
        (',"id":5.0', "Invalid reply: 'id' given twice (5 and 5.0)"),
        (',"method":"$/services","params":{}', "Invalid reply: both 'result' and 'method'"),
        (',"error":{"code":1,"message":"m"}', "Invalid reply: both 'result' and 'error'"),
    ],
)
def test_a_large_reply_that_is_another_message_is_refused_as_the_full_parse_refuses_it(
    after: str, error: str
) -> None:
    with pytest.raises(ProtocolViolation) as caught:
        large_reply(after=after).decode(Counting())
    assert str(caught.value.error.message) == error


def test_a_large_result_that_does_not_fit_has_the_errors_of_the_parsed_one() -> None:
    text = reply_writer(Samples.Response)(5, response(COUNT)).decode()
    bad = text.replace("0.3857142857142857,", '"x",', 1)  # values[2]
    decoder = ModelDecoder(Samples.Response)
    with pytest.raises(ValidationError) as whole:
        decoder.from_reply(bad, 5)
    with pytest.raises(ValidationError) as read:
        raw = peek_reply(bad)
        assert raw is not None
        raw.decode(decoder)
    with pytest.raises(ValidationError) as parsed:
        Response(5, json.loads(bad)["result"]).decode(decoder)
    assert [(e["loc"], e["type"]) for e in read.value.errors()] == [(("values", 2), "float_type")]
    assert [(e["loc"], e["type"]) for e in parsed.value.errors()] == [(("values", 2), "float_type")]
    assert [(e["loc"], e["type"]) for e in whole.value.errors()] == [
        (("result", "values", 2), "float_type")
    ]


# --- over real connections -----------------------------------------------------------------------


@pytest.mark.parametrize("mode", INF_NAN_MODES)
async def test_a_large_array_with_non_finite_values_crosses_both_ways_in_every_mode(
    transport: Transport, mode: InfNan
) -> None:
    sent = samples(COUNT)

    async def scaled_back(request: Any) -> Any:
        assert same_floats(request.samples, sent[: len(request.samples)], mode)
        return Samples.Response(
            values=[v * request.scale for v in request.samples], narrow=[math.nan]
        )

    server = Server(max_message_size=BIG, inf_nan=mode)
    server.add_service("/samples", Samples, scaled_back)
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        async with connect(
            running.url, transport=transport, max_message_size=BIG, inf_nan=mode, timeout=scaled(20)
        ) as client:
            for _ in range(3):  # each reply as large as the last: the same path every time
                got = await client.call("/samples", Samples.Request(samples=sent, scale=2.0))
                assert isinstance(got, Samples.Response)
                assert same_floats(got.values, [v * 2.0 for v in sent], mode)
                assert math.isnan(got.narrow[0])
            untyped = await client.call("/samples", {"samples": sent[:10], "scale": 1.0})
            assert same_floats(untyped.values, sent[:10], mode)


async def test_a_large_reply_past_the_clients_limit_drops_only_that_connection(
    transport: Transport,
) -> None:
    sent = samples(COUNT)
    server = Server(max_message_size=BIG)  # as many values back as the request's scale says
    server.add_service("/samples", Samples, lambda request: {"values": sent[: int(request.scale)]})
    async with serve(server, "127.0.0.1", 0, transport=transport) as running:
        async with connect(
            running.url, transport=transport, max_message_size=2**20, timeout=scaled(20)
        ) as small:
            assert len((await small.call("/samples", {"scale": 1000})).values) == 1000
            with pytest.raises(ConnectionLost) as caught:
                await small.call("/samples", {"scale": COUNT})  # 1.8 MB back
            assert caught.value.data["close_code"] == 1009
        async with connect(
            running.url, transport=transport, max_message_size=BIG, timeout=scaled(20)
        ) as big:
            got = await big.call("/samples", {"scale": COUNT})
            assert same_floats(got.values, sent, "strings")
