"""``srvwire gen``: write a typed Python module for interface packages or single types.

Each PACKAGE names a package, or one type when it holds a slash (``std_srvs/srv/Trigger``). An
``--output`` ending in ``.py`` gets everything; any other is a folder with one module per package.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from srvwire.cli.common import (
    CommandError,
    Commands,
    ExitCode,
    add_command,
    interface_loader,
    local_options,
    plural,
)
from srvwire.codegen import generate_module
from srvwire.idl import MessageSpec, TypeSpec


def register(commands: Commands) -> None:
    gen = add_command(
        commands,
        "gen",
        "generate a typed Python module from interface packages",
        "examples:\n"
        "  srvwire gen std_srvs example_interfaces -o my_app/interfaces.py\n"
        "  srvwire gen my_pkg --path ./interfaces -o generated/",
        [local_options()],
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


def _cmd_gen(args: argparse.Namespace) -> int:
    loader = interface_loader(args)
    output: Path = args.output
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
        source = generate_module([loader.spec(name) for name in names], resolve_spec=resolve)
        try:
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_text(source, encoding="utf-8")
        except OSError as exc:
            raise CommandError(f"cannot write {target}: {exc.strerror or exc}") from None
        print(f"wrote {target} ({plural(len(names), 'interface')})")
    return ExitCode.OK
