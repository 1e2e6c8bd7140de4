"""The ``srvwire`` command line: call services, inspect servers and interfaces, serve an app.

Theory of operation
-------------------

:func:`main` builds one :mod:`argparse` parser, runs the chosen command and returns its exit
code; it never raises and never prints a traceback. Commands report failure by raising
:class:`CommandError` (a message and an exit code) or by letting a srvwire error escape, which
:func:`main` turns into one line on stderr, ``srvwire: error: ...``, and the code below. A
standard output closed early (``srvwire ... | head``) ends the command quietly with code 1.
Commands that talk to a server run their own event loop with :func:`asyncio.run`, so ``main``
must be called from a thread that has no running loop.

Exit codes
----------

===  ========================================================================================
0    success
1    a local failure: an unknown type or package, an interface file that does not parse,
     ``interface check`` found errors, a ``serve`` target that cannot be loaded
2    usage: bad arguments, VALUES that are not a YAML mapping
3    the server cannot be reached, the connection dropped, or the server is shutting down
4    the deadline passed (DEADLINE_EXCEEDED)
5    the server has no such service (SERVICE_NOT_FOUND)
6    the request does not fit the service type (INVALID_PARAMS)
7    the handler failed: INTERNAL, or an application error raised with ``ServiceError``
8    any other error from the server: CANCELLED, RESOURCE_EXHAUSTED, UNAUTHENTICATED, ...
130  interrupted with Ctrl-C (except ``serve`` and ``call --rate``, which Ctrl-C ends normally)
===  ========================================================================================
"""

from __future__ import annotations

import argparse
import asyncio
import difflib
import enum
import importlib
import importlib.util
import json
import logging
import os
import re
import sys
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from types import ModuleType
from typing import Any, NoReturn

import pydantic
import yaml

from srvwire import version
from srvwire.client import DEFAULT_TIMEOUT, DEFAULT_URL, Connecting, ServiceInfo, connect
from srvwire.codegen import generate_module
from srvwire.errors import (
    DeadlineExceeded,
    InterfaceError,
    InternalError,
    InvalidParams,
    RPCError,
    ServiceError,
    ServiceNotFound,
    ServiceUnavailable,
    SrvwireError,
)
from srvwire.idl import ActionSpec, InterfaceKind, MessageSpec, ServiceSpec, TypeSpec
from srvwire.loader import InterfaceLoader, default_search_path
from srvwire.models import Service, summarize_errors, validation_errors
from srvwire.parser import parse_file
from srvwire.protocol import canonical_name
from srvwire.server import RunningServer, Server

__all__ = ["ExitCode", "main"]

URL_ENV_VAR = "SRVWIRE_URL"
INTERFACE_SUFFIXES = (".msg", ".srv", ".action")

# TYPE and VALUES are both optional in `srvwire call NAME [TYPE] [VALUES]`; with one of them
# given, it is TYPE when it reads like a type name. VALUES never does: a YAML mapping has a colon.
_TYPE_SHAPE = re.compile(r"^\w+/(?:\w+/)?\w+$")
_ATTRIBUTE_PATH = re.compile(r"^[A-Za-z_]\w*(?:\.[A-Za-z_]\w*)*$")
_DEFAULT_TARGET_ATTRIBUTES = ("server", "app")

logger = logging.getLogger("srvwire.cli")


class ExitCode(enum.IntEnum):
    """What the process exit status means; docs/cli.md has the same table."""

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


EXIT_CODES_HELP = """\
exit codes:
  0    success
  1    local failure: unknown type or package, interface file that does not parse
  2    usage error, or VALUES that are not a YAML mapping
  3    server unreachable, connection lost, or server shutting down (UNAVAILABLE)
  4    deadline exceeded (DEADLINE_EXCEEDED)
  5    no such service (SERVICE_NOT_FOUND)
  6    request does not fit the service type (INVALID_PARAMS)
  7    the handler failed (INTERNAL, or an application error)
  8    any other error from the server (CANCELLED, RESOURCE_EXHAUSTED, ...)
  130  interrupted with Ctrl-C"""


class CommandError(Exception):
    """Raised by a command to stop with one line on stderr and a given exit code."""

    def __init__(self, message: str, exit_code: ExitCode = ExitCode.FAILURE) -> None:
        self.message = message
        self.exit_code = exit_code
        super().__init__(message)


