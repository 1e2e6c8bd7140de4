"""The edge policy without a socket: each check on opening requests made by hand."""

from __future__ import annotations

import logging
import ssl
from typing import Any

import pytest

from conftest import Subtract
from srvwire.auth import Identity, TokenAuth, bearer_subprotocol, certificate_subject
from srvwire.dispatch import ServiceRegistry
from srvwire.errors import RegistrationError
from srvwire.handshake import EdgePolicy, describe_reach, is_loopback
from srvwire.transports.base import Admitted, Answered, Handshake, Options
from srvwire.transports.memory import MemoryTransport

UPGRADE = (("Upgrade", "websocket"),)


def request(*headers: tuple[str, str], path: str = "/", **more: Any) -> Handshake:
    return Handshake(path=path, headers=[*UPGRADE, *headers], peer=("10.0.0.9", 5000), **more)


@pytest.mark.parametrize(
    ("listen", "headers", "admitted"),
    [
        # A server on another address: the name the client used is the server's.
        ("0.0.0.0", [("Host", "10.0.0.5:8765"), ("Origin", "http://10.0.0.5:8765")], True),
        ("0.0.0.0", [("Host", "10.0.0.5:8765"), ("Origin", "http://10.0.0.6:8765")], False),
        ("0.0.0.0", [("Host", "10.0.0.5:8765"), ("Origin", "http://10.0.0.5:9999")], False),
        # Behind a proxy: a Host without a port is on the origin's scheme's default port.
        ("0.0.0.0", [("Host", "robot.example.com"), ("Origin", "https://robot.example.com")], True),
        (
            "0.0.0.0",
            [("Host", "robot.example.com"), ("Origin", "http://robot.example.com:81")],
            False,
        ),
        # Loopback: only its own names, IPv6 included, and never a foreign Host.
        ("::1", [("Host", "[::1]:8765"), ("Origin", "http://[::1]:8765")], True),
        ("127.0.0.1", [("Host", "localhost:8765"), ("Origin", "http://localhost:8765")], True),
        (
            "127.0.0.1",
            [("Host", "evil.example:8765"), ("Origin", "http://evil.example:8765")],
            False,
        ),
        ("127.0.0.1", [], False),  # no Host at all
        (
            "127.0.0.1",
            [("Host", "localhost:8765"), ("Origin", "http://localhost:8765/page")],
            False,
        ),
        # No Origin: a program, not a browser.
        ("0.0.0.0", [("Host", "anything")], True),
    ],
)
async def test_host_and_origin(listen: str, headers: list[tuple[str, str]], admitted: bool) -> None:
    answer = await EdgePolicy(listen).admit(request(*headers))
    assert isinstance(answer, Admitted) is admitted, answer


async def test_an_origin_with_a_path_is_named_in_the_refusal() -> None:
    answer = await EdgePolicy("127.0.0.1").admit(
        request(("Host", "localhost:1"), ("Origin", "http://localhost:1/page"))
    )
    assert answer == Answered(
        403, "Origin 'http://localhost:1/page' is not an origin (scheme://host[:port])\n"
    )


async def test_the_subprotocol_selected_is_srvwire_v1_never_the_token() -> None:
    policy = EdgePolicy("127.0.0.1", auth=TokenAuth({"t": "me"}))
    offered = ["srvwire.v1", bearer_subprotocol("t")]
    answer = await policy.admit(request(("Host", "localhost"), subprotocols=offered))
    assert answer == Admitted(Identity("me"), "srvwire.v1")
    only_token = await policy.admit(
        request(("Host", "localhost"), subprotocols=[bearer_subprotocol("t")])
    )
    assert only_token == Admitted(Identity("me"), None)


async def test_an_authenticator_that_fails_is_a_500_and_logged(
    caplog: pytest.LogCaptureFixture,
) -> None:
    async def broken(handshake: Handshake) -> Identity:
        raise RuntimeError("database down")

    answer = await EdgePolicy("127.0.0.1", auth=broken).admit(
        request(("Host", "localhost"), ("Authorization", "Bearer secret-value"))
    )
    assert answer == Answered(500, "the server failed to check the credentials\n")
    assert "database down" in caplog.text and "secret-value" not in caplog.text
    assert caplog.records[0].levelno == logging.ERROR


