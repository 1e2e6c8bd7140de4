"""Modules import only from layers below them (docs/design.md); nothing imports the top ones."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import srvwire

PACKAGE = Path(srvwire.__file__).parent

# module -> its layer; a module may import only modules of lower layers
LAYERS: dict[str, int] = {
    "errors": 0,
    "version": 0,
    "inline": 0,
    "threads": 0,
    "heap": 0,
    "idl": 1,
    "scanner": 1,
    "primitives": 1,
    "pysource": 1,
    "protocol": 1,
    "transports.base": 1,
    "parser": 2,
    "models": 2,
    "session": 2,
    "auth": 2,
    "transports.memory": 2,
    "transports.websockets": 2,
    "transports.picows": 2,
    "typeregistry": 2,
    "goals": 2,
    "topics": 2,
    "loader": 3,
    "codegen": 3,
    "dispatch": 3,
    "pubsub": 4,
    "calls": 3,
    "handshake": 3,
    "link": 3,
    "transports": 3,
    "actions": 3,
    "serving": 4,
    "client": 4,
    "server": 5,
    "sync": 5,
    "cli": 6,
    "testing": 6,
    "__init__": 6,
    "__main__": 6,
}
TOP = {"cli", "testing", "__init__", "__main__"}


def module_name(path: Path) -> str:
    """``transports/base.py`` -> ``transports.base``; a package's ``__init__`` -> the package."""
    parts = list(path.relative_to(PACKAGE).with_suffix("").parts)
    if parts[-1] == "__init__" and len(parts) > 1:
        parts.pop()
    return ".".join(parts)


def layer_key(module: str) -> str:
    """The key of ``module`` in LAYERS: every module of the cli package is ``cli``."""
    return "cli" if module == "cli" or module.startswith("cli.") else module


def srvwire_imports(path: Path) -> set[str]:
    """The srvwire modules ``path`` imports, as LAYERS names them."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            parts = node.module.split(".")
            if parts[0] != "srvwire":
                continue
            if len(parts) > 1:
                found.add(".".join(parts[1:]))
            else:  # from srvwire import version
                found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level > 0:
            raise AssertionError(f"{path}: relative import; srvwire imports absolutely")
        elif isinstance(node, ast.Import):
            for alias in node.names:
                parts = alias.name.split(".")
                if parts[0] == "srvwire":
                    found.add(".".join(parts[1:]) if len(parts) > 1 else "__init__")
    return found


MODULES = {module_name(path): path for path in sorted(PACKAGE.rglob("*.py"))}


def test_every_module_has_a_layer() -> None:
    missing = {m for m in MODULES if layer_key(m) not in LAYERS}
    assert not missing, f"give {sorted(missing)} a layer in LAYERS (and in docs/design.md)"


def test_imports_point_down() -> None:
    for module, path in MODULES.items():
        if module == "__main__":
            assert srvwire_imports(path) == {"cli"}
            continue
        own = LAYERS[layer_key(module)]
        for imported in srvwire_imports(path):
            key = layer_key(imported)
            if module.startswith("cli") and key == "cli":
                continue  # the command line's own modules
            assert key not in TOP, f"{module} imports {imported}"
            assert LAYERS[key] < own, f"{module} (layer {own}) imports {imported} ({LAYERS[key]})"


def test_the_asyncio_shells_never_import_each_other() -> None:
    assert "client" not in srvwire_imports(MODULES["server"])
    assert "server" not in srvwire_imports(MODULES["client"])
    assert "server" not in srvwire_imports(MODULES["sync"])
    assert "sync" not in srvwire_imports(MODULES["server"])


def test_the_layer_table_in_the_design_page_agrees() -> None:
    design = (PACKAGE.parents[1] / "docs" / "design.md").read_text(encoding="utf-8")
    for module, layer in LAYERS.items():
        if module in {"__main__"}:
            continue
        shown = f"`{module.replace('.', '/')}`"
        rows = [line for line in design.splitlines() if line.startswith(f"| {layer} |")]
        assert any(shown in row for row in rows), f"docs/design.md: {module} in layer {layer}"


# What another module may take from a websocket library: the native transport masks the client
# frames it writes together with websockets' C masking, as websockets' own frames are masked.
BORROWED = {("transports.picows", "websockets.speedups"), ("transports.picows", "websockets.utils")}


@pytest.mark.parametrize(
    ("library", "owner"),
    [("websockets", "transports.websockets"), ("picows", "transports.picows")],
)
def test_only_its_transport_imports_a_websocket_library(library: str, owner: str) -> None:
    for module, path in MODULES.items():
        if module == owner:
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            names = (
                [alias.name for alias in node.names]
                if isinstance(node, ast.Import)
                else [node.module or ""]
                if isinstance(node, ast.ImportFrom)
                else []
            )
            assert all(
                name.split(".")[0] != library or (module, name) in BORROWED for name in names
            ), module


def test_the_native_transport_borrows_only_websockets_masking() -> None:
    tree = ast.parse(MODULES["transports.picows"].read_text(encoding="utf-8"))
    borrowed = [
        (node.module, [alias.name for alias in node.names])
        for node in ast.walk(tree)
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("websockets")
    ]
    assert borrowed == [
        ("websockets.speedups", ["apply_mask"]),
        ("websockets.utils", ["apply_mask"]),
    ]