class _UsageError(Exception):
    """Raised instead of argparse's print-usage-and-exit, so main() can return 2."""

    def __init__(self, message: str, prog: str) -> None:
        self.message = message
        self.prog = prog
        super().__init__(message)


class _HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Keep the epilog's examples as written, and give option names a wider column."""

    def __init__(self, prog: str) -> None:
        super().__init__(prog, max_help_position=32)
        self._action_max_length = 14  # room for "    interface" in the list of commands


class _Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors reach main() instead of exiting the process."""

    def error(self, message: str) -> NoReturn:
        raise _UsageError(message, self.prog)


def main(argv: list[str] | None = None) -> int:
    """Run the ``srvwire`` command line with ``argv`` (default ``sys.argv[1:]``)."""
    try:
        code = _run(argv)
        sys.stdout.flush()  # so a closed pipe shows up here, not at interpreter exit
    except BrokenPipeError:  # the reader went away (`srvwire ... | head`): stop quietly
        _discard_stdout()
        return ExitCode.FAILURE
    return code


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
    except _UsageError as exc:
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
        return _exit_code_for(exc)
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
    """Give ``call`` the TYPE and VALUES written after an option (``call /x --json '{a: 1}'``).

    argparse matches consecutive positionals in one go, so optional ones that come after an
    option are left over as "unrecognized"; any other leftover is an error, as argparse says.
    """
    if args.command is _cmd_call and not any(extra.startswith("-") for extra in extras):
        free = [slot for slot in ("type", "values") if getattr(args, slot) is None]
        if len(extras) <= len(free):
            for slot, extra in zip(free, extras, strict=False):
                setattr(args, slot, extra)  # _cmd_call tells TYPE from VALUES as usual
            return
    parser.error(f"unrecognized arguments: {' '.join(extras)}")


def _error(message: str) -> None:
    print(f"srvwire: error: {message}", file=sys.stderr)


# --- the parser -------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    """Build the parser for every command; defaults that come from the environment are read now."""
    parser = _Parser(
        prog="srvwire",
        description="ROS 2 style services over JSON-RPC 2.0 on WebSockets.",
        epilog=(
            "examples:\n"
            "  srvwire call /add_two_ints '{a: 1, b: 2}'\n"
            "  srvwire service list -t\n"
            "  srvwire interface show geometry_msgs/msg/Pose\n"
            "  srvwire serve app.py:server\n\n"
            "Run 'srvwire COMMAND --help' for the options of one command.\n\n" + EXIT_CODES_HELP
        ),
        formatter_class=_HelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"srvwire {version.__version__}")
    commands = parser.add_subparsers(title="commands", metavar="COMMAND", required=True)

    remote = _Parser(add_help=False)
    remote.add_argument(
        "--url",
        default=os.environ.get(URL_ENV_VAR) or DEFAULT_URL,
        help=f"server to talk to (default: ${URL_ENV_VAR}, else {DEFAULT_URL})",
    )
    remote.add_argument(
        "--timeout",
        type=_positive_float,
        default=DEFAULT_TIMEOUT,
        metavar="SECONDS",
        help=f"deadline for connecting and for each call (default: {DEFAULT_TIMEOUT:g})",
    )
    local = _Parser(add_help=False)
    local.add_argument(
        "--path",
        action="append",
        default=[],
        type=Path,
        metavar="DIR",
        help="a folder of interface packages, searched before $SRVWIRE_INTERFACE_PATH and the "
        "bundled interfaces (repeatable)",
    )

    _add_call(commands, [remote, local])
    _add_service(commands, [remote])
    _add_interface(commands, [local])
    _add_gen(commands, [local])
    _add_serve(commands)
    return parser


def _add_parser(
    commands: argparse._SubParsersAction[_Parser],
    name: str,
    summary: str,
    epilog: str,
    parents: Sequence[_Parser] = (),
) -> _Parser:
    return commands.add_parser(
        name,
        help=summary,
        description=summary[0].upper() + summary[1:] + ".",
        epilog=epilog,
        parents=list(parents),
        formatter_class=_HelpFormatter,
    )


def _add_call(commands: argparse._SubParsersAction[_Parser], parents: Sequence[_Parser]) -> None:
    call = _add_parser(
        commands,
        "call",
        "call a service and print its response",
        "examples:\n"
        "  srvwire call /add_two_ints '{a: 1, b: 2}'\n"
        "  srvwire call /add_two_ints example_interfaces/srv/AddTwoInts '{a: 1, b: 2}'\n"
        "  srvwire call /trigger --json\n"
        "  srvwire call /get_robot_state '{query_type: pose}' --rate 2\n\n"
        "TYPE may be left out when the server advertises the service's type. With only one of\n"
        "TYPE and VALUES given, it is TYPE when it looks like pkg/srv/Name or pkg/Name.\n\n"
        + EXIT_CODES_HELP,
        parents,
    )
    call.add_argument("name", metavar="NAME", help="the service to call, e.g. /add_two_ints")
    call.add_argument(
        "type", metavar="TYPE", nargs="?", help="its type, e.g. example_interfaces/srv/AddTwoInts"
    )
    call.add_argument(
        "values",
        metavar="VALUES",
        nargs="?",
        help="the request as a YAML mapping, e.g. '{a: 1, b: 2}' (default: {}, all defaults)",
    )
    call.add_argument(
        "-r",
        "--rate",
        type=_positive_float,
        metavar="HZ",
        help="repeat the call HZ times a second, until Ctrl-C or --count calls",
    )
    call.add_argument(
        "-n",
        "--count",
        type=_positive_int,
        metavar="N",
        help="make N calls, then stop (default: 1, or unlimited with --rate)",
    )
    call.add_argument(
        "--json",
        action="store_true",
        help="print only each response, as one line of JSON",
    )
    call.set_defaults(command=_cmd_call)


def _add_service(commands: argparse._SubParsersAction[_Parser], parents: Sequence[_Parser]) -> None:
    service = _add_parser(
        commands,
        "service",
        "ask a running server about its services",
        "examples:\n"
        "  srvwire service list -t\n"
        "  srvwire service type /add_two_ints\n"
        "  srvwire service find std_srvs/srv/Trigger",
    )
    verbs = service.add_subparsers(title="subcommands", metavar="SUBCOMMAND", required=True)

    listing = _add_parser(
        verbs,
        "list",
        "list the services the server offers",
        "example:\n  srvwire service list -t --url ws://robot:8765",
        parents,
    )
    listing.add_argument(
        "-t", "--show-types", action="store_true", help="add each service's type in brackets"
    )
    listing.add_argument(
        "-c", "--count-services", action="store_true", help="print only the number of services"
    )
    listing.set_defaults(command=_cmd_service_list)

    type_ = _add_parser(
        verbs,
        "type",
        "print the type of a service",
        "example:\n  srvwire service type /add_two_ints",
        parents,
    )
    type_.add_argument("name", metavar="NAME", help="the service, e.g. /add_two_ints")
    type_.set_defaults(command=_cmd_service_type)

    find = _add_parser(
        verbs,
        "find",
        "list the services of a given type",
        "example:\n  srvwire service find std_srvs/srv/Trigger",
        parents,
    )
    find.add_argument("type", metavar="TYPE", help="a service type, pkg/srv/Name or pkg/Name")
    find.set_defaults(command=_cmd_service_find)


def _add_interface(
    commands: argparse._SubParsersAction[_Parser], parents: Sequence[_Parser]
) -> None:
    interface = _add_parser(
        commands,
        "interface",
        "inspect and check interface files on the local search path",
        "examples:\n"
        "  srvwire interface list\n"
        "  srvwire interface show geometry_msgs/msg/Pose\n"
        "  srvwire interface proto example_interfaces/srv/AddTwoInts\n"
        "  srvwire interface check interfaces/",
    )
    verbs = interface.add_subparsers(title="subcommands", metavar="SUBCOMMAND", required=True)

    listing = _add_parser(
        verbs,
        "list",
        "list every message, service and action type",
        "example:\n  srvwire interface list -s",
        parents,
    )
    listing.add_argument("-m", "--only-msgs", action="store_true", help="list messages only")
    listing.add_argument("-s", "--only-srvs", action="store_true", help="list services only")
    listing.add_argument("-a", "--only-actions", action="store_true", help="list actions only")
    listing.set_defaults(command=_cmd_interface_list)

    packages = _add_parser(
        verbs,
        "packages",
        "list the interface packages",
        "example:\n  srvwire interface packages --path ./my_interfaces",
        parents,
    )
    packages.set_defaults(command=_cmd_interface_packages)

    package = _add_parser(
        verbs,
        "package",
        "list the types in one package",
        "example:\n  srvwire interface package std_srvs",
        parents,
    )
    package.add_argument("package", metavar="PACKAGE", help="a package name, e.g. std_srvs")
    package.set_defaults(command=_cmd_interface_package)

    show = _add_parser(
        verbs,
        "show",
        "print an interface's definition, with nested types expanded",
        "examples:\n"
        "  srvwire interface show geometry_msgs/msg/Pose\n"
        "  srvwire interface show sensor_msgs/JointState --no-comments\n\n"
        "Nested types are printed beneath the field that uses them, indented by one tab.\n"
        "By default only the comments of the type asked for are kept.",
        parents,
    )
    show.add_argument("type", metavar="TYPE", help="pkg/msg/Name, pkg/srv/Name, or pkg/Name")
    comments = show.add_mutually_exclusive_group()
    comments.add_argument(
        "--all-comments", action="store_true", help="keep the comments of nested types too"
    )
    comments.add_argument("--no-comments", action="store_true", help="strip every comment")
    show.set_defaults(command=_cmd_interface_show)

    proto = _add_parser(
        verbs,
        "proto",
        "print a YAML template of a message, or of a service's request",
        "examples:\n"
        "  srvwire interface proto example_interfaces/srv/AddTwoInts\n"
        '  srvwire call /add_two_ints "$(srvwire interface proto AddTwoInts --flow '
        '--no-quotes)"\n\n'
        "The template holds every field at its default value; for an action it is the goal.",
        parents,
    )
    proto.add_argument("type", metavar="TYPE", help="pkg/msg/Name, pkg/srv/Name, or pkg/Name")
    proto.add_argument(
        "--no-quotes", action="store_true", help="do not wrap the template in double quotes"
    )
    proto.add_argument(
        "--flow", action="store_true", help="print one line, {a: 0, b: 0}, instead of a block"
    )
    proto.set_defaults(command=_cmd_interface_proto)

    check = _add_parser(
        verbs,
        "check",
        "parse interface files and report every one that is broken",
        "examples:\n"
        "  srvwire interface check interfaces/\n"
        "  srvwire interface check my_pkg/srv/Move.srv my_pkg/msg/\n\n"
        "Folders are searched recursively for .msg, .srv and .action files. Each broken file\n"
        "is reported as path:line:column: message; the exit code is 1 if any file is broken.",
    )
    check.add_argument(
        "paths", metavar="PATH", nargs="+", type=Path, help="an interface file or a folder"
    )
    check.set_defaults(command=_cmd_interface_check)


def _add_gen(commands: argparse._SubParsersAction[_Parser], parents: Sequence[_Parser]) -> None:
    gen = _add_parser(
        commands,
        "gen",
        "generate a typed Python module from interface packages",
        "examples:\n"
        "  srvwire gen std_srvs example_interfaces -o my_app/interfaces.py\n"
        "  srvwire gen my_pkg --path ./interfaces -o generated/",
        parents,
    )
    gen.add_argument("packages", metavar="PACKAGE", nargs="+", help="an interface package")
    gen.add_argument(
        "-o",
        "--output",
        required=True,
        type=Path,
        metavar="FILE_OR_DIR",
        help="the .py file to write, or an existing folder to write one module per package into",
    )
    gen.set_defaults(command=_cmd_gen)


def _add_serve(commands: argparse._SubParsersAction[_Parser]) -> None:
    serve_ = _add_parser(
        commands,
        "serve",
        "serve the services of a srvwire Server object",
        "examples:\n"
        "  srvwire serve my_app.services:server\n"
        "  srvwire serve path/to/app.py --port 9000\n"
        "  srvwire serve examples/robot_state_server.py:build_server --factory\n\n"
        "TARGET is MODULE[:ATTR] or FILE.py[:ATTR]; ATTR defaults to 'server', then 'app'.\n"
        "Ctrl-C stops the server gracefully.",
    )
    serve_.add_argument("target", metavar="TARGET", help="where the Server object lives")
    serve_.add_argument(
        "--factory",
        action="store_true",
        help="TARGET is a function that takes no arguments and returns the Server",
    )
    serve_.add_argument(
        "--host", default="127.0.0.1", help="interface to listen on (default: 127.0.0.1)"
    )
    serve_.add_argument(
        "--port",
        type=_port,
        default=8765,
        help="port to listen on; 0 picks a free one (default: 8765)",
    )
    serve_.add_argument(
        "--log-level",
        type=str.lower,
        choices=["debug", "info", "warning", "error"],
        default="info",
        help="how much the server logs to stderr (default: info)",
    )
    serve_.set_defaults(command=_cmd_serve)


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a positive number, not {text}")
    return value


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, not {value}")
    return value


def _port(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a port number: {text!r}") from None
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"must be between 0 and 65535, not {value}")
    return value


# --- interface commands -----------------------------------------------------------------------

_LINE_BREAK = re.compile(r"\r\n|\r|\n")
_KIND_HEADINGS = (
    (InterfaceKind.MSG, "Messages:"),
    (InterfaceKind.SRV, "Services:"),
    (InterfaceKind.ACTION, "Actions:"),
)


def _loader(args: argparse.Namespace) -> InterfaceLoader:
    extra: list[Path] = args.path
    return InterfaceLoader([*extra, *default_search_path()])


def _cmd_interface_list(args: argparse.Namespace) -> int:
    wanted = {
        InterfaceKind.MSG: args.only_msgs,
        InterfaceKind.SRV: args.only_srvs,
        InterfaceKind.ACTION: args.only_actions,
    }
    if not any(wanted.values()):
        wanted = dict.fromkeys(wanted, True)
    names = _loader(args).types()
    for kind, heading in _KIND_HEADINGS:
        if wanted[kind]:
            print(heading)
            for name in names:
                if name.split("/")[1] == kind.value:
                    print(f"    {name}")
    return ExitCode.OK


def _cmd_interface_packages(args: argparse.Namespace) -> int:
    for package in _loader(args).packages():
        print(package)
    return ExitCode.OK


def _cmd_interface_package(args: argparse.Namespace) -> int:
    for name in _loader(args).types(args.package):
        print(name)
    return ExitCode.OK


def _cmd_interface_show(args: argparse.Namespace) -> int:
    loader = _loader(args)
    keep = "all" if args.all_comments else "none" if args.no_comments else "top"
    for line in _definition_lines(loader, loader.resolve_name(args.type), keep, ()):
        print(line)
    return ExitCode.OK


def _definition_lines(
    loader: InterfaceLoader, name: str, keep: str, outer: tuple[str, ...]
) -> Iterator[str]:
    """Yield the lines of ``name``'s file, each nested type's lines after the field using it.

    ``keep`` says whose comments survive: ``"all"``, ``"top"`` (the outermost file's) or
    ``"none"``. ``outer`` is the chain of types being expanded, so a cycle stops expanding.
    """
    spec = _spec_of(loader, name)
    nested = {
        field.line: field.type.qualified_name
        for part in _parts_of(spec)
        for field in part.fields
        if not field.type.is_primitive
    }
    text = loader.path_of(name).read_text(encoding="utf-8").removeprefix("\ufeff")
    lines = _LINE_BREAK.split(text)
    if lines and not lines[-1]:
        lines.pop()
    depth = len(outer)
    strip = keep == "none" or (keep == "top" and depth > 0)
    for number, raw in enumerate(lines, start=1):
        line = _strip_comment(raw) if strip else raw.rstrip()
        if strip and not line.strip():
            continue
        yield "\t" * depth + line if line else ""
        inner = nested.get(number)
        if inner is not None and inner not in outer and inner != name:
            yield from _definition_lines(loader, inner, keep, (*outer, name))


def _spec_of(loader: InterfaceLoader, name: str) -> MessageSpec | ServiceSpec | ActionSpec:
    kind = name.split("/")[1]
    if kind == InterfaceKind.MSG.value:
        return loader.message_spec(name)
    if kind == InterfaceKind.SRV.value:
        return loader.service_spec(name)
    return loader.action_spec(name)


def _parts_of(spec: MessageSpec | ServiceSpec | ActionSpec) -> tuple[MessageSpec, ...]:
    if isinstance(spec, MessageSpec):
        return (spec,)
    if isinstance(spec, ServiceSpec):
        return (spec.request, spec.response)
    return (spec.goal, spec.result, spec.feedback)


def _strip_comment(line: str) -> str:
    """Return ``line`` without its comment; a ``#`` inside a quoted default is not one."""
    quote = ""
    for index, char in enumerate(line):
        if quote:
            if char == quote and line[index - 1] != "\\":
                quote = ""
        elif char in "\"'" and (index == 0 or line[index - 1] in " \t[,"):
            quote = char
        elif char == "#":
            return line[:index].rstrip()
    return line.rstrip()


def _cmd_interface_proto(args: argparse.Namespace) -> int:
    loader = _loader(args)
    name = loader.resolve_name(args.type)
    kind = name.split("/")[1]
    if kind == InterfaceKind.MSG.value:
        instance: pydantic.BaseModel = loader.load_message(name)()
    elif kind == InterfaceKind.SRV.value:
        instance = loader.load_service(name).Request()
    else:
        instance = loader.load_action(name).Goal()
    values = instance.model_dump(mode="json", by_alias=True)
    if args.flow:
        text = yaml.safe_dump(
            values, default_flow_style=True, sort_keys=False, allow_unicode=True, width=float("inf")
        )
        text = text.rstrip("\n")
    else:
        text = yaml.safe_dump(values, default_flow_style=False, sort_keys=False, allow_unicode=True)
    # Quoted, the template pastes into a shell as one argument, as `ros2 interface proto` prints.
    print(text.rstrip("\n") if args.no_quotes else f'"{text}"')
    return ExitCode.OK


def _cmd_interface_check(args: argparse.Namespace) -> int:
    files: list[Path] = []
    for path in args.paths:
        if path.is_dir():
            files.extend(
                sorted(p for p in path.rglob("*") if p.suffix in INTERFACE_SUFFIXES and p.is_file())
            )
        elif path.is_file():
            files.append(path)
        else:
            raise CommandError(f"no such file or folder: {path}", ExitCode.USAGE)
    errors = 0
    for file in files:
        try:
            parse_file(file)
        except InterfaceError as exc:
            errors += 1
            print(exc)
        except OSError as exc:
            errors += 1
            print(f"{file}: cannot read the file: {exc.strerror}")
    print(f"checked {_plural(len(files), 'file')}, {_plural(errors, 'error')}")
    return ExitCode.FAILURE if errors else ExitCode.OK


def _plural(count: int, noun: str) -> str:
    return f"{count} {noun}" if count == 1 else f"{count} {noun}s"


# --- errors from the server -------------------------------------------------------------------


def _exit_code_for(exc: RPCError) -> ExitCode:
    """Map an error from a call to the process exit code documented in docs/cli.md."""
    if isinstance(exc, DeadlineExceeded):
        return ExitCode.DEADLINE_EXCEEDED
    if isinstance(exc, ServiceUnavailable):  # ConnectionLost is one too
        return ExitCode.UNAVAILABLE
    if isinstance(exc, ServiceNotFound):
        return ExitCode.SERVICE_NOT_FOUND
    if isinstance(exc, InvalidParams):
        return ExitCode.INVALID_PARAMS
    if isinstance(exc, InternalError | ServiceError):
        return ExitCode.SERVICE_FAILED
    return ExitCode.OTHER_RPC_ERROR


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
    return text


def _names(message: str, name: str) -> bool:
    """Whether ``message`` mentions the service ``name`` as a whole (not ``/a`` in ``/ab``)."""
    return re.search(rf"(?<![\w/]){re.escape(name)}(?![\w/])", message) is not None


# --- srvwire call -----------------------------------------------------------------------------


def _cmd_call(args: argparse.Namespace) -> int:
    type_arg: str | None = args.type
    values_arg: str | None = args.values
    if values_arg is None and type_arg is not None and not _TYPE_SHAPE.match(type_arg):
        type_arg, values_arg = None, type_arg
    values = _parse_values(values_arg)
    srv_type = _loader(args).load_service(type_arg) if type_arg is not None else None
    count: int | None = args.count if args.count is not None else None if args.rate else 1
    try:
        return asyncio.run(_call(args, srv_type, values, count))
    except KeyboardInterrupt:
        if args.rate is not None:  # Ctrl-C is how a repeating call is meant to end
            return ExitCode.OK
        raise


def _parse_values(text: str | None) -> dict[str, Any]:
    """Read VALUES: a YAML mapping, ``{}`` when left out."""
    if text is None:
        return {}
    try:
        values = yaml.safe_load(text)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = exc.problem or exc.context or "not valid YAML"
        raise CommandError(f"invalid VALUES{where}: {problem}", ExitCode.USAGE) from None
    except yaml.YAMLError as exc:
        raise CommandError(f"invalid VALUES: {exc}", ExitCode.USAGE) from None
    if values is None:
        return {}
    if not isinstance(values, dict):
        raise CommandError(
            f"invalid VALUES: expected a YAML mapping such as '{{a: 1, b: 2}}', "
            f"got {type(values).__name__} {values!r}",
            ExitCode.USAGE,
        )
    return values


async def _call(
    args: argparse.Namespace,
    srv_type: type[Service] | None,
    values: dict[str, Any],
    count: int | None,
) -> int:
    name = canonical_name(args.name)
    async with _connect(args) as client:
        type_name = srv_type.type_name if srv_type is not None else None
        # The server advertised its services' types on connecting; an unknown service is left
        # for the call to report.
        advertised = client.services.get(name)
        if advertised is not None:
            if srv_type is None:
                type_name = advertised
                srv_type = _try_load_service(args, advertised)
            elif advertised != type_name:
                raise CommandError(
                    f"{name} is a {advertised} service, not {type_name}", ExitCode.USAGE
                )
        request: pydantic.BaseModel | dict[str, Any] = values
        if srv_type is not None:
            request = _validate_request(name, srv_type, values)
        loop = asyncio.get_running_loop()
        start = loop.time()
        done = 0
        while count is None or done < count:
            if done and args.rate is not None:
                await asyncio.sleep(max(0.0, start + done / args.rate - loop.time()))
            if not args.json:
                if done:
                    print()
                shown = _ros_repr(request, _part_label(srv_type, type_name, "Request"))
                print(f"requester: making request: {shown}", flush=True)
            response = await client.call(name, request, timeout=args.timeout, srv_type=srv_type)
            if args.json:
                print(json.dumps(_jsonable(response), ensure_ascii=False), flush=True)
            else:
                shown = _ros_repr(response, _part_label(srv_type, type_name, "Response"))
                print(f"\nresponse:\n{shown}", flush=True)
            done += 1
    return ExitCode.OK


def _try_load_service(args: argparse.Namespace, type_name: str) -> type[Service] | None:
    """Load a type the server advertised; None (plain dicts) when it is not on the search path."""
    try:
        return _loader(args).load_service(type_name)
    except InterfaceError as exc:
        logger.debug("cannot load %s here (%s); sending a plain mapping", type_name, exc)
        return None


def _validate_request(name: str, srv_type: type[Service], values: dict[str, Any]) -> Any:
    try:
        return srv_type.Request.model_validate(values)
    except pydantic.ValidationError as exc:
        errors = validation_errors(exc)
        raise InvalidParams(
            f"VALUES do not fit {srv_type.type_name} (checked locally, not sent): "
            f"{summarize_errors(errors)}",
            {"errors": errors},
            service=name,
        ) from None


def _part_label(srv_type: type[Service] | None, type_name: str | None, part: str) -> str | None:
    """Name a request or response as ROS prints it: ``std_srvs.srv.Trigger_Request``."""
    if srv_type is not None:
        model: type[pydantic.BaseModel] = getattr(srv_type, part)
        label = getattr(model, "type_name", None)
        if isinstance(label, str):
            return label.replace("/", ".")
    if type_name is not None:
        return f"{type_name.replace('/', '.')}_{part}"
    return None  # the server did not say: the values print as a plain mapping


def _ros_repr(value: Any, label: str | None = None) -> str:
    """Write a value as ROS 2's Python messages print: ``pkg.msg.Name(field=value, ...)``."""
    if isinstance(value, pydantic.BaseModel):
        model = type(value)
        if label is None:
            type_name = getattr(model, "type_name", None)
            label = type_name.replace("/", ".") if isinstance(type_name, str) else model.__name__
        fields = ", ".join(
            f"{info.alias or key}={_ros_repr(getattr(value, key))}"
            for key, info in model.model_fields.items()
        )
        return f"{label}({fields})"
    if isinstance(value, dict) and label is not None:
        fields = ", ".join(f"{key}={_ros_repr(item)}" for key, item in value.items())
        return f"{label}({fields})"
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_ros_repr(item) for item in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{key!r}: {_ros_repr(item)}" for key, item in value.items()) + "}"
    return repr(value)


