"""``srvwire serve``: run the services of a :class:`~srvwire.server.Server` defined in user code.

TARGET is ``module[:attr]`` or ``file.py[:attr]``; the attribute defaults to ``server``, then
``app``. The first line printed is always ``serving N services on URL[, URL...]``, with every
address the server can be reached at; the services follow, then a line saying who can reach the
server. Ctrl-C or SIGTERM stops the server gracefully and exits with 0. It refuses to listen on
an address other than loopback when nobody has to authenticate (no ``auth`` on the Server, no
``--client-ca``), unless ``--allow-unauthenticated``.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import inspect
import logging
import os
import re
import ssl
import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

from srvwire.cli.common import (
    CommandError,
    Commands,
    ExitCode,
    add_command,
    port,
    positive_int,
)
from srvwire.handshake import EdgePolicy, is_loopback
from srvwire.server import RunningServer, Server
from srvwire.transports import get_transport

_ATTRIBUTE_PATH = re.compile(r"^[A-Za-z_]\w*(?:\.[A-Za-z_]\w*)*$")
_DEFAULT_TARGET_ATTRIBUTES = ("server", "app")


def register(commands: Commands) -> None:
    serve = add_command(
        commands,
        "serve",
        "serve the services of a srvwire Server object",
        "examples:\n"
        "  srvwire serve my_app.services:server\n"
        "  srvwire serve path/to/app.py --port 9000\n"
        "  srvwire serve examples/robot_state_server.py:build_server --factory\n"
        "  srvwire serve app.py --certfile cert.pem --keyfile key.pem --client-ca clients.pem "
        "--host 0.0.0.0\n\n"
        "TARGET is MODULE[:ATTR] or FILE.py[:ATTR]; ATTR defaults to 'server', then 'app'.\n"
        "Ctrl-C stops the server gracefully.",
    )
    serve.add_argument("target", metavar="TARGET", help="where the Server object lives")
    serve.add_argument(
        "--factory",
        action="store_true",
        help="TARGET is a function that takes no arguments and returns the Server",
    )
    serve.add_argument(
        "--host",
        action="append",
        help="interface to listen on (default: 127.0.0.1); give it again to listen on several "
        "(--host 0.0.0.0 --host :: for every IPv4 and IPv6 interface), or '' for every one",
    )
    serve.add_argument(
        "--port",
        type=port,
        default=8765,
        help="port to listen on; 0 picks a free one (default: 8765)",
    )
    serve.add_argument(
        "--origin",
        action="append",
        default=[],
        metavar="ORIGIN",
        help="also allow browser pages from ORIGIN, such as https://app.example.com "
        "(repeatable; 'null' for file:// pages; '*' for any page, which is dangerous)",
    )
    serve.add_argument(
        "--certfile", type=Path, metavar="FILE", help="serve TLS (wss://) with this certificate"
    )
    serve.add_argument(
        "--keyfile", type=Path, metavar="FILE", help="the private key of --certfile (PEM)"
    )
    serve.add_argument(
        "--client-ca",
        type=Path,
        metavar="FILE",
        help="require a client certificate signed by these CAs (mutual TLS); its subject "
        "becomes the connection's identity",
    )
    serve.add_argument(
        "--allow-unauthenticated",
        action="store_true",
        help="listen on an address other than loopback even though nobody has to "
        "authenticate (only on a network you trust)",
    )
    serve.add_argument(
        "--max-message-size",
        type=positive_int,
        metavar="BYTES",
        help="the largest message a client may send, such as a large request (default: the "
        "Server's max_message_size, 1048576 unless the code sets it)",
    )
    serve.add_argument(
        "--log-level",
        type=str.lower,
        choices=["debug", "info", "warning", "error"],
        default="info",
        help="how much the server logs to stderr (default: info)",
    )
    serve.add_argument(
        "--access-log",
        action="store_true",
        help="log a line per call: peer, service, outcome, duration (logger srvwire.access)",
    )
    serve.add_argument(
        "--transport",
        choices=["websockets", "picows"],
        default="websockets",
        help="the WebSocket library to serve on: websockets (default), or picows, the native "
        "one (pip install 'srvwire[fast]')",
    )
    serve.set_defaults(command=_cmd_serve)


def _cmd_serve(args: argparse.Namespace) -> int:
    server = _load_target(args.target, factory=args.factory)
    try:
        transport = get_transport(args.transport)
    except ValueError as exc:
        raise CommandError(str(exc), ExitCode.USAGE) from None
    hosts: list[str] = args.host or ["127.0.0.1"]
    host: str | list[str] = hosts[0] if len(hosts) == 1 else hosts
    if args.max_message_size is not None:
        server.max_message_size = args.max_message_size
    if args.access_log:
        server.access_log = logging.getLogger("srvwire.access")
    if args.origin:
        try:
            EdgePolicy(host, origins=args.origin)
        except ValueError as exc:
            raise CommandError(f"bad --origin: {exc}", ExitCode.USAGE) from None
        server.origins = (*server.origins, *args.origin)
    context = _tls_context(args)
    mutual = context is not None and context.verify_mode == ssl.CERT_REQUIRED
    public = [h for h in hosts if not is_loopback(h)]
    if public and server.auth is None and not mutual:
        if not args.allow_unauthenticated:
            where = public[0] or "every interface"
            raise CommandError(
                f"refusing to listen on {where} without authentication: any host that can "
                "reach it could call every service. Give the Server an authenticator "
                "(Server(auth=srvwire.TokenAuth(...))), require client certificates "
                "(--client-ca), or pass --allow-unauthenticated on a network you trust",
                ExitCode.USAGE,
            )
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    handler.addFilter(_printed_already)
    package_logger = logging.getLogger("srvwire")
    previous_level = package_logger.level
    package_logger.addHandler(handler)
    package_logger.setLevel(args.log_level.upper())

    def ready(running: RunningServer) -> None:
        services = server.registry.services()
        urls = ", ".join(running.urls)
        print(f"serving {server.summary()} on {urls}", flush=True)
        for name, type_name in services:
            print(f"  {name} [{type_name}]", flush=True)
        print(running.reach, flush=True)

    def stopping(running: RunningServer) -> None:
        print("shutting down", flush=True)

    try:
        # run() stops on SIGINT or SIGTERM, and takes a KeyboardInterrupt where it cannot.
        server.run(
            host, args.port, ready=ready, stopping=stopping, ssl=context, transport=transport
        )
    except BrokenPipeError:
        raise  # stdout was closed, which is not a listening problem
    except OSError as exc:
        where = ", ".join(f"{h}:{args.port}" for h in hosts)
        raise CommandError(f"cannot listen on {where}: {exc}") from None
    finally:
        package_logger.removeHandler(handler)
        package_logger.setLevel(previous_level)
    print("stopped", flush=True)
    return ExitCode.OK


def _tls_context(args: argparse.Namespace) -> ssl.SSLContext | None:
    """The server's TLS context from ``--certfile``/``--keyfile``/``--client-ca``, or None.

    A file that cannot be used is a usage error that names the option and the file and says
    what is wrong with it: missing or unreadable, no certificate in it, no private key where
    one is expected (a CA's file given as the key), or a key that is not the certificate's.
    """
    certfile: Path | None = args.certfile
    keyfile: Path | None = args.keyfile
    client_ca: Path | None = args.client_ca
    if certfile is None:
        if keyfile is not None or client_ca is not None:
            raise CommandError(
                "--keyfile and --client-ca need --certfile (the server's certificate)",
                ExitCode.USAGE,
            )
        return None
    cert_pem = _read_pem("--certfile", certfile)
    if not _has_block(cert_pem, "CERTIFICATE"):
        holds = " (it holds a private key: give that as --keyfile)" if _has_key(cert_pem) else ""
        raise _tls_error(f"--certfile {certfile} holds no PEM certificate{holds}")
    if keyfile is not None:
        key_pem = _read_pem("--keyfile", keyfile)
        if not _has_key(key_pem):
            holds = " (it holds a certificate)" if _has_block(key_pem, "CERTIFICATE") else ""
            raise _tls_error(f"--keyfile {keyfile} holds no PEM private key{holds}")
    elif not _has_key(cert_pem):
        raise _tls_error(
            f"--certfile {certfile} holds no private key: give the certificate's key with "
            "--keyfile FILE"
        )
    context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    key_source = f"--keyfile {keyfile}" if keyfile is not None else f"--certfile {certfile}"
    try:
        context.load_cert_chain(certfile, keyfile, password=_no_password(key_source))
    except ssl.SSLError as exc:
        if exc.reason == "KEY_VALUES_MISMATCH":
            raise _tls_error(
                f"the private key in {key_source} is not the key of the certificate in "
                f"--certfile {certfile}"
            ) from None
        raise _tls_error(f"cannot use --certfile {certfile} with {key_source}: {exc}") from None
    if client_ca is not None:
        ca_pem = _read_pem("--client-ca", client_ca)
        if not _has_block(ca_pem, "CERTIFICATE"):
            raise _tls_error(f"--client-ca {client_ca} holds no PEM certificate")
        try:
            context.load_verify_locations(client_ca)
        except ssl.SSLError as exc:
            raise _tls_error(f"cannot use --client-ca {client_ca}: {exc}") from None
        context.verify_mode = ssl.CERT_REQUIRED
    return context


def _read_pem(option: str, path: Path) -> str:
    try:
        return path.read_bytes().decode("ascii", errors="replace")
    except OSError as exc:
        raise _tls_error(f"cannot read {option} {path}: {exc.strerror or exc}") from None


def _has_block(pem: str, label: str) -> bool:
    """Whether ``pem`` has a ``-----BEGIN <label>-----`` block."""
    return f"-----BEGIN {label}-----" in pem


def _has_key(pem: str) -> bool:
    """Whether ``pem`` has a private key block (PKCS #8, RSA, EC, or encrypted)."""
    return re.search(r"-----BEGIN (?:[A-Z]+ )?PRIVATE KEY-----", pem) is not None


def _no_password(key_source: str) -> Callable[[], str]:
    """The password callback of an encrypted key: refuse, instead of a prompt on the terminal."""

    def refuse() -> str:
        raise _tls_error(
            f"the private key in {key_source} is encrypted; serve needs it unencrypted"
        )

    return refuse


def _tls_error(message: str) -> CommandError:
    return CommandError(message, ExitCode.USAGE)


def _printed_already(record: logging.LogRecord) -> bool:
    """Drop the server's start and stop lines, which ``serve`` prints on stdout its own way."""
    return not getattr(record, "srvwire_lifecycle", False)


def _load_target(target: str, *, factory: bool = False) -> Server:
    """Find the Server object TARGET names: ``module[:attr]`` or ``file.py[:attr]``.

    With ``factory``, the attribute is a function to call (with no arguments) for the Server.
    """
    location, _, attribute = target.rpartition(":")
    if not location or not _ATTRIBUTE_PATH.match(attribute):
        location, attribute = target, ""
    module = _import_target(location)
    names = [attribute] if attribute else list(_DEFAULT_TARGET_ATTRIBUTES)
    for name in names:
        found: Any = module
        try:
            for part in name.split("."):
                found = getattr(found, part)
        except AttributeError:
            continue
        if factory:
            if not callable(found):
                raise CommandError(f"{location}:{name} is not callable, so it is not a factory")
            try:
                found = found()
            except Exception as exc:
                raise CommandError(
                    f"{location}:{name}() failed: {type(exc).__name__}: {exc}"
                ) from exc
            if not isinstance(found, Server):
                raise CommandError(
                    f"{location}:{name}() returned {type(found).__name__!r}, not a srvwire Server"
                )
        if not isinstance(found, Server):
            hint = (
                "; if it returns the Server, add --factory"
                if inspect.isfunction(found) or inspect.ismethod(found)
                else ""
            )
            raise CommandError(
                f"{location}:{name} is {type(found).__name__!r}, not a srvwire Server{hint}"
            )
        return found
    wanted = " or ".join(repr(name) for name in names)
    raise CommandError(
        f"{location} has no attribute {wanted}; name the Server object as {location}:NAME"
    )


def _import_target(location: str) -> ModuleType:
    path = Path(location)
    if location.endswith(".py") or os.sep in location or "/" in location:
        if not path.is_file():
            raise CommandError(f"no such file: {location}")
        directory = str(path.resolve().parent)
        if directory not in sys.path:
            sys.path.insert(0, directory)  # so the app can import its neighbours
        spec = importlib.util.spec_from_file_location(path.stem, path)
        if spec is None or spec.loader is None:
            raise CommandError(f"cannot import {location}: not a Python file")
        module = importlib.util.module_from_spec(spec)
        sys.modules[path.stem] = module
        try:
            spec.loader.exec_module(module)
        except Exception as exc:
            del sys.modules[path.stem]
            raise CommandError(f"importing {location} failed: {type(exc).__name__}: {exc}") from exc
        return module
    if "" not in sys.path and os.getcwd() not in sys.path:
        sys.path.insert(0, os.getcwd())  # as `python -m` would, so local modules are found
    try:
        return importlib.import_module(location)
    except ModuleNotFoundError as exc:
        if exc.name is not None and location.startswith(exc.name):
            raise CommandError(f"no module named {location!r}") from None
        raise CommandError(f"importing {location} failed: {type(exc).__name__}: {exc}") from exc
    except Exception as exc:
        raise CommandError(f"importing {location} failed: {type(exc).__name__}: {exc}") from exc