async def test_an_authenticator_that_returns_something_else_is_a_500() -> None:
    async def wrong(handshake: Handshake) -> Any:
        return 42

    answer = await EdgePolicy("127.0.0.1", auth=wrong).admit(request(("Host", "localhost")))
    assert isinstance(answer, Answered) and answer.status == 500


def test_identity_scopes_are_a_set_of_names() -> None:
    assert Identity("a", ["x", "x", "y"]).scopes == frozenset({"x", "y"})
    with pytest.raises(TypeError) as exc:
        Identity("a", "robot:write")
    assert str(exc.value) == "scopes must be a collection of names, not the string 'robot:write'"


def test_certificate_subject() -> None:
    certificate = {"subject": ((("organizationName", "Lab"),), (("commonName", "op"),))}
    assert certificate_subject(certificate) == "O=Lab,CN=op"
    assert certificate_subject({}) is None


@pytest.mark.parametrize(
    ("host", "loopback"),
    [
        ("127.0.0.1", True),
        ("127.1.2.3", True),
        ("::1", True),
        ("[::1]", True),
        ("localhost", True),
        ("robot.localhost", True),
        ("0.0.0.0", False),
        ("::", False),
        ("10.0.0.5", False),
        ("robot.example.com", False),
        ("", False),
    ],
)
def test_is_loopback(host: str, loopback: bool) -> None:
    assert is_loopback(host) is loopback


def test_describe_reach() -> None:
    assert describe_reach("0.0.0.0", authenticated=True, tls=True) == (
        "any host that can route to 0.0.0.0 can connect; callers must authenticate; over TLS"
    )


async def test_refusals_are_logged_at_most_once_per_interval(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO)
    now = [100.0]
    policy = EdgePolicy("127.0.0.1", clock=lambda: now[0])
    hostile = request(("Host", "localhost"), ("Origin", "https://evil.example"))
    for _ in range(5):
        await policy.admit(hostile)
    now[0] += 1.0
    await policy.admit(hostile)
    said = [record.getMessage() for record in caplog.records]
    reason = (
        "Origin https://evil.example is not allowed: a page from another site may not "
        "connect; list it in the origins (srvwire serve --origin ORIGIN) to allow it"
    )
    assert said == [
        f"refused a connection from ('10.0.0.9', 5000): HTTP 403, {reason}",
        f"refused a connection from ('10.0.0.9', 5000): HTTP 403, {reason} "
        "(4 more refused since the last line)",
    ]


def test_tokenauth_takes_tokens_or_a_function() -> None:
    with pytest.raises(ValueError) as empty:
        TokenAuth({"": "nobody"})
    assert str(empty.value) == "every token must be a non-empty string"
    with pytest.raises(TypeError) as other:
        TokenAuth(42)  # type: ignore[arg-type]
    assert str(other.value) == "TokenAuth takes a mapping of tokens or a function, not int"
    assert repr(TokenAuth(lambda token: None)) == "<TokenAuth by a function>"
    assert repr(TokenAuth({"a": "me"})) == "<TokenAuth with 1 token>"


def test_scopes_must_be_a_collection_not_a_string() -> None:
    with pytest.raises(RegistrationError) as exc:
        ServiceRegistry().add("/arm", Subtract, lambda request: None, "robot:write")
    assert str(exc.value) == (
        "the scopes of /arm must be a collection of names, such as {'robot:write'}, not the "
        "string 'robot:write'"
    )


async def test_the_memory_transport_has_no_tls() -> None:
    async def handler(connection: Any) -> None:
        pass

    with pytest.raises(ValueError) as exc:
        await MemoryTransport().listen(
            handler, "localhost", 0, Options(), ssl=ssl.create_default_context()
        )
    assert str(exc.value) == "the memory transport has no TLS: pass ssl=None"
