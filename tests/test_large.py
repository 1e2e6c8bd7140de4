"""Large float arrays end to end: written whole in one pass, read back exactly, limits kept.

A reply is written by :func:`srvwire.models.reply_writer`, the envelope and the result in one
pass; these check that what it writes is byte for byte what the two-step writing gave, in every
``inf_nan`` mode and for every kind of id, and that a 100 000-value array with non-finite
values crosses real connections both ways in every mode.
"""

from __future__ import annotations

import math
import warnings
from typing import Any

import pytest
from pydantic_core import PydanticSerializationError

from srvwire.client import connect
from srvwire.errors import ConnectionLost
from srvwire.idl import TypeSpec
from srvwire.models import (
    INF_NAN_MODES,
    InfNan,
    Message,
    build_message,
    build_service,
    json_writer,
    reply_writer,
)
from srvwire.parser import parse_message, parse_service
from srvwire.protocol import write_response
from srvwire.server import Server, serve
from srvwire.transports.base import Transport
from support import scaled

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
