"""Validating a reply's JSON text in one pass agrees with decoding it first and validating that.

The client decodes a typed reply straight from its text, where it used to decode the text into
Python data (``from_json``) and validate that (``model_validate``). For every part of every type
srvwire bundles and of ROS 2's test corpus, both ways must give equal instances for random valid
payloads, and refuse the same wrong documents with errors at the same places, of the same types.

They disagree in one place, pinned below: pydantic-core reads an integer literal beyond the range
of a double as infinity in a float field when it validates JSON text (as it reads ``1e400``),
and refuses the Python int that ``from_json`` makes of it. The client reads such a reply as
infinity; everything else it decodes must be exactly what the two-pass way gives.
"""

from __future__ import annotations

import json
import math
from typing import Any

import pytest
from hypothesis import given, settings, strategies as st
from pydantic import ValidationError
from pydantic_core import from_json

import test_conformance as conformance
from srvwire.client import Client
from srvwire.idl import ArrayKind, MessageSpec
from srvwire.loader import InterfaceLoader, bundled_interfaces
from srvwire.models import Message

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

Errors = list[tuple[tuple[int | str, ...], str]]
Outcome = Message | Errors  # an instance, or where and why validation failed

# An integer literal a double cannot hold: it rounds to infinity.
BEYOND_DOUBLE = "1" + "0" * 309


def errors_of(exc: ValidationError) -> Errors:
    return [(error["loc"], error["type"]) for error in exc.errors()]


def one_pass(cls: type[Message], text: str) -> Outcome:
    """What ``model_validate_json`` makes of ``text``: the client's way since it got raw replies."""
    try:
        return cls.model_validate_json(text)
    except ValidationError as exc:
        return errors_of(exc)


def two_pass(cls: type[Message], text: str) -> Outcome:
    """What ``model_validate(from_json(...))`` makes of ``text``: the client's way before."""
    try:
        data = from_json(text, allow_inf_nan=True)
    except ValueError:
        return [((), "json_invalid")]
    try:
        return cls.model_validate(data)
    except ValidationError as exc:
        return errors_of(exc)


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
def test_random_valid_instances_decode_alike_in_one_pass_and_in_two(
    loader: InterfaceLoader, source: str, name: str, index: int
) -> None:
    interfaces, cls = part(loader, source, name, index)
    client = Client()

    @settings(max_examples=30, deadline=None)
    @given(conformance.payloads(interfaces, cls.spec), st.booleans())
    def decode(payload: dict[str, Any], as_written_by_json: bool) -> None:
        instance = cls.model_validate(payload)
        # As a srvwire server writes it, or as Python's json module does (NaN and Infinity
        # as tokens, and strings escaped to ASCII).
        text = json.dumps(payload) if as_written_by_json else instance.model_dump_json()
        expected = two_pass(cls, text)
        assert isinstance(expected, cls)
        assert conformance.same(expected, instance)
        assert same_outcome(one_pass(cls, text), expected)
        decoded = client._decode_in_one_pass(cls, text)
        assert decoded is not None and conformance.same(decoded, expected)

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
# The disagreement pinned by test_json_text_reads_an_integer_beyond_a_double_as_infinity.
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


def is_known(document: str) -> bool:
    return any(known in document for known in KNOWN)


@pytest.mark.parametrize(("source", "name", "index"), PARTS, ids=PART_IDS)
def test_wrong_documents_are_refused_alike_in_one_pass_and_in_two(
    loader: InterfaceLoader, source: str, name: str, index: int
) -> None:
    interfaces, cls = part(loader, source, name, index)
    client = Client()
    refused = 0
    for document in documents(interfaces, cls.spec):
        expected = two_pass(cls, document)
        refused += isinstance(expected, list)
        if is_known(document):
            continue  # the one difference, pinned below
        assert same_outcome(one_pass(cls, document), expected), document
        # The client decodes what validates in one pass, and parses the rest in full.
        decoded = client._decode_in_one_pass(cls, document)
        assert (decoded is None) == isinstance(expected, list), document
        if decoded is not None:
            assert same_outcome(decoded, expected), document
    assert refused > 0


def test_json_text_reads_an_integer_beyond_a_double_as_infinity() -> None:
    # pydantic-core turns a JSON integer too large for an int64 into a float (pydantic-core
    # PR 1685) without checking the range; from_json makes it a Python int, which a float field
    # refuses as soon as float() of it overflows.
    response = BUNDLED.load_service("advanced_communication_tutorials/srv/RobotStateQuery").Response
    for literal, infinity in ((BEYOND_DOUBLE, math.inf), ("-" + BEYOND_DOUBLE, -math.inf)):
        document = f'{{"values": [1.5, {literal}]}}'
        assert one_pass(response, document) == response(values=[1.5, infinity])
        assert two_pass(response, document) == [(("values", 1), "float_type")]
        # The client reads it as infinity, as it reads a float literal such as 1e400.
        assert Client()._decode_in_one_pass(response, document) == response(values=[1.5, infinity])
        assert one_pass(response, '{"values": [1e400]}') == two_pass(
            response, '{"values": [1e400]}'
        )
    # One less than the first integer that rounds to infinity still decodes alike.
    largest = 2**1024 - 2**970 - 1
    document = f'{{"values": [{largest}]}}'
    assert one_pass(response, document) == two_pass(response, document)
    assert two_pass(response, document) == response(values=[float(largest)])
