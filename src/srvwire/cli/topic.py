"""``srvwire topic``: list a server's topics, print their messages, publish, measure the rate.

Shaped like ``ros2 topic``: ``list``, ``info``, ``echo`` (each message as YAML, then ``---``),
``pub`` (VALUES as YAML, as ``srvwire call`` takes them; once, N times or at a rate) and ``hz``.
"""

from __future__ import annotations

import argparse
import asyncio
import itertools
import math
import sys
from typing import Any

import pydantic
import yaml

from srvwire.calls import encode_message
from srvwire.cli.call import _TYPE_SHAPE, _json_line, _parse_values, _ros_repr
from srvwire.cli.common import (
    EXIT_CODES_HELP,
    Commands,
    ExitCode,
    add_command,
    local_options,
    open_client,
    plural,
    positive_float,
    positive_int,
    remote_options,
)
from srvwire.client import TopicInfo
from srvwire.errors import ServiceNotFound
from srvwire.loader import InterfaceLoader
from srvwire.protocol import canonical_name


def register(commands: Commands) -> None:
    topic = add_command(
        commands,
        "topic",
        "list a server's topics, print their messages, publish on them",
        "examples:\n"
        "  srvwire topic list -t\n"
        "  srvwire topic info /joint_states\n"
        "  srvwire topic echo /joint_states --once\n"
        "  srvwire topic pub /joint_states '{name: [joint_0], position: [0.5]}' --once\n"
        "  srvwire topic hz /joint_states",
    )
    verbs = topic.add_subparsers(title="subcommands", metavar="SUBCOMMAND", required=True)
    remote = remote_options()
    local = local_options()

    listing = add_command(
        verbs,
        "list",
        "list the topics the server offers",
        "example:\n  srvwire topic list -t",
        [remote],
    )
    listing.add_argument(
        "-t", "--show-types", action="store_true", help="add each topic's type in brackets"
    )
    listing.add_argument(
        "-c", "--count-topics", action="store_true", help="print only the number of topics"
    )
    listing.set_defaults(command=_cmd_list)

    info = add_command(
        verbs,
        "info",
        "print a topic's type, QoS, and whether clients may publish on it",
        "example:\n  srvwire topic info /joint_states",
        [remote],
    )
    info.add_argument("name", metavar="NAME", help="the topic, e.g. /joint_states")
    info.set_defaults(command=_cmd_info)

    echo = add_command(
        verbs,
        "echo",
        "print the messages of a topic as they arrive",
        "examples:\n"
        "  srvwire topic echo /joint_states --once\n"
        "  srvwire topic echo /joint_states -n 10 --qos-reliability best_effort\n\n"
        "Each message prints as YAML, followed by a line '---'. Messages the subscription\n"
        "missed (a best-effort queue that overflowed) are said on standard error.\n\n"
        + EXIT_CODES_HELP,
        [remote, local],
    )
    echo.add_argument("name", metavar="NAME", help="the topic, e.g. /joint_states")
    echo.add_argument(
        "type", metavar="TYPE", nargs="?", help="its type (default: what the server announces)"
    )
    _qos_options(echo)
    echo.add_argument("--once", action="store_true", help="print one message, then exit")
    echo.add_argument(
        "-n", "--count", type=positive_int, metavar="N", help="print N messages, then exit"
    )
    echo.add_argument("--json", action="store_true", help="print each message as one JSON line")
    echo.set_defaults(command=_cmd_echo)

    pub = add_command(
        verbs,
        "pub",
        "publish a message on a topic, once or at a rate",
        "examples:\n"
        "  srvwire topic pub /joint_states '{name: [joint_0], position: [0.5]}' --once\n"
        "  srvwire topic pub /joint_states sensor_msgs/msg/JointState '{}' -r 10 -t 50\n\n"
        "Without --once or --times it publishes until Ctrl-C. Each message is acknowledged\n"
        "by the server, so a message it refuses stops the command with its error.\n\n"
        + EXIT_CODES_HELP,
        [remote, local],
    )
    pub.add_argument("name", metavar="NAME", help="the topic, e.g. /joint_states")
    pub.add_argument("type", metavar="TYPE", nargs="?", help="its type, e.g. std_msgs/msg/String")
    pub.add_argument(
        "values",
        metavar="VALUES",
        nargs="?",
        help="the message as a YAML mapping; '-' reads it from stdin, '@FILE' from FILE "
        "(default: {}, all defaults)",
    )
    pub.add_argument("-1", "--once", action="store_true", help="publish one message, then exit")
    pub.add_argument(
        "-t", "--times", type=positive_int, metavar="N", help="publish N messages, then exit"
    )
    pub.add_argument(
        "-r",
        "--rate",
        type=positive_float,
        default=1.0,
        metavar="HZ",
        help="messages a second (default: 1)",
    )
    pub.set_defaults(command=_cmd_pub, late_positionals=("type", "values"))

    hz = add_command(
        verbs,
        "hz",
        "print the rate at which a topic's messages arrive",
        "examples:\n  srvwire topic hz /joint_states\n  srvwire topic hz /joint_states -n 100\n\n"
        "Prints the average rate once a second, and when it stops (after --count messages).",
        [remote, local],
    )
    hz.add_argument("name", metavar="NAME", help="the topic, e.g. /joint_states")
    hz.add_argument(
        "-w",
        "--window",
        type=positive_int,
        default=10_000,
        metavar="N",
        help="measure over the last N messages (default: %(default)s)",
    )
    hz.add_argument("-n", "--count", type=positive_int, metavar="N", help="stop after N messages")
    hz.set_defaults(command=_cmd_hz)


