"""What every ``srvwire`` command shares: exit codes, parser classes, argument types, options.

A command reports failure by raising :class:`CommandError` (a message and an exit code) or by
letting a srvwire error escape; :func:`srvwire.cli.main` prints either as one line. An error
from a call exits with the code :data:`EXIT_CODES` gives its JSON-RPC code, or
``SERVICE_FAILED`` for an application code (a ``ServiceError``'s, outside the reserved range).
What each exit code means is written for users twice, briefly in :data:`EXIT_CODES_HELP`
(``srvwire --help``) and at length in docs/cli.md; tests/test_cli.py checks that they agree
with :class:`ExitCode` and :data:`EXIT_CODES`.
"""

from __future__ import annotations

import argparse
import contextlib
import enum
import logging
import os
import re
import ssl
from collections.abc import AsyncIterator, Mapping, Sequence
from pathlib import Path
from typing import Final, NoReturn, TypeAlias

from srvwire.client import DEFAULT_TIMEOUT, DEFAULT_URL, Client, connect, plaintext_host
from srvwire.errors import (
    ErrorCode,
    InterfaceError,
    ResourceExhausted,
    RPCError,
    is_reserved_code,
)
from srvwire.loader import InterfaceLoader
from srvwire.typeregistry import TypeRegistry

DEFAULT_MAX_MESSAGE_SIZE = 2**20
"""``--max-message-size``'s default, in bytes: the client's and the server's own."""

CLOSE_MESSAGE_TOO_BIG = 1009
"""The WebSocket close code of a message over the reading side's limit (RFC 6455)."""

URL_ENV_VAR = "SRVWIRE_URL"
TOKEN_ENV_VAR = "SRVWIRE_TOKEN"

_HOST_PORT = re.compile(r"^(?:\[[0-9A-Fa-f:.]+\]|[^:/\[\]]+):\d+$")


class ExitCode(enum.IntEnum):
    """The process exit status of ``srvwire``."""

    OK = 0
    FAILURE = 1
    USAGE = 2
    UNAVAILABLE = 3
    DEADLINE_EXCEEDED = 4
    SERVICE_NOT_FOUND = 5
    INVALID_PARAMS = 6
    SERVICE_FAILED = 7
    OTHER_RPC_ERROR = 8
    INTERRUPTED = 130


EXIT_CODES: Final[Mapping[ErrorCode, ExitCode]] = {
    ErrorCode.PARSE_ERROR: ExitCode.OTHER_RPC_ERROR,
    ErrorCode.INVALID_REQUEST: ExitCode.OTHER_RPC_ERROR,
    ErrorCode.SERVICE_NOT_FOUND: ExitCode.SERVICE_NOT_FOUND,
    ErrorCode.INVALID_PARAMS: ExitCode.INVALID_PARAMS,
    ErrorCode.INTERNAL: ExitCode.SERVICE_FAILED,
    ErrorCode.DEADLINE_EXCEEDED: ExitCode.DEADLINE_EXCEEDED,
    ErrorCode.CANCELLED: ExitCode.OTHER_RPC_ERROR,
    ErrorCode.UNAVAILABLE: ExitCode.UNAVAILABLE,  # ConnectionLost has this code too
    ErrorCode.RESOURCE_EXHAUSTED: ExitCode.OTHER_RPC_ERROR,
    ErrorCode.UNAUTHENTICATED: ExitCode.OTHER_RPC_ERROR,
    ErrorCode.PERMISSION_DENIED: ExitCode.OTHER_RPC_ERROR,
    ErrorCode.GOAL_REJECTED: ExitCode.SERVICE_FAILED,
}
"""The exit code for an error from a call, by the error's JSON-RPC code."""

GOAL_EXIT_CODES: Final[Mapping[str, ExitCode]] = {
    "succeeded": ExitCode.OK,
    "aborted": ExitCode.SERVICE_FAILED,
    "canceled": ExitCode.OTHER_RPC_ERROR,
}
"""The exit code of ``srvwire action send_goal``, by the goal's final status."""


def exit_code_for(error: RPCError) -> ExitCode:
    """Return the exit code for ``error``, chosen by its JSON-RPC code."""
    if not is_reserved_code(error.code):
        return ExitCode.SERVICE_FAILED  # an application error, sent with ServiceError
    try:
        return EXIT_CODES[ErrorCode(error.code)]
    except ValueError:  # a reserved code srvwire has no name for
        return ExitCode.OTHER_RPC_ERROR


EXIT_CODES_HELP = """\
exit codes:
  0    success
  1    local failure: unknown type or package, interface file that does not parse
  2    usage error, or VALUES that are not a YAML mapping
  3    server unreachable, connection lost, or server shutting down (UNAVAILABLE)
  4    deadline exceeded (DEADLINE_EXCEEDED)
  5    no such service or topic (SERVICE_NOT_FOUND)
  6    request or message does not fit its type (INVALID_PARAMS)
  7    the handler failed (INTERNAL, or an application error); a goal GOAL_REJECTED or aborted
  8    any other error from the server (CANCELLED, RESOURCE_EXHAUSTED, ...)
  130  interrupted with Ctrl-C"""


