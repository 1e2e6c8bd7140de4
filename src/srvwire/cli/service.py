"""``srvwire service``: ask a running server what it offers, through ``rpc.discover``."""

from __future__ import annotations

import argparse
import asyncio

from srvwire.cli.common import Commands, ExitCode, add_command, open_client, remote_options
from srvwire.cli.interface import remote_definition_lines
from srvwire.client import ServiceInfo
from srvwire.dispatch import service_not_found
from srvwire.protocol import canonical_name


def register(commands: Commands) -> None:
    service = add_command(
        commands,
        "service",
        "ask a running server about its services",
        "examples:\n"
        "  srvwire service list -t\n"
        "  srvwire service type /add_two_ints\n"
        "  srvwire service describe /add_two_ints\n"
        "  srvwire service find std_srvs/srv/Trigger",
    )
    verbs = service.add_subparsers(title="subcommands", metavar="SUBCOMMAND", required=True)
    remote = remote_options()

    listing = add_command(
        verbs,
        "list",
        "list the services the server offers",
        "example:\n  srvwire service list -t --url ws://robot:8765",
        [remote],
    )
    listing.add_argument(
        "-t", "--show-types", action="store_true", help="add each service's type in brackets"
    )
    listing.add_argument(
        "-c", "--count-services", action="store_true", help="print only the number of services"
    )
    listing.set_defaults(command=_cmd_service_list)

    type_ = add_command(
        verbs,
        "type",
        "print the type of a service",
        "example:\n  srvwire service type /add_two_ints",
        [remote],
    )
    type_.add_argument("name", metavar="NAME", help="the service, e.g. /add_two_ints")
    type_.set_defaults(command=_cmd_service_type)

    describe = add_command(
        verbs,
        "describe",
        "print a service's type and its definition, as the server describes it",
        "example:\n  srvwire service describe /add_two_ints\n\n"
        "The definition comes from the server (rpc.discover), not from local files; each\n"
        "nested type is printed beneath the field that uses it, indented by one tab.",
        [remote],
    )
    describe.add_argument("name", metavar="NAME", help="the service, e.g. /add_two_ints")
    describe.set_defaults(command=_cmd_service_describe)

    find = add_command(
        verbs,
        "find",
        "list the services of a given type",
        "example:\n  srvwire service find std_srvs/srv/Trigger",
        [remote],
    )
    find.add_argument("type", metavar="TYPE", help="a service type, pkg/srv/Name or pkg/Name")
    find.set_defaults(command=_cmd_service_find)


async def _services(args: argparse.Namespace) -> list[ServiceInfo]:
    """The services, without the actions (``srvwire action list`` lists those)."""
    async with open_client(args) as client:
        listed = await client.list_services(timeout=args.timeout)
        return [info for info in listed if "/action/" not in info.type]


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
    raise service_not_found(name, (info.name for info in services))


def _cmd_service_find(args: argparse.Namespace) -> int:
    parts = args.type.split("/")
    wanted = f"{parts[0]}/srv/{parts[1]}" if len(parts) == 2 else args.type
    for info in asyncio.run(_services(args)):
        if info.type == wanted:
            print(info.name)
    return ExitCode.OK


async def _described(args: argparse.Namespace) -> tuple[list[ServiceInfo], dict[str, str], str]:
    async with open_client(args) as client:
        services = await client.list_services(timeout=args.timeout)
        return services, await client.definitions(timeout=args.timeout), client.url


def _cmd_service_describe(args: argparse.Namespace) -> int:
    name = canonical_name(args.name)
    services, texts, url = asyncio.run(_described(args))
    for info in services:
        if info.name == name:
            lines = remote_definition_lines(texts, info.type, "top", f"server {url}")
            print(f"{info.name} [{info.type}]")
            for line in lines:
                print(line)
            return ExitCode.OK
    raise service_not_found(name, (info.name for info in services))
