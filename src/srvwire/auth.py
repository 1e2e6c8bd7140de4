"""Who a connection is: identities, the credentials a client sends, and the bearer-token check.

An *authenticator* is an async callable that receives the opening request
(a :class:`~srvwire.transports.base.Handshake`) and returns an :class:`Identity` (or a plain
name), or raises :class:`~srvwire.errors.Unauthenticated` with the reason to refuse it; the
server answers that refusal with HTTP 401 before the connection opens. :class:`TokenAuth` is
the one srvwire ships.

Rules:

* **Credentials travel in the opening request**, in this order of preference: the header
  ``Authorization: Bearer <token>``; the subprotocol ``srvwire.bearer.<base64url token>``
  (a browser's WebSocket cannot set headers; it offers ``srvwire.v1`` beside it, which is the
  one the server selects, so the token is never echoed); a query parameter, only when the
  authenticator is told its name.
* **A token is a secret.** No ``repr`` here shows one, and :class:`TokenAuth` keeps only their
  SHA-256 digests, so a token does not sit in memory as text longer than the check.
* **Scopes say what an identity may call.** A service registered with ``scopes=`` is callable
  by a connection whose identity holds every one of them; a connection without an identity
  holds none.
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import inspect
import urllib.parse
from collections.abc import Awaitable, Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, TypeAlias

from srvwire.errors import Unauthenticated
from srvwire.transports.base import Handshake

__all__ = [
    "BEARER_PREFIX",
    "SUBPROTOCOL",
    "Authenticator",
    "Identity",
    "TokenAuth",
    "bearer_subprotocol",
    "bearer_token",
    "certificate_subject",
]

SUBPROTOCOL = "srvwire.v1"
"""The subprotocol a server selects when a client offers it (a browser sending a token must)."""

BEARER_PREFIX = "srvwire.bearer."
"""A subprotocol that starts with this carries a token: ``srvwire.bearer.<base64url token>``."""

NO_CREDENTIALS = (
    "no credentials: send the header 'Authorization: Bearer <token>', or offer the "
    "subprotocols 'srvwire.v1' and 'srvwire.bearer.<base64url of the token>'"
)


@dataclass(frozen=True, slots=True)
class Identity:
    """Who a connection is: a ``name``, the ``scopes`` it holds, and when its credentials
    ``expires`` (seconds since the epoch, as :func:`time.time`; None: never).

    Past ``expires`` the connection stays open, but every call is answered
    ``UNAUTHENTICATED``: the client reconnects with fresh credentials.
    """

    name: str
    scopes: frozenset[str] = field(default=frozenset())
    expires: float | None = None

    def __init__(self, name: str, scopes: Iterable[str] = (), expires: float | None = None) -> None:
        if isinstance(scopes, str):
            raise TypeError(f"scopes must be a collection of names, not the string {scopes!r}")
        object.__setattr__(self, "name", name)
        object.__setattr__(self, "scopes", frozenset(scopes))
        object.__setattr__(self, "expires", expires)


Authenticator: TypeAlias = Callable[[Handshake], Awaitable["Identity | str"]]
"""Checks an opening request: returns who it is, or raises ``Unauthenticated`` saying why not."""


def as_identity(found: Identity | str) -> Identity:
    """An authenticator's answer as an :class:`Identity` (a plain name holds no scopes)."""
    if isinstance(found, Identity):
        return found
    if isinstance(found, str):
        return Identity(found)
    raise TypeError(
        f"an authenticator returns an Identity or a name, not {type(found).__name__}; "
        "raise srvwire.Unauthenticated to refuse"
    )


def bearer_subprotocol(token: str) -> str:
    """The subprotocol that carries ``token``: ``srvwire.bearer.`` and its base64url text.

    A browser offers it beside ``srvwire.v1``:
    ``new WebSocket(url, ["srvwire.v1", "srvwire.bearer." + base64url(token)])``.
    """
    encoded = base64.urlsafe_b64encode(token.encode()).decode("ascii").rstrip("=")
    return BEARER_PREFIX + encoded


