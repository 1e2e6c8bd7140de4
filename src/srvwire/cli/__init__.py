"""The ``srvwire`` command line: :func:`main`, and the parser the command groups register with.

:func:`main` builds one :mod:`argparse` parser, runs the chosen command and returns its exit
code; it never raises and never prints a traceback. A failure is one line on stderr,
``srvwire: error: ...``, and an :class:`ExitCode`. A standard output closed early
(``srvwire ... | head``) ends the command quietly with code 1. Commands that talk to a server
run their own event loop with :func:`asyncio.run`, so ``main`` must be called from a thread
that has no running loop.

Each command group is a module with a ``register(commands)`` function that adds its parser:
``call``, ``service``, ``topic``, ``action``, ``interface``, ``gen`` and ``serve``;
:mod:`srvwire.cli.common` holds what they share.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
from collections.abc import Callable

from srvwire import version
from srvwire.cli import action, call, gen, interface, serve, service, topic
from srvwire.cli.common import (
    EXIT_CODES_HELP,
    CommandError,
    ExitCode,
    HelpFormatter,
    Parser,
    UsageError,
    exit_code_for,
    size_limit_hint,
)
from srvwire.errors import RPCError, ServiceNotFound, SrvwireError

__all__ = ["ExitCode", "main"]


def main(argv: list[str] | None = None) -> int:
    """Run the ``srvwire`` command line with ``argv`` (default ``sys.argv[1:]``)."""
    try:
        code = _run(argv)
        sys.stdout.flush()  # so a closed pipe shows up here, not at interpreter exit
    except BrokenPipeError:  # the reader went away (`srvwire ... | head`): stop quietly
        _discard_stdout()
        return ExitCode.FAILURE
    return code


def build_parser() -> argparse.ArgumentParser:
    """Build the parser for every command (the environment is read when a command runs)."""
    parser = Parser(
        prog="srvwire",
        description="ROS 2 style services over JSON-RPC 2.0 on WebSockets.",
        epilog=(
            "examples:\n"
            "  srvwire call /add_two_ints '{a: 1, b: 2}'\n"
            "  srvwire service list -t\n"
            "  srvwire topic echo /joint_states --once\n"
            "  srvwire action send_goal /fibonacci '{order: 5}' --feedback\n"
            "  srvwire interface show geometry_msgs/msg/Pose\n"
            "  srvwire serve app.py:server\n\n"
            "Run 'srvwire COMMAND --help' for the options of one command.\n\n" + EXIT_CODES_HELP
        ),
        formatter_class=HelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"srvwire {version.__version__}")
    commands = parser.add_subparsers(title="commands", metavar="COMMAND", required=True)
    call.register(commands)
    service.register(commands)
    topic.register(commands)
    action.register(commands)
    interface.register(commands)
    gen.register(commands)
    serve.register(commands)
    return parser


def _discard_stdout() -> None:
    """Point stdout's file descriptor at devnull, so the interpreter's last flush succeeds.

    The standard recipe from the :mod:`signal` documentation ("Note on SIGPIPE").
    """
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):  # replaced by an object without a descriptor
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, fd)
    finally:
        os.close(devnull)


def _run(argv: list[str] | None) -> int:
    parser = build_parser()
    try:
        args, extras = parser.parse_known_args(argv)
        if extras:
            _take_late_positionals(parser, args, extras)
    except UsageError as exc:
        _error(f"{exc.message} (see '{exc.prog} --help')")
        return ExitCode.USAGE
    except SystemExit as exc:  # --help and --version print, then "exit"
        return exc.code if isinstance(exc.code, int) else ExitCode.OK
    command: Callable[[argparse.Namespace], int] = args.command
    try:
        return command(args)
    except CommandError as exc:
        _error(exc.message)
        return exc.exit_code
    except RPCError as exc:
        _error(_describe_rpc_error(exc))
        return exit_code_for(exc)
    except SrvwireError as exc:
        _error(str(exc))
        return ExitCode.FAILURE
    except KeyboardInterrupt:
        _error("interrupted")
        return ExitCode.INTERRUPTED
    except BrokenPipeError:
        raise  # stdout was closed: main() ends quietly
    except OSError as exc:  # a file that cannot be read or written
        _error(str(exc))
        return ExitCode.FAILURE
    except Exception as exc:  # a bug: still one line, never a traceback
        _error(f"unexpected {type(exc).__name__}: {exc}")
        return ExitCode.FAILURE


def _take_late_positionals(
    parser: argparse.ArgumentParser, args: argparse.Namespace, extras: list[str]
) -> None:
    """Give a command its optional positionals written after an option (``call /x --json '{}'``).

    argparse matches consecutive positionals in one go, so optional ones that come after an
    option are left over as "unrecognized". A command that takes them back names them in its
    ``late_positionals`` default (``call``: TYPE and VALUES); any other leftover is an error,
    as argparse says. A lone ``-`` is a positional (``call``'s VALUES from stdin).
    """
    slots: tuple[str, ...] = getattr(args, "late_positionals", ())
    if slots and not any(extra.startswith("-") and extra != "-" for extra in extras):
        free = [slot for slot in slots if getattr(args, slot) is None]
        if len(extras) <= len(free):
            for slot, extra in zip(free, extras, strict=False):
                setattr(args, slot, extra)  # the command tells them apart as usual
            return
    parser.error(f"unrecognized arguments: {' '.join(extras)}")


def _error(message: str) -> None:
    print(f"srvwire: error: {message}", file=sys.stderr)


def _describe_rpc_error(exc: RPCError) -> str:
    """One line: the class, status and code, the service, the message, and the data as JSON.

    Each fact is said once: a ServiceNotFound's candidates are left out of the data when the
    message already offers them ("did you mean ..."), as srvwire's server writes it.
    """
    text = f"{type(exc).__name__}: {exc}"
    data = exc.data
    if isinstance(exc, ServiceNotFound) and isinstance(data, dict):
        candidates = data.get("candidates")
        if isinstance(candidates, list) and all(
            isinstance(name, str) and _names(exc.message, name) for name in candidates
        ):
            data = {key: value for key, value in data.items() if key != "candidates"} or None
    if data is not None:
        text += f" (data: {json.dumps(data, default=str, ensure_ascii=False)})"
    hint = size_limit_hint(exc)
    if hint is not None:
        text += f"; {hint}"
    return text


def _names(message: str, name: str) -> bool:
    """Whether ``message`` mentions the service ``name`` as a whole (not ``/a`` in ``/ab``)."""
    return re.search(rf"(?<![\w/]){re.escape(name)}(?![\w/])", message) is not None
