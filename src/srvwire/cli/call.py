"""``srvwire call``: call a service, once or at a rate, and print what was sent and came back.

TYPE and VALUES are both optional; with one of them given, it is TYPE when it reads like a type
name (VALUES never does: a YAML mapping has a colon). The type is TYPE, else the one the server
advertised; when it loads here, the request is checked before it is sent, and both sides print
as ROS 2's Python messages do. Without it, the values go as they are and print as a mapping.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import math
import re
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pydantic
import yaml

from srvwire.calls import validate_request
from srvwire.cli.common import (
    EXIT_CODES_HELP,
    CommandError,
    Commands,
    ExitCode,
    add_command,
    local_options,
    open_client,
    positive_float,
    positive_int,
    remote_options,
)
from srvwire.errors import InvalidParams
from srvwire.loader import InterfaceLoader
from srvwire.models import Service, summarize_errors
from srvwire.protocol import canonical_name

_TYPE_SHAPE = re.compile(r"^\w+/(?:\w+/)?\w+$")

logger = logging.getLogger("srvwire.cli")


def register(commands: Commands) -> None:
    call = add_command(
        commands,
        "call",
        "call a service and print its response",
        "examples:\n"
        "  srvwire call /add_two_ints '{a: 1, b: 2}'\n"
        "  srvwire call /add_two_ints example_interfaces/srv/AddTwoInts '{a: 1, b: 2}'\n"
        "  srvwire call /trigger --json\n"
        "  srvwire call /get_robot_state '{query_type: position}' --rate 2\n"
        "  srvwire call /add_two_ints @request.yaml\n\n"
        "TYPE may be left out when the server advertises the service's type. With only one of\n"
        "TYPE and VALUES given, it is TYPE when it looks like pkg/srv/Name or pkg/Name.\n"
        "VALUES '-' reads the mapping from standard input, and '@FILE' from FILE.\n\n"
        + EXIT_CODES_HELP,
        [remote_options(), local_options()],
    )
    call.add_argument("name", metavar="NAME", help="the service to call, e.g. /add_two_ints")
    call.add_argument(
        "type", metavar="TYPE", nargs="?", help="its type, e.g. example_interfaces/srv/AddTwoInts"
    )
    call.add_argument(
        "values",
        metavar="VALUES",
        nargs="?",
        help="the request as a YAML mapping, e.g. '{a: 1, b: 2}'; '-' reads it from stdin, "
        "'@FILE' from FILE (default: {}, all defaults)",
    )
    call.add_argument(
        "-r",
        "--rate",
        type=positive_float,
        metavar="HZ",
        help="repeat the call HZ times a second, until Ctrl-C or --count calls",
    )
    call.add_argument(
        "-n",
        "--count",
        type=positive_int,
        metavar="N",
        help="make N calls, then stop (default: 1, or unlimited with --rate)",
    )
    call.add_argument(
        "--json",
        action="store_true",
        help="print only each response, as one line of JSON",
    )
    call.set_defaults(command=_cmd_call, late_positionals=("type", "values"))


def _cmd_call(args: argparse.Namespace) -> int:
    type_arg: str | None = args.type
    values_arg: str | None = args.values
    if values_arg is None and type_arg is not None and not _TYPE_SHAPE.match(type_arg):
        type_arg, values_arg = None, type_arg
    values = _parse_values(values_arg)
    if type_arg is not None and "/action/" in type_arg:
        raise CommandError(
            f"{type_arg} is an action type, not a service type: send it a goal with "
            f"srvwire action send_goal {args.name}",
            ExitCode.USAGE,
        )
    # The process's classes: the client types the call's nested messages with them too.
    loader = InterfaceLoader(args.path)
    srv_type = loader.load_service(type_arg) if type_arg is not None else None
    count: int | None = args.count if args.count is not None else None if args.rate else 1
    try:
        return asyncio.run(_call(args, srv_type, values, count))
    except KeyboardInterrupt:
        if args.rate is not None:  # Ctrl-C is how a repeating call is meant to end
            return ExitCode.OK
        raise


def _stdin() -> bytes:
    stdin = sys.stdin
    if stdin is None:
        raise OSError("standard input is closed")
    if stdin.isatty():
        raise OSError("standard input is a terminal; pipe the values in, or give @FILE")
    binary = getattr(stdin, "buffer", None)  # a text stream put in its place has none
    return binary.read() if binary is not None else stdin.read().encode()


def _read_values(source: str, read: Callable[[], bytes]) -> str:
    """Read VALUES from ``source`` as UTF-8 text; a usage error says why it cannot be."""
    try:
        return read().decode("utf-8")
    except OSError as exc:
        reason = exc.strerror or str(exc)
        raise CommandError(f"cannot read VALUES from {source}: {reason}", ExitCode.USAGE) from None
    except UnicodeDecodeError as exc:
        raise CommandError(
            f"cannot read VALUES from {source}: not UTF-8 text ({exc.reason})", ExitCode.USAGE
        ) from None


class _ValuesLoader(yaml.SafeLoader):
    """``yaml.safe_load``'s reading, except that a number with an exponent is a float however
    JSON or YAML 1.2 spell it (``1e3``, ``2E-7``, ``1.0e+16``): YAML 1.1, which PyYAML reads,
    wants a dot and a signed exponent, and reads the others as strings, so pasted JSON (and
    ``--json``'s own output) would not read back."""


_ValuesLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)[eE][-+]?[0-9]+$"),
    list("-+.0123456789"),
)