def _qos_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--qos-depth", type=positive_int, metavar="N", help="the subscription's queue length"
    )
    parser.add_argument(
        "--qos-reliability",
        choices=("reliable", "best_effort"),
        help="reliable: end the subscription rather than drop; best_effort: drop the oldest",
    )
    parser.add_argument(
        "--qos-durability",
        choices=("volatile", "transient_local"),
        help="transient_local: start with the last messages the topic kept",
    )


def _qos(args: argparse.Namespace) -> dict[str, Any] | None:
    asked = {
        "depth": args.qos_depth,
        "reliability": args.qos_reliability,
        "durability": args.qos_durability,
    }
    chosen = {key: value for key, value in asked.items() if value is not None}
    return chosen or None


async def _topics(args: argparse.Namespace) -> list[TopicInfo]:
    async with open_client(args) as client:
        return await client.list_topics(timeout=args.timeout)


def _not_found(name: str, topics: list[TopicInfo]) -> ServiceNotFound:
    names = ", ".join(info.name for info in topics) or "none"
    return ServiceNotFound(f"the server has no topic named {name} (topics: {names})", service=name)


def _cmd_list(args: argparse.Namespace) -> int:
    topics = asyncio.run(_topics(args))
    if args.count_topics:
        print(len(topics))
        return ExitCode.OK
    for info in topics:
        print(f"{info.name} [{info.type}]" if args.show_types else info.name)
    return ExitCode.OK


def _cmd_info(args: argparse.Namespace) -> int:
    name = canonical_name(args.name)
    topics = asyncio.run(_topics(args))
    for info in topics:
        if info.name == name:
            qos = info.qos
            print(f"Type: {info.type}")
            print(
                f"QoS: depth {qos.get('depth')}, {qos.get('reliability')}, {qos.get('durability')}"
            )
            print(f"Clients may publish: {'yes' if info.publish else 'no'}")
            return ExitCode.OK
    raise _not_found(name, topics)


def _message_type(args: argparse.Namespace, type_arg: str | None) -> Any:
    return InterfaceLoader(args.path).load_message(type_arg) if type_arg is not None else None


def _cmd_echo(args: argparse.Namespace) -> int:
    count = 1 if args.once else args.count
    try:
        return asyncio.run(_echo(args, _message_type(args, args.type), count))
    except KeyboardInterrupt:  # Ctrl-C is how an endless echo is meant to end
        return ExitCode.OK


