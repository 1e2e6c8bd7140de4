"""``srvwire action``: list a server's actions, and send one a goal, as ``ros2 action`` does.

``send_goal`` prints the goal, its acceptance, each feedback with ``--feedback`` (the latest,
when they come faster than the terminal takes them), the result and the final status, in
YAML; its exit code says how the goal ended (:data:`~srvwire.cli.common.GOAL_EXIT_CODES`).
"""

from __future__ import annotations

import argparse
import asyncio
from typing import Any

import pydantic
import yaml

from srvwire.actions import ClientGoal, GoalResult
from srvwire.cli.call import _TYPE_SHAPE, _parse_values
from srvwire.cli.common import (
    EXIT_CODES_HELP,
    GOAL_EXIT_CODES,
    CommandError,
    Commands,
    ExitCode,
    add_command,
    local_options,
    open_client,
    remote_options,
)
from srvwire.client import ServiceInfo
from srvwire.dispatch import service_not_found
from srvwire.loader import InterfaceLoader
from srvwire.models import Action
from srvwire.protocol import canonical_name


def register(commands: Commands) -> None:
    action = add_command(
        commands,
        "action",
        "ask a running server about its actions, and send them goals",
        "examples:\n"
        "  srvwire action list -t\n"
        "  srvwire action info /fibonacci\n"
        "  srvwire action send_goal /fibonacci '{order: 5}' --feedback",
    )
    verbs = action.add_subparsers(title="subcommands", metavar="SUBCOMMAND", required=True)
    remote = remote_options()

    listing = add_command(
        verbs,
        "list",
        "list the actions the server offers",
        "example:\n  srvwire action list -t",
        [remote],
    )
    listing.add_argument(
        "-t", "--show-types", action="store_true", help="add each action's type in brackets"
    )
    listing.add_argument(
        "-c", "--count-actions", action="store_true", help="print only the number of actions"
    )
    listing.set_defaults(command=_cmd_action_list)

    info = add_command(
        verbs,
        "info",
        "print an action's type and its definition, as the server describes it",
        "example:\n  srvwire action info /fibonacci",
        [remote],
    )
    info.add_argument("name", metavar="NAME", help="the action, e.g. /fibonacci")
    info.set_defaults(command=_cmd_action_info)

    send = add_command(
        verbs,
        "send_goal",
        "send a goal to an action, and print its result",
        "examples:\n"
        "  srvwire action send_goal /fibonacci '{order: 5}'\n"
        "  srvwire action send_goal /fibonacci example_interfaces/action/Fibonacci "
        "'{order: 5}' --feedback\n\n"
        "TYPE may be left out when the server advertises the action's type. --timeout bounds\n"
        "the whole goal, until its result. Ctrl-C asks the server to cancel the goal and\n"
        "waits for its outcome (exit 130); a second Ctrl-C stops waiting.\n\n"
        "A goal that ends canceled exits with 8, aborted or rejected with 7.\n\n" + EXIT_CODES_HELP,
        [remote, local_options()],
    )
    send.add_argument("name", metavar="NAME", help="the action, e.g. /fibonacci")
    send.add_argument(
        "type", metavar="TYPE", nargs="?", help="its type, e.g. example_interfaces/action/Fibonacci"
    )
    send.add_argument(
        "values",
        metavar="VALUES",
        nargs="?",
        help="the goal as a YAML mapping, e.g. '{order: 5}'; '-' reads it from stdin, "
        "'@FILE' from FILE (default: {}, all defaults)",
    )
    send.add_argument(
        "-f", "--feedback", action="store_true", help="print the goal's feedback as it comes"
    )
    send.set_defaults(command=_cmd_send_goal, late_positionals=("type", "values"))


async def _actions(args: argparse.Namespace) -> tuple[list[ServiceInfo], dict[str, str], str]:
    async with open_client(args) as client:
        listed = await client.list_actions(timeout=args.timeout)
        texts = await client.definitions(timeout=args.timeout)
        return listed, texts, client.url