def _jsonable(value: Any) -> Any:
    if isinstance(value, pydantic.BaseModel):
        return value.model_dump(mode="json", by_alias=True)
    return value


# --- srvwire service --------------------------------------------------------------------------


def _connect(args: argparse.Namespace) -> Connecting:
    try:
        return connect(
            args.url,
            timeout=args.timeout,
            open_timeout=args.timeout,
            search_path=[*getattr(args, "path", []), *default_search_path()],
        )
    except ValueError as exc:
        raise CommandError(f"bad --url: {exc}", ExitCode.USAGE) from None


async def _services(args: argparse.Namespace) -> list[ServiceInfo]:
    async with _connect(args) as client:
        return await client.list_services(timeout=args.timeout)


def _cmd_service_list(args: argparse.Namespace) -> int:
    services = asyncio.run(_services(args))
    if args.count_services:
        print(len(services))
        return ExitCode.OK
    for info in services:
        print(f"{info.name} [{info.type}]" if args.show_types else info.name)
    return ExitCode.OK


def _cmd_service_type(args: argparse.Namespace) -> int:
    name = canonical_name(args.name)
    services = asyncio.run(_services(args))
    for info in services:
        if info.name == name:
            print(info.type)
            return ExitCode.OK
    candidates = difflib.get_close_matches(name, [info.name for info in services], n=3)
    hint = f"; did you mean {', '.join(candidates)}?" if candidates else ""
    raise ServiceNotFound(
        f"no service named {name}{hint}", {"candidates": candidates}, service=name
    )


