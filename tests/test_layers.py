"""Modules import only from layers below them (DESIGN §2); nothing imports cli or __init__."""

from __future__ import annotations

import ast
from pathlib import Path

import srvwire

PACKAGE = Path(srvwire.__file__).parent

# module -> the srvwire modules it may import
ALLOWED: dict[str, set[str]] = {
    "version": set(),
    "inline": set(),
    "errors": set(),
    "idl": {"errors"},
    "protocol": {"errors"},
    "parser": {"idl", "errors"},
    "models": {"idl", "errors"},
    "loader": {"parser", "models", "idl", "errors"},
    "codegen": {"loader", "parser", "models", "idl", "errors"},
    "dispatch": {"protocol", "models", "idl", "errors", "version", "inline"},
    "server": {"dispatch", "protocol", "models", "idl", "errors", "inline"},
    "client": {"protocol", "models", "loader", "idl", "errors", "inline"},
}
TOP = {"cli", "__init__", "__main__"}


def srvwire_imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            parts = node.module.split(".")
            if parts[0] == "srvwire":
                if len(parts) > 1:
                    found.add(parts[1])
                else:
                    found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level > 0:
            found.add((node.module or "__init__").split(".")[0])
        elif isinstance(node, ast.Import):
            for alias in node.names:
                parts = alias.name.split(".")
                if parts[0] == "srvwire":
                    found.add(parts[1] if len(parts) > 1 else "__init__")
    return found


def test_every_module_has_a_layer() -> None:
    modules = {p.stem for p in PACKAGE.glob("*.py")}
    assert modules - TOP <= set(ALLOWED), "add the new module to ALLOWED with its layer"


def test_imports_point_down() -> None:
    for path in sorted(PACKAGE.glob("*.py")):
        module = path.stem
        imported = srvwire_imports(path)
        if module in TOP:
            assert "cli" not in imported or module == "__main__", module
            continue
        unexpected = imported - ALLOWED[module]
        assert not unexpected, f"{module} imports {sorted(unexpected)} from a layer above it"