def bearer_token(handshake: Handshake, query_parameter: str | None = None) -> str | None:
    """The token ``handshake`` carries, or None; raise ``Unauthenticated`` for one that is
    malformed (see the module's rules for where it is looked for)."""
    header = handshake.header("Authorization")
    if header is not None:
        scheme, _, token = header.strip().partition(" ")
        if scheme.lower() != "bearer" or not token.strip():
            raise Unauthenticated("the Authorization header is not 'Bearer <token>'")
        return token.strip()
    for offered in handshake.subprotocols:
        if offered.startswith(BEARER_PREFIX):
            encoded = offered[len(BEARER_PREFIX) :]
            try:
                padded = encoded + "=" * (-len(encoded) % 4)
                return base64.b64decode(padded, altchars=b"-_", validate=True).decode()
            except (binascii.Error, ValueError):
                raise Unauthenticated(
                    f"the {BEARER_PREFIX}* subprotocol does not hold base64url UTF-8 text"
                ) from None
    if query_parameter is not None:
        query = urllib.parse.urlsplit(handshake.path).query
        values = urllib.parse.parse_qs(query).get(query_parameter)
        if values:
            return values[0]
    return None


def certificate_subject(certificate: Mapping[str, Any]) -> str | None:
    """The subject of a peer certificate as ``ssl.getpeercert()`` gives it, written
    ``CN=name,O=org``; None when it has none."""
    short = {"commonName": "CN", "organizationName": "O", "organizationalUnitName": "OU"}
    text = ",".join(
        f"{short.get(key, key)}={value}"
        for rdn in certificate.get("subject", ())
        for key, value in rdn
    )
    return text or None


def _digest(token: str) -> bytes:
    return hashlib.sha256(token.encode()).digest()


TokenLookup: TypeAlias = Callable[[str], "Identity | str | Awaitable[Identity | str | None] | None"]


class TokenAuth:
    """Admit a connection whose bearer token is known: ``TokenAuth({token: identity})``.

    ``tokens`` maps each token to the :class:`Identity` (or plain name) it stands for, or is a
    function from a token to its identity (None: unknown), which may be async. With
    ``query_parameter`` the token may also come in the URL's query string under that name
    (a URL is logged by proxies and kept in histories: prefer the header or subprotocol).
    """

    def __init__(
        self,
        tokens: Mapping[str, Identity | str] | TokenLookup,
        *,
        query_parameter: str | None = None,
    ) -> None:
        self._lookup: TokenLookup | None = None
        self._digests: dict[bytes, Identity] = {}
        if isinstance(tokens, Mapping):
            for token, identity in tokens.items():
                if not isinstance(token, str) or not token:
                    raise ValueError("every token must be a non-empty string")
                self._digests[_digest(token)] = as_identity(identity)
        elif callable(tokens):
            self._lookup = tokens
        else:
            raise TypeError(
                f"TokenAuth takes a mapping of tokens or a function, not {type(tokens).__name__}"
            )
        self.query_parameter = query_parameter

    def __repr__(self) -> str:
        if self._lookup is not None:
            return "<TokenAuth by a function>"
        count = len(self._digests)
        return f"<TokenAuth with {count} {'token' if count == 1 else 'tokens'}>"

    async def __call__(self, handshake: Handshake) -> Identity:
        token = bearer_token(handshake, self.query_parameter)
        if token is None:
            raise Unauthenticated(NO_CREDENTIALS)
        if self._lookup is None:
            identity: Identity | str | None = self._digests.get(_digest(token))
        else:
            found = self._lookup(token)
            identity = await found if inspect.isawaitable(found) else found
        if identity is None:
            raise Unauthenticated("the token is not valid")
        return as_identity(identity)