def _cmd_service_find(args: argparse.Namespace) -> int:
    parts = args.type.split("/")
    wanted = f"{parts[0]}/srv/{parts[1]}" if len(parts) == 2 else args.type
    for info in asyncio.run(_services(args)):
        if info.type == wanted:
            print(info.name)
    return ExitCode.OK


# --- srvwire gen ------------------------------------------------------------------------------


def _cmd_gen(args: argparse.Namespace) -> int:
    loader = _loader(args)
    output: Path = args.output
    # Each PACKAGE names a package, or one type (`std_srvs/srv/Trigger`) when it holds a slash.
    groups: dict[str, list[str]] = {}
    for item in args.packages:
        names = [loader.resolve_name(item)] if "/" in item else loader.types(item)
        group = groups.setdefault(item.split("/")[0], [])
        group.extend(name for name in names if name not in group)
    if output.suffix == ".py":
        targets = {output: [name for names in groups.values() for name in names]}
    else:  # a folder: one module per package
        targets = {output / f"{package}.py": names for package, names in groups.items()}

    def resolve(type_: TypeSpec) -> MessageSpec:
        return loader.message_spec(type_.qualified_name)

    for target, names in targets.items():
        source = generate_module([_spec_of(loader, name) for name in names], resolve_spec=resolve)
        try:
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_text(source, encoding="utf-8")
        except OSError as exc:
            raise CommandError(f"cannot write {target}: {exc.strerror or exc}") from None
        print(f"wrote {target} ({_plural(len(names), 'interface')})")
    return ExitCode.OK


