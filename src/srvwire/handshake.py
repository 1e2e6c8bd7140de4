"""The server's edge: which opening requests become connections, decided without I/O.

:class:`EdgePolicy` takes one :class:`~srvwire.transports.base.Handshake` and the server's
state (connections open, draining or not) and returns
:class:`~srvwire.transports.base.Admitted` with the identity, or
:class:`~srvwire.transports.base.Answered` with an HTTP status and a reason. A transport only
carries the answer out (the WebSocket one in ``process_request``), so another transport reuses
it as it is. The checks, in order:

1. ``GET /healthz`` is answered ``200 ok`` while serving and ``503 draining`` while shutting
   down, upgrade or not.
2. A request that is not a WebSocket upgrade (a browser opening the URL) is answered 426 with
   a line saying what this port is.
3. While shutting down, every upgrade is answered 503 with ``Retry-After``.
4. **Host** (the DNS-rebinding guard): a server bound to loopback answers 403 to a ``Host``
   that is not one of its names (``localhost``, ``127.0.0.1``, ``[::1]``, or the host of an
   origin listed in ``origins``).
5. **Origin**: no ``Origin`` header (a program, not a browser) passes. A browser's origin
   passes when it is listed in ``origins``, or names the same host and port as the ``Host``
   header (the page came from this server); ``Origin: null`` passes only when ``"null"`` is
   listed. ``"*"`` in ``origins`` turns steps 4 and 5 off. Anything else is 403.
6. Past ``max_connections`` open connections: 503 with ``Retry-After``.
7. **Authentication**: with an authenticator, its identity, or 401 with
   ``WWW-Authenticate: Bearer`` and its reason. Without one, a client certificate's subject
   (mutual TLS) is the identity, else there is none.

The subprotocol selected is ``srvwire.v1`` when offered, else none: a token offered as a
subprotocol is never echoed. A refusal is logged (at INFO, with its reason, never the
credentials) at most once per :data:`REFUSAL_LOG_INTERVAL`; the next line says how many were
refused in between, so a client knocking in a loop cannot fill the log.
"""

from __future__ import annotations

import ipaddress
import logging
import time
import urllib.parse
from collections.abc import Callable, Iterable
from typing import Any

from srvwire.auth import SUBPROTOCOL, Authenticator, Identity, as_identity, certificate_subject
from srvwire.errors import Unauthenticated
from srvwire.transports.base import Admitted, Answered, Handshake, Hosts

__all__ = ["HEALTH_PATH", "EdgePolicy", "describe_reach", "is_loopback"]

HEALTH_PATH = "/healthz"
RETRY_AFTER = "5"  # seconds, for a client refused because the server is full or draining
REFUSAL_LOG_INTERVAL = 1.0
"""Seconds: at most one log line about refused connections in this time."""
_DEFAULT_PORTS = {"http": 80, "ws": 80, "https": 443, "wss": 443}
_LOOPBACK_NAMES = frozenset({"localhost", "127.0.0.1", "::1"})

NOT_WEBSOCKET = (
    "This is a srvwire server: JSON-RPC 2.0 services over WebSocket. Connect with a WebSocket "
    "client to this URL (for example: srvwire service list --url ws://HOST:PORT, or wscat -c "
    "ws://HOST:PORT). GET /healthz tells whether it is serving.\n"
)


def is_loopback(host: Hosts) -> bool:
    """Whether ``host`` (a name or an address, IPv6 with or without brackets) is loopback;
    for several hosts, whether every one is (None, every interface, is not)."""
    if host is None:
        return False
    if not isinstance(host, str):
        return bool(host) and all(is_loopback(one) for one in host)
    name = host.strip("[]").lower()
    if name == "localhost" or name.endswith(".localhost"):
        return True
    try:
        return ipaddress.ip_address(name).is_loopback
    except ValueError:
        return False


def describe_reach(host: Hosts, *, authenticated: bool, tls: bool) -> str:
    """Say who can reach a server listening on ``host``, for its startup line."""
    over = "over TLS" if tls else "unencrypted"
    if is_loopback(host):
        who = "only programs on this machine can connect (loopback)"
    else:
        hosts = [host] if isinstance(host, str) else list(host or [])
        where = ", ".join(h for h in hosts if h and not is_loopback(h)) or "this machine"
        who = f"any host that can route to {where} can connect"
    check = "callers must authenticate" if authenticated else "no authentication"
    return f"{who}; {check}; {over}"


def _split_host(text: str, default_port: int) -> tuple[str, int] | None:
    """``host[:port]`` (IPv6 in brackets) as ``(host, port)``; None when it is not one."""
    try:
        parts = urllib.parse.urlsplit("//" + text.strip())
        port = parts.port
    except ValueError:
        return None
    if not parts.hostname or parts.path or parts.query or parts.username is not None:
        return None
    return parts.hostname.lower(), default_port if port is None else port


def _parse_origin(text: str) -> tuple[str, str, int] | None:
    """An origin ``scheme://host[:port]`` as ``(scheme, host, port)``; None when it is not."""
    try:
        parts = urllib.parse.urlsplit(text.strip())
        port = parts.port
    except ValueError:
        return None
    scheme = parts.scheme.lower()
    if scheme not in _DEFAULT_PORTS or not parts.hostname or parts.path not in ("", "/"):
        return None
    return scheme, parts.hostname.lower(), _DEFAULT_PORTS[scheme] if port is None else port


