"""``srvwire interface``: list, show, template and check interface files; no server involved.

Every subcommand reads the search path (``--path``, then the default one) through an
:class:`~srvwire.loader.InterfaceLoader`. ``check`` parses the files it is given, then loads each
through a loader that finds its package first, so the loader reports a nested type that does not
resolve, at the field that names it.
"""

from __future__ import annotations

import argparse
import asyncio
import difflib
from collections.abc import Callable, Iterator
from pathlib import Path

import pydantic
import yaml

from srvwire.cli.common import (
    CommandError,
    Commands,
    ExitCode,
    add_command,
    interface_loader,
    local_options,
    open_client,
    plural,
    positive_float,
    resolve_type,
)
from srvwire.client import DEFAULT_TIMEOUT
from srvwire.errors import InterfaceError, InterfaceSyntaxError
from srvwire.idl import ActionSpec, InterfaceKind, MessageSpec, ServiceSpec
from srvwire.loader import InterfaceLoader
from srvwire.models import values_past
from srvwire.parser import parse_action, parse_file, parse_message, parse_service, split_comment
from srvwire.scanner import split_lines
from srvwire.transports.base import Options
from srvwire.typeregistry import TypeRegistry

INTERFACE_SUFFIXES = (".msg", ".srv", ".action")

_KIND_HEADINGS = (
    (InterfaceKind.MSG, "Messages:"),
    (InterfaceKind.SRV, "Services:"),
    (InterfaceKind.ACTION, "Actions:"),
)