def _parse_values(text: str | None) -> dict[str, Any]:
    """Read VALUES: a YAML mapping, ``{}`` when left out; ``-`` is stdin and ``@path`` a file."""
    if text is None:
        return {}
    what = "VALUES"
    if text == "-":
        what, text = "VALUES from standard input", _read_values("standard input", _stdin)
    elif text.startswith("@"):
        path = text[1:]
        what, text = f"VALUES in {path}", _read_values(path, Path(path).read_bytes)
    try:
        values = yaml.load(text, _ValuesLoader)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = exc.problem or exc.context or "not valid YAML"
        raise CommandError(f"invalid {what}{where}: {problem}", ExitCode.USAGE) from None
    except yaml.YAMLError as exc:
        raise CommandError(f"invalid {what}: {exc}", ExitCode.USAGE) from None
    if values is None:
        return {}
    if not isinstance(values, dict):
        raise CommandError(
            f"invalid {what}: expected a YAML mapping such as '{{a: 1, b: 2}}', "
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
    async with open_client(args) as client:
        type_name = srv_type.type_name if srv_type is not None else None
        # The server advertised its services' types on connecting; an unknown service is left
        # for the call to report.
        advertised = client.services.get(name)
        if advertised is not None and "/action/" in advertised:
            raise CommandError(
                f"{name} is the action {advertised}, not a service: use srvwire action "
                f"send_goal {name}",
                ExitCode.USAGE,
            )
        if advertised is not None:
            if srv_type is None:
                type_name = advertised
                srv_type = await client.service_type(name, timeout=args.timeout)
            elif advertised != type_name:
                raise CommandError(
                    f"{name} is a service of type {advertised}, not {type_name}", ExitCode.USAGE
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
                print(_json_line(response), flush=True)
            else:
                shown = _ros_repr(response, _part_label(srv_type, type_name, "Response"))
                print(f"\nresponse:\n{shown}", flush=True)
            done += 1
    return ExitCode.OK


def _validate_request(name: str, srv_type: type[Service], values: dict[str, Any]) -> Any:
    """Validate VALUES as the client does, in the command's words."""
    try:
        return validate_request(name, srv_type, values)
    except InvalidParams as exc:
        errors = exc.errors
        count = exc.data.get("error_count") if isinstance(exc.data, dict) else None
        raise InvalidParams(
            f"VALUES do not fit {srv_type.type_name} (checked locally, not sent): "
            f"{summarize_errors(errors, count)}",
            exc.data,
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


def _json_line(value: Any) -> str:
    """``value`` (a model, or a model's ``model_dump(mode="json")``) as one line of standard
    JSON, as ``--json`` prints it. A float that is not finite is written as the string a server
    writes it as by default (``"NaN"``, ``"Infinity"``, ``"-Infinity"``: see Infinity and NaN in
    the types page), never as a bare token, which is not JSON."""
    if isinstance(value, pydantic.BaseModel):
        value = value.model_dump(mode="json", by_alias=True)
    return json.dumps(_finite(value), ensure_ascii=False, allow_nan=False)


def _finite(value: Any) -> Any:
    """``value`` with each float that is not finite replaced by its JSON string."""
    if isinstance(value, float):
        if math.isfinite(value):
            return value
        return "NaN" if math.isnan(value) else ("Infinity" if value > 0 else "-Infinity")
    if isinstance(value, list):
        return [_finite(item) for item in value]
    if isinstance(value, dict):
        return {key: _finite(item) for key, item in value.items()}
    return value