class EdgePolicy:
    """Who may open a connection to one listening server (see the module's checks).

    ``host`` is where the server listens; ``origins`` the browser origins allowed besides
    same-host pages (``"null"`` for ``Origin: null``, ``"*"`` for all: dangerous, any web page
    the operator opens can then call the services); ``auth`` the authenticator (None: no
    authentication); ``max_connections`` the most connections open at once (None: no limit);
    ``clock`` what the log's rate limit reads (seconds).
    """

    def __init__(
        self,
        host: Hosts,
        *,
        origins: Iterable[str] = (),
        auth: Authenticator | None = None,
        max_connections: int | None = None,
        logger: logging.Logger | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.host = host
        self.clock = clock
        self.refused_unlogged = 0  # refusals since the last line about one
        self.refusal_logged: float | None = None
        self.loopback = is_loopback(host)
        self.any_origin = False
        self.allow_null = False
        self.origins: set[tuple[str, str, int]] = set()
        names = set(_LOOPBACK_NAMES)
        for origin in origins:
            if origin == "*":
                self.any_origin = True
            elif origin == "null":
                self.allow_null = True
            else:
                parsed = _parse_origin(origin)
                if parsed is None:
                    raise ValueError(
                        f"not an origin: {origin!r}; write scheme://host[:port], such as "
                        "https://app.example.com, or 'null', or '*'"
                    )
                self.origins.add(parsed)
                names.add(parsed[1])
        self.names = frozenset(names)
        self.auth = auth
        self.max_connections = max_connections
        self.log = logger if logger is not None else logging.getLogger(__name__)

    def __repr__(self) -> str:
        return (
            f"<EdgePolicy on {self.host}: {len(self.origins)} origins listed, "
            f"auth={self.auth!r}, max_connections={self.max_connections}>"
        )

    async def admit(
        self, handshake: Handshake, *, connections: int = 0, draining: bool = False
    ) -> Admitted | Answered:
        """Admit ``handshake`` or answer it; ``connections`` are open now."""
        path = urllib.parse.urlsplit(handshake.path).path
        if path == HEALTH_PATH and handshake.method == "GET":
            return Answered(503, "draining\n") if draining else Answered(200, "ok\n")
        upgrade = handshake.header("Upgrade") or ""
        if "websocket" not in upgrade.lower():
            return Answered(426, NOT_WEBSOCKET, (("Upgrade", "websocket"),))
        if draining:
            return self._refuse(
                handshake, 503, "the server is shutting down", (("Retry-After", RETRY_AFTER),)
            )
        refusal = self.check_host_and_origin(handshake)
        if refusal is not None:
            return self._refuse(handshake, 403, refusal)
        limit = self.max_connections
        if limit is not None and connections >= limit:
            return self._refuse(
                handshake,
                503,
                f"too many connections (the limit is {limit}); try again later",
                (("Retry-After", RETRY_AFTER),),
            )
        identity: Identity | None = None
        if self.auth is not None:
            try:
                identity = as_identity(await self.auth(handshake))
            except Unauthenticated as exc:
                return self._refuse(handshake, 401, exc.message, (("WWW-Authenticate", "Bearer"),))
            except Exception:
                self.log.exception("the authenticator %r failed on %r", self.auth, handshake)
                return Answered(500, "the server failed to check the credentials\n")
        elif handshake.client_certificate is not None:
            subject = certificate_subject(handshake.client_certificate)
            if subject is not None:
                identity = Identity(subject)
        subprotocol = SUBPROTOCOL if SUBPROTOCOL in handshake.subprotocols else None
        return Admitted(identity, subprotocol)

    def check_host_and_origin(self, handshake: Handshake) -> str | None:
        """Return why the ``Host`` or ``Origin`` of ``handshake`` is refused, or None."""
        if self.any_origin:
            return None
        default_port = 443 if handshake.tls else 80
        host_text = handshake.header("Host") or ""
        host = _split_host(host_text, default_port)
        if self.loopback and (host is None or host[0] not in self.names):
            return (
                f"Host {host_text!r} is not a name of this server: it listens on loopback, "
                "whose names are localhost, 127.0.0.1 and [::1]; a page can point any DNS "
                "name at 127.0.0.1. List an origin with that host to allow it"
            )
        origin_text = handshake.header("Origin")
        if origin_text is None:
            return None  # not a browser
        if origin_text.strip() == "null":
            if self.allow_null:
                return None
            return (
                "Origin null (a file:// page or a sandboxed frame) is not allowed; "
                "list 'null' in the origins to allow it"
            )
        origin = _parse_origin(origin_text)
        if origin is None:
            return f"Origin {origin_text!r} is not an origin (scheme://host[:port])"
        if origin in self.origins:
            return None
        if host is not None:
            # A Host without a port was sent for the origin's scheme (behind a proxy, too).
            same_host = _split_host(host_text, _DEFAULT_PORTS[origin[0]])
            if same_host == (origin[1], origin[2]) and (
                not self.loopback or origin[1] in self.names
            ):
                return None
        return (
            f"Origin {origin_text} is not allowed: a page from another site may not connect; "
            "list it in the origins (srvwire serve --origin ORIGIN) to allow it"
        )

    def _refuse(
        self, handshake: Handshake, status: int, reason: str, headers: tuple[Any, ...] = ()
    ) -> Answered:
        if self.log.isEnabledFor(logging.INFO):
            now = self.clock()
            last = self.refusal_logged
            if last is not None and now - last < REFUSAL_LOG_INTERVAL:
                self.refused_unlogged += 1
            else:
                self.refusal_logged = now
                more, self.refused_unlogged = self.refused_unlogged, 0
                self.log.info(
                    "refused a connection from %s: HTTP %d, %s%s",
                    handshake.peer,
                    status,
                    reason,
                    f" ({more} more refused since the last line)" if more else "",
                )
        return Answered(status, reason + "\n", headers)