def register(commands: Commands) -> None:
    interface = add_command(
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
    local = local_options()

    listing = add_command(
        verbs,
        "list",
        "list every message, service and action type",
        "example:\n  srvwire interface list -s",
        [local],
    )
    listing.add_argument("-m", "--only-msgs", action="store_true", help="list messages only")
    listing.add_argument("-s", "--only-srvs", action="store_true", help="list services only")
    listing.add_argument("-a", "--only-actions", action="store_true", help="list actions only")
    listing.set_defaults(command=_cmd_interface_list)

    packages = add_command(
        verbs,
        "packages",
        "list the interface packages",
        "example:\n  srvwire interface packages --path ./my_interfaces",
        [local],
    )
    packages.set_defaults(command=_cmd_interface_packages)

    package = add_command(
        verbs,
        "package",
        "list the types in one package",
        "example:\n  srvwire interface package std_srvs",
        [local],
    )
    package.add_argument("package", metavar="PACKAGE", help="a package name, e.g. std_srvs")
    package.set_defaults(command=_cmd_interface_package)

    show = add_command(
        verbs,
        "show",
        "print an interface's definition, with nested types expanded",
        "examples:\n"
        "  srvwire interface show geometry_msgs/msg/Pose\n"
        "  srvwire interface show sensor_msgs/JointState --no-comments\n"
        "  srvwire interface show my_robot/srv/GetStatus --url ws://robot:8765\n\n"
        "Nested types are printed beneath the field that uses them, indented by one tab.\n"
        "By default only the comments of the type asked for are kept.",
        [local],
    )
    show.add_argument("type", metavar="TYPE", help="pkg/msg/Name, pkg/srv/Name, or pkg/Name")
    show.add_argument(
        "--url",
        metavar="URL",
        help="show the type as the server at URL describes it, instead of the local files",
    )
    show.add_argument(
        "--timeout",
        type=positive_float,
        default=DEFAULT_TIMEOUT,
        metavar="SECONDS",
        help=f"with --url: deadline for connecting and asking (default: {DEFAULT_TIMEOUT:g})",
    )
    comments = show.add_mutually_exclusive_group()
    comments.add_argument(
        "--all-comments", action="store_true", help="keep the comments of nested types too"
    )
    comments.add_argument("--no-comments", action="store_true", help="strip every comment")
    show.set_defaults(command=_cmd_interface_show)

    proto = add_command(
        verbs,
        "proto",
        "print a YAML template of a message, or of a service's request",
        "examples:\n"
        "  srvwire interface proto example_interfaces/srv/AddTwoInts\n"
        '  srvwire call /add_two_ints "$(srvwire interface proto AddTwoInts --flow '
        '--no-quotes)"\n\n'
        "The template holds every field at its default value; for an action it is the goal.",
        [local],
    )
    proto.add_argument("type", metavar="TYPE", help="pkg/msg/Name, pkg/srv/Name, or pkg/Name")
    proto.add_argument(
        "--no-quotes", action="store_true", help="do not wrap the template in double quotes"
    )
    proto.add_argument(
        "--flow", action="store_true", help="print one line, {a: 0, b: 0}, instead of a block"
    )
    proto.set_defaults(command=_cmd_interface_proto)

    check = add_command(
        verbs,
        "check",
        "parse interface files and report every one that is broken",
        "examples:\n"
        "  srvwire interface check interfaces/\n"
        "  srvwire interface check my_pkg/srv/Move.srv my_pkg/msg/\n\n"
        "Folders are searched recursively for .msg, .srv and .action files. Each broken file\n"
        "is reported as path:line:column: message; the exit code is 1 if any file is broken.\n"
        "Nested types are looked up in the file's own package, then on the search path.",
        [local],
    )
    check.add_argument(
        "paths", metavar="PATH", nargs="+", type=Path, help="an interface file or a folder"
    )
    check.set_defaults(command=_cmd_interface_check)


def _cmd_interface_list(args: argparse.Namespace) -> int:
    wanted = {
        InterfaceKind.MSG: args.only_msgs,
        InterfaceKind.SRV: args.only_srvs,
        InterfaceKind.ACTION: args.only_actions,
    }
    if not any(wanted.values()):
        wanted = dict.fromkeys(wanted, True)
    names = interface_loader(args).types()
    for kind, heading in _KIND_HEADINGS:
        if wanted[kind]:
            print(heading)
            for name in names:
                if name.split("/")[1] == kind.value:
                    print(f"    {name}")
    return ExitCode.OK


def _cmd_interface_packages(args: argparse.Namespace) -> int:
    for package in interface_loader(args).packages():
        print(package)
    return ExitCode.OK


def _cmd_interface_package(args: argparse.Namespace) -> int:
    for name in interface_loader(args).types(args.package):
        print(name)
    return ExitCode.OK


def _cmd_interface_show(args: argparse.Namespace) -> int:
    keep = "all" if args.all_comments else "none" if args.no_comments else "top"
    if args.url is not None:
        lines = asyncio.run(_remote_show(args, args.type, keep))
    else:
        loader = interface_loader(args)
        name = resolve_type(loader, args.type)
        loader.load(name)  # the whole type first: a broken one is said before anything is shown
        lines = list(_definition_lines(_local_definition(loader), name, keep, ()))
    for line in lines:
        print(line)
    return ExitCode.OK


Definition = Callable[[str], tuple[MessageSpec | ServiceSpec | ActionSpec, str]]
"""Gives the spec and the text of a type, by its full name."""


def _local_definition(loader: InterfaceLoader) -> Definition:
    def read(name: str) -> tuple[MessageSpec | ServiceSpec | ActionSpec, str]:
        text = loader.path_of(name).read_text(encoding="utf-8").removeprefix("\ufeff")
        return loader.spec(name), text

    return read


async def _remote_show(args: argparse.Namespace, wanted: str, keep: str) -> list[str]:
    """The lines ``interface show`` prints for ``wanted`` as the server at ``--url`` has it."""
    async with open_client(args) as client:
        texts = await client.definitions(timeout=args.timeout)
    return remote_definition_lines(texts, wanted, keep, f"server {client.url}")


def remote_definition_lines(
    texts: dict[str, str], wanted: str, keep: str, source: str
) -> list[str]:
    """The lines of ``wanted`` (``pkg/kind/Name`` or ``pkg/Name``) as ``texts`` define it.

    ``texts`` is a server's description (:meth:`~srvwire.client.Client.definitions`), which
    holds every type its services nest; ``source`` names it in errors.
    """
    parts = wanted.split("/")
    kinds = [parts[1]] if len(parts) == 3 else [kind.value for kind in InterfaceKind]
    names = [f"{parts[0]}/{kind}/{parts[-1]}" for kind in kinds if len(parts) in (2, 3)]
    found = [name for name in names if name in texts]
    if len(found) != 1:
        close = difflib.get_close_matches(wanted, list(texts), n=3, cutoff=0.5)
        hint = f"; did you mean {', '.join(close)}?" if close else ""
        what = f"more than one type named {wanted!r}" if found else f"no type {wanted!r}"
        raise CommandError(f"the {source} describes {what} (of {len(texts)} types){hint}")

    def read(name: str) -> tuple[MessageSpec | ServiceSpec | ActionSpec, str]:
        text = texts.get(name)
        if text is None:
            raise CommandError(f"the {source} does not describe {name}, which it nests")
        package, kind, short = name.split("/")
        parse = _PARSERS[kind]
        return parse(text, package, short, path=source), text

    return list(_definition_lines(read, found[0], keep, ()))


_PARSERS: dict[str, Callable[..., MessageSpec | ServiceSpec | ActionSpec]] = {
    InterfaceKind.MSG.value: parse_message,
    InterfaceKind.SRV.value: parse_service,
    InterfaceKind.ACTION.value: parse_action,
}


def _definition_lines(
    definition: Definition, name: str, keep: str, outer: tuple[str, ...]
) -> Iterator[str]:
    """Yield the lines of ``name``'s file, each nested type's lines after the field using it.

    ``keep`` says whose comments survive: ``"all"``, ``"top"`` (the outermost file's) or
    ``"none"``. ``outer`` is the chain of types being expanded, so a cycle stops expanding.
    """
    spec, text = definition(name)
    nested = {
        field.line: field.type.qualified_name
        for part in _parts_of(spec)
        for field in part.fields
        if not field.type.is_primitive
    }
    lines = split_lines(text)
    if lines and not lines[-1]:
        lines.pop()
    depth = len(outer)
    strip = keep == "none" or (keep == "top" and depth > 0)
    for number, raw in enumerate(lines, start=1):
        line = split_comment(raw)[0].rstrip() if strip else raw.rstrip()
        if strip and not line.strip():
            continue
        yield "\t" * depth + line if line else ""
        inner = nested.get(number)
        if inner is not None and inner not in outer and inner != name:
            yield from _definition_lines(definition, inner, keep, (*outer, name))


def _parts_of(spec: MessageSpec | ServiceSpec | ActionSpec) -> tuple[MessageSpec, ...]:
    if isinstance(spec, MessageSpec):
        return (spec,)
    if isinstance(spec, ServiceSpec):
        return (spec.request, spec.response)
    return (spec.goal, spec.result, spec.feedback)


def _cmd_interface_proto(args: argparse.Namespace) -> int:
    loader = interface_loader(args)
    name = resolve_type(loader, args.type)
    kind = name.split("/")[1]
    _refuse_a_template_too_large_to_send(loader, loader.spec(name))
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


def _refuse_a_template_too_large_to_send(
    loader: InterfaceLoader, spec: MessageSpec | ServiceSpec | ActionSpec
) -> None:
    """Refuse a template holding more values than ``srvwire call`` can send in one message.

    Every value takes a byte of the message at least, so such a template could only be
    printed, slowly (a fixed array's values are made only here): ``int32[4294967295] a`` could
    not be printed at all.
    """
    part = _parts_of(spec)[0]  # the message, the request or the goal
    limit = Options().max_message_size  # what srvwire call's client has
    assert limit is not None
    held = values_past(limit, part, loader.message_spec, {})
    if held is not None:
        raise CommandError(
            f"the template of {part.package}/{part.name} would hold "
            f"{held}, more than the {limit} bytes of a message "
            "srvwire call sends by default (srvwire call --max-message-size raises its limit): "
            "write the values of such a type yourself"
        )


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
    loaders: dict[Path, InterfaceLoader] = {}
    checked = {str(file.resolve()): file for file in files}
    reported: set[tuple[str, int, int]] = set()  # each place an error is at, reported once
    for file in files:
        try:
            spec = parse_file(file)
            if file.resolve().parent.name == file.suffix.removeprefix("."):  # pkg/srv/Name.srv
                _load_checked(file, spec.package, loaders, args.path, checked)
        except InterfaceSyntaxError as exc:
            place = (str(Path(exc.path or file).resolve()), exc.line, exc.column)
            if place not in reported:
                reported.add(place)
                errors += 1
                print(exc)
        except InterfaceError as exc:  # no position of its own: say which file it is about
            errors += 1
            print(f"{file}: {exc}")
        except OSError as exc:
            errors += 1
            print(f"{file}: cannot read the file: {exc.strerror}")
    print(f"checked {plural(len(files), 'file')}, {plural(errors, 'error')}")
    return ExitCode.FAILURE if errors else ExitCode.OK


def _load_checked(
    file: Path,
    package: str,
    loaders: dict[Path, InterfaceLoader],
    extra: list[Path],
    checked: dict[str, Path],
) -> None:
    """Load the type ``file`` defines, so its nested types resolve or are reported.

    The loader searches the folder holding the file's package first, then ``--path`` and the
    default search path; one loader serves every file under the same folder. An error the
    loader places in one of the ``checked`` files (each resolved path to the path as the user
    wrote it) names that file as the user wrote it. It may be in another file than ``file``:
    a cycle through two files is found in the second file whichever file the load starts from,
    so each file's load reports the other's field (the caller reports each place once).
    """
    resolved = file.resolve()  # the folders as they are, whatever '..' the user wrote
    root = resolved.parent.parent.parent
    loader = loaders.get(root)
    if loader is None:
        loader = loaders[root] = InterfaceLoader([root, *extra], types=TypeRegistry())
    try:
        loader.load(f"{package}/{resolved.parent.name}/{file.stem}")
    except InterfaceSyntaxError as exc:
        given = checked.get(str(Path(exc.path).resolve())) if exc.path else None
        if given is None:
            raise
        raise InterfaceSyntaxError(
            exc.message, path=given, line=exc.line, column=exc.column
        ) from exc