class CommandError(Exception):
    """Raised by a command to stop with one line on stderr and a given exit code."""

    def __init__(self, message: str, exit_code: ExitCode = ExitCode.FAILURE) -> None:
        self.message = message
        self.exit_code = exit_code
        super().__init__(message)


# --- the parser -------------------------------------------------------------------------------


class UsageError(Exception):
    """Raised instead of argparse's print-usage-and-exit, so main() can return 2."""

    def __init__(self, message: str, prog: str) -> None:
        self.message = message
        self.prog = prog
        super().__init__(message)


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Keep the epilog's examples as written, and give option names a wider column."""

    def __init__(self, prog: str) -> None:
        super().__init__(prog, max_help_position=32)
        self._action_max_length = 14  # room for "    interface" in the list of commands


class Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors reach main() instead of exiting the process."""

    def error(self, message: str) -> NoReturn:
        raise UsageError(message, self.prog)


Commands: TypeAlias = "argparse._SubParsersAction[Parser]"
"""Where a command group registers its parser: ``parser.add_subparsers(...)``."""


def add_command(
    commands: Commands,
    name: str,
    summary: str,
    epilog: str,
    parents: Sequence[Parser] = (),
) -> Parser:
    """Add the parser of one command or subcommand; ``summary`` is its line in the list."""
    return commands.add_parser(
        name,
        help=summary,
        description=summary[0].upper() + summary[1:] + ".",
        epilog=epilog,
        parents=list(parents),
        formatter_class=HelpFormatter,
    )


def remote_options() -> Parser:
    """The options of a command that talks to a server, read by :func:`open_client`."""
    remote = Parser(add_help=False)
    remote.add_argument(
        "--url",
        help=f"server to talk to, ws://HOST:PORT, wss://HOST:PORT or HOST:PORT "
        f"(default: ${URL_ENV_VAR}, else {DEFAULT_URL})",
    )
    remote.add_argument(
        "--timeout",
        type=positive_float,
        default=DEFAULT_TIMEOUT,
        metavar="SECONDS",
        help=f"deadline for connecting and for each call (default: {DEFAULT_TIMEOUT:g})",
    )
    remote.add_argument(
        "--token",
        help=f"bearer token to authenticate with (default: ${TOKEN_ENV_VAR}); sent as "
        "'Authorization: Bearer TOKEN', never over plain ws:// to another host",
    )
    remote.add_argument(
        "-H",
        "--header",
        action="append",
        default=[],
        type=header,
        metavar="'NAME: VALUE'",
        help="send this header with the opening request (repeatable)",
    )
    remote.add_argument(
        "--max-message-size",
        type=positive_int,
        default=DEFAULT_MAX_MESSAGE_SIZE,
        metavar="BYTES",
        help="the largest reply or message taken from the server, and the largest request "
        f"sent (default: {DEFAULT_MAX_MESSAGE_SIZE}, 1 MiB); the server has its own limit",
    )
    remote.add_argument(
        "--cacert",
        type=Path,
        metavar="FILE",
        help="trust the server certificates this CA file signed (wss://)",
    )
    remote.add_argument(
        "--insecure",
        action="store_true",
        help="do NOT check the server's TLS certificate: anyone on the way can pretend to be "
        "the server (for a test bench only)",
    )
    return remote


def header(text: str) -> tuple[str, str]:
    name, colon, value = text.partition(":")
    if not colon or not name.strip() or name != name.strip():
        raise argparse.ArgumentTypeError(f"not a header: {text!r}; write 'Name: value'")
    return name, value.strip()


def client_tls(args: argparse.Namespace) -> ssl.SSLContext | None:
    """The client's TLS context from ``--cacert`` and ``--insecure``, or None (the system's)."""
    cacert: Path | None = getattr(args, "cacert", None)
    if getattr(args, "insecure", False):
        context = ssl.create_default_context()
        context.check_hostname = False
        context.verify_mode = ssl.CERT_NONE
        return context
    if cacert is None:
        return None
    try:
        return ssl.create_default_context(cafile=os.fspath(cacert))
    except (OSError, ssl.SSLError) as exc:
        raise CommandError(f"cannot use --cacert {cacert}: {exc}", ExitCode.USAGE) from None


def local_options() -> Parser:
    """The option of a command that reads interface files, read by :func:`interface_loader`."""
    local = Parser(add_help=False)
    local.add_argument(
        "--path",
        action="append",
        default=[],
        type=Path,
        metavar="DIR",
        help="a folder of interface packages, searched before $SRVWIRE_INTERFACE_PATH and the "
        "bundled interfaces (repeatable)",
    )
    return local


def positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a positive number, not {text}")
    return value


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, not {value}")
    return value


def port(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a port number: {text!r}") from None
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"must be between 0 and 65535, not {value}")
    return value


# --- what the options open --------------------------------------------------------------------


def interface_loader(args: argparse.Namespace) -> InterfaceLoader:
    """A loader for the ``--path`` folders, then the default search path.

    Its classes are its own (a :class:`~srvwire.typeregistry.TypeRegistry` of its own): a
    command that reads files does not record them as the process's.
    """
    extra: list[Path] = args.path
    return InterfaceLoader(extra, types=TypeRegistry())


def resolve_type(loader: InterfaceLoader, name: str) -> str:
    """Return the full name of TYPE; a name without a package suggests the full names that fit.

    As with ``ros2 interface``, TYPE names its package: ``AddTwoInts`` alone is an error, which
    names the types of that name on the search path.
    """
    if "/" in name:
        return loader.resolve_name(name)
    matches = [full for full in loader.types() if full.rsplit("/", 1)[1] == name]
    fits = f"; did you mean {' or '.join(matches)}?" if matches else ""
    raise InterfaceError(
        f"{name!r} has no package: write pkg/kind/Name or pkg/Name, as ros2 interface does{fits}"
    )


def server_url(args: argparse.Namespace) -> str:
    """The server's URL: ``--url``, else ``$SRVWIRE_URL``, else the default.

    ``HOST:PORT`` means ``ws://HOST:PORT``; any other text without a scheme is a usage error.
    A URL with a scheme is left for the transport to check.
    """
    given: str | None = args.url
    source = "--url"
    if given is None:
        given, source = os.environ.get(URL_ENV_VAR) or DEFAULT_URL, f"${URL_ENV_VAR}"
    if "://" in given:
        return given
    if _HOST_PORT.match(given):
        return f"ws://{given}"
    raise CommandError(
        f"bad {source}: {given!r} is not a server address; "
        "expected ws://HOST:PORT, wss://HOST:PORT or HOST:PORT",
        ExitCode.USAGE,
    )


@contextlib.asynccontextmanager
async def open_client(args: argparse.Namespace) -> AsyncIterator[Client]:
    """Open a client on ``--url`` with ``--timeout`` and the search path, as ``async with``.

    A URL that is not ``ws://``, ``wss://`` or ``HOST:PORT`` is a usage error.
    """
    url = server_url(args)
    source = "--url" if args.url is not None else f"${URL_ENV_VAR}"
    token: str | None = getattr(args, "token", None) or os.environ.get(TOKEN_ENV_VAR) or None
    headers: list[tuple[str, str]] = getattr(args, "header", [])
    exposed = plaintext_host(url)
    if exposed is not None and (token or any(k.lower() == "authorization" for k, _ in headers)):
        raise CommandError(
            f"refusing to send credentials over plain ws:// to {exposed}, where anyone on the "
            "way can read them: use wss://",
            ExitCode.USAGE,
        )
    entered = False
    try:
        options = connect(
            url,
            timeout=args.timeout,
            open_timeout=args.timeout,
            search_path=getattr(args, "path", []),
            token=token,
            headers=headers,
            ssl=client_tls(args),
            logger=_unlogged(),
            max_message_size=getattr(args, "max_message_size", DEFAULT_MAX_MESSAGE_SIZE),
        )
    except ValueError as exc:
        raise CommandError(f"bad {source}: {exc}", ExitCode.USAGE) from None
    try:
        async with options as client:
            entered = True
            yield client
    except ValueError as exc:
        if entered:  # raised by the command, not by connecting: not about --url
            raise
        raise CommandError(f"bad {source}: {exc}", ExitCode.USAGE) from None


def _unlogged() -> logging.Logger:
    """The client's logger in a command: one that writes nothing.

    What goes wrong reaches the command as an error, which it says in its one line; the
    client's own warnings (a connection lost, with the calls it failed) would be a second.
    """
    logger = logging.Logger("srvwire.client")  # not the process's: nothing else changes
    logger.addHandler(logging.NullHandler())  # else logging's last resort writes to stderr
    return logger


def size_limit_hint(error: RPCError) -> str | None:
    """What to do about ``error`` when a message was over a ``max_message_size``, else None.

    The client refuses to send a request over its limit (``ResourceExhausted`` with the
    limit in its data); a message over the limit of the side that reads it closes the
    connection with 1009, whose reason says which side's limit it was.
    """
    data = error.data if isinstance(error.data, dict) else {}
    mine = "raise this command's limit with --max-message-size BYTES"
    if isinstance(error, ResourceExhausted) and "max_message_size" in data:
        return f"{mine} (a request that size needs the server's limit raised too)"
    if data.get("close_code") != CLOSE_MESSAGE_TOO_BIG:
        return None
    if str(data.get("close_reason", "")).startswith("over the server's"):
        return (
            "the message was over the server's limit: raise it there (srvwire serve "
            "--max-message-size BYTES, or Server(max_message_size=...))"
        )
    return mine


def plural(count: int, noun: str) -> str:
    return f"{count} {noun}" if count == 1 else f"{count} {noun}s"