async def _echo(args: argparse.Namespace, msg_type: Any, count: int | None) -> int:
    name = canonical_name(args.name)
    async with open_client(args) as client:
        async with client.subscribe(name, msg_type, qos=_qos(args), timeout=args.timeout) as sub:
            printed = 0
            while count is None or printed < count:
                message = await sub.receive()
                if sub.missed:
                    print(
                        f"srvwire: {plural(sub.missed, 'message')} missed before this one",
                        file=sys.stderr,
                    )
                data = message.model_dump(mode="json", by_alias=True)
                if args.json:
                    print(_json_line(data), flush=True)
                else:
                    text = yaml.safe_dump(data, sort_keys=False, allow_unicode=True)
                    print(f"{text}---", flush=True)
                printed += 1
    return ExitCode.OK


def _cmd_pub(args: argparse.Namespace) -> int:
    type_arg: str | None = args.type
    values_arg: str | None = args.values
    if values_arg is None and type_arg is not None and not _TYPE_SHAPE.match(type_arg):
        type_arg, values_arg = None, type_arg
    values = _parse_values(values_arg)
    times = 1 if args.once else args.times
    try:
        return asyncio.run(_pub(args, _message_type(args, type_arg), values, times))
    except KeyboardInterrupt:
        if times is None:
            return ExitCode.OK
        raise


async def _pub(
    args: argparse.Namespace, msg_type: Any, values: dict[str, Any], times: int | None
) -> int:
    name = canonical_name(args.name)
    async with open_client(args) as client:
        if msg_type is None:
            msg_type = await client.topic_type(name, timeout=args.timeout)
        message: pydantic.BaseModel = _validated(name, msg_type, values)
        print("publisher: beginning loop", flush=True)
        loop = asyncio.get_running_loop()
        start = loop.time()
        done = 0
        while times is None or done < times:
            if done:
                await asyncio.sleep(max(0.0, start + done / args.rate - loop.time()))
            await client.publish(name, message, msg_type=msg_type, ack=True, timeout=args.timeout)
            done += 1
            print(f"publishing #{done}: {_ros_repr(message)}\n", flush=True)
    return ExitCode.OK


def _validated(name: str, msg_type: Any, values: dict[str, Any]) -> pydantic.BaseModel:
    """VALUES as the topic's message; InvalidParams with the fields' paths when they do not fit."""
    encode_message(name, msg_type, values)  # raises InvalidParams with the fields' paths
    validated: pydantic.BaseModel = msg_type.model_validate(values)
    return validated


def _cmd_hz(args: argparse.Namespace) -> int:
    try:
        return asyncio.run(_hz(args))
    except KeyboardInterrupt:
        return ExitCode.OK


async def _hz(args: argparse.Namespace) -> int:
    name = canonical_name(args.name)
    loop = asyncio.get_running_loop()
    arrivals: list[float] = []
    async with open_client(args) as client:
        async with client.subscribe(name, timeout=args.timeout) as sub:
            next_report = loop.time() + 1.0
            received = 0
            while args.count is None or received < args.count:
                try:
                    async with asyncio.timeout_at(next_report):
                        await sub.receive()
                except TimeoutError:
                    _report(arrivals)
                    next_report = loop.time() + 1.0
                    continue
                received += 1
                arrivals.append(loop.time())
                del arrivals[: -args.window - 1]
                if loop.time() >= next_report:
                    _report(arrivals)
                    next_report = loop.time() + 1.0
    _report(arrivals)
    return ExitCode.OK


def _report(arrivals: list[float]) -> None:
    """Print the rate as ``ros2 topic hz`` does, from the arrival times of the window."""
    if len(arrivals) < 2:
        print("no new messages", flush=True)
        return
    gaps = [b - a for a, b in itertools.pairwise(arrivals)]
    mean = sum(gaps) / len(gaps)
    deviation = math.sqrt(sum((g - mean) ** 2 for g in gaps) / len(gaps))
    print(
        f"average rate: {1 / mean if mean else math.inf:.3f}\n"
        f"\tmin: {min(gaps):.3f}s max: {max(gaps):.3f}s std dev: {deviation:.5f}s "
        f"window: {len(arrivals)}",
        flush=True,
    )