# --- srvwire serve ----------------------------------------------------------------------------


def _cmd_serve(args: argparse.Namespace) -> int:
    server = _load_target(args.target, factory=args.factory)
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    package_logger = logging.getLogger("srvwire")
    previous_level = package_logger.level
    package_logger.addHandler(handler)
    package_logger.setLevel(args.log_level.upper())

    def ready(running: RunningServer) -> None:
        services = server.registry.services()
        print(f"serving {_plural(len(services), 'service')} on {running.url}", flush=True)
        for name, type_name in services:
            print(f"  {name} [{type_name}]", flush=True)

    def stopping(running: RunningServer) -> None:
        print("shutting down", flush=True)

    try:
        # run() stops on SIGINT or SIGTERM, and takes a KeyboardInterrupt where it cannot.
        server.run(args.host, args.port, ready=ready, stopping=stopping)
    except BrokenPipeError:
        raise  # stdout was closed, which is not a listening problem
    except OSError as exc:
        raise CommandError(f"cannot listen on {args.host}:{args.port}: {exc}") from None
    finally:
        package_logger.removeHandler(handler)
        package_logger.setLevel(previous_level)
    print("stopped", flush=True)
    return ExitCode.OK


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
            raise CommandError(
                f"{location}:{name} is {type(found).__name__!r}, not a srvwire Server"
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