def _cmd_action_list(args: argparse.Namespace) -> int:
    actions, _, _ = asyncio.run(_actions(args))
    if args.count_actions:
        print(len(actions))
        return ExitCode.OK
    for info in actions:
        print(f"{info.name} [{info.type}]" if args.show_types else info.name)
    return ExitCode.OK


def _cmd_action_info(args: argparse.Namespace) -> int:
    name = canonical_name(args.name)
    actions, texts, _ = asyncio.run(_actions(args))
    for info in actions:
        if info.name == name:
            print(f"Action: {info.name}")
            print(f"Type: {info.type}")
            text = texts.get(info.type)
            if text is not None:
                print()
                print(text.rstrip("\n"))
            return ExitCode.OK
    raise service_not_found(name, (info.name for info in actions))


def _cmd_send_goal(args: argparse.Namespace) -> int:
    type_arg: str | None = args.type
    values_arg: str | None = args.values
    if values_arg is None and type_arg is not None and not _TYPE_SHAPE.match(type_arg):
        type_arg, values_arg = None, type_arg
    values = _parse_values(values_arg)
    action = InterfaceLoader(args.path).load_action(type_arg) if type_arg is not None else None
    return asyncio.run(_send_goal(args, action, values))


def _yaml(value: Any) -> str:
    if isinstance(value, pydantic.BaseModel):
        value = value.model_dump(mode="json", by_alias=True)
    text = yaml.safe_dump(value, default_flow_style=False, sort_keys=False, allow_unicode=True)
    return "\n".join(f"    {line}" for line in text.rstrip("\n").splitlines())


async def _send_goal(
    args: argparse.Namespace, action: type[Action] | None, values: dict[str, Any]
) -> int:
    name = canonical_name(args.name)
    async with open_client(args) as client:
        advertised = client.services.get(name)
        if action is not None and advertised is not None and advertised != action.type_name:
            raise CommandError(
                f"{name} is an action of type {advertised}, not {action.type_name}", ExitCode.USAGE
            )
        if advertised is not None and "/action/" not in advertised:
            raise CommandError(
                f"{name} is the service {advertised}, not an action: use srvwire call",
                ExitCode.USAGE,
            )
        # Said once the goal got past the client's own checks (a known action, values that fit
        # its Goal), which send nothing when they fail, and the server accepted it.
        handle = await client.send_goal(name, values, timeout=args.timeout, action_type=action)
        print("Sending goal:")
        print(_yaml(values or {}))
        print(f"\nGoal accepted with ID: {handle.goal_id}", flush=True)
        try:
            if args.feedback:
                async for feedback in handle.feedback():
                    print(f"\nFeedback:\n{_yaml(feedback)}", flush=True)
            outcome = await handle.result()
        except asyncio.CancelledError:
            task = asyncio.current_task()
            if task is None or task.uncancel() > 0:
                raise  # cancelled by something other than asyncio.run's first Ctrl-C
            outcome = await _cancel_on_interrupt(handle)
            _print_outcome(outcome)
            return ExitCode.INTERRUPTED
        _print_outcome(outcome)
        return GOAL_EXIT_CODES[outcome.status]


async def _cancel_on_interrupt(handle: ClientGoal[Any]) -> GoalResult[Any]:
    """After a first Ctrl-C: ask the server to cancel the goal, and wait for its outcome.

    The wait ends with the outcome the handler chose (``canceled``, or what it reached first),
    with the goal's deadline (``DeadlineExceeded``), or at a second Ctrl-C, which
    :func:`asyncio.run` raises as ``KeyboardInterrupt``; leaving then closes the connection,
    which stops the handler at once.
    """
    print("\nCanceling goal (Ctrl-C again to stop waiting)...", flush=True)
    await handle.cancel()
    return await handle.result()


def _print_outcome(outcome: GoalResult[Any]) -> None:
    print(f"\nResult:\n{_yaml(outcome.result)}")
    print(f"\nGoal finished with status: {outcome.status.upper()}", flush=True)
