"""The interface loader: search path, overlays, names, errors, laziness, caching, nesting."""

from __future__ import annotations

import errno
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

import srvwire.loader as loader_module
from srvwire import parser
from srvwire.cli import main
from srvwire.errors import (
    InterfaceConflictError,
    InterfaceError,
    InterfaceNotFoundError,
    InterfaceSyntaxError,
)
from srvwire.idl import ActionSpec, InterfaceKind, MessageSpec, ServiceSpec
from srvwire.loader import (
    ENV_VAR,
    InterfaceLoader,
    bundled_interfaces,
    default_search_path,
    load_action,
    load_message,
    load_service,
)
from srvwire.typeregistry import TypeRegistry
from support import ROOT

Spec = MessageSpec | ServiceSpec | ActionSpec

POSE2D = "float64 x\nfloat64 y\nfloat64 theta 0.5\n"
MOVE = "demo/Pose2D target\n---\nbool ok\n"
GO = "Pose2D target\n---\nbool reached\n---\nfloat64 remaining\n"


def write(root: Path, relative: str, text: str | bytes) -> Path:
    """Write one interface file under ``root``, creating its folders."""
    path = root / relative
    path.parent.mkdir(parents=True, exist_ok=True)
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text, encoding="utf-8")
    return path


def attribute(instance: object, name: str) -> Any:
    return getattr(instance, name)


def dump(instance: Any) -> dict[str, Any]:
    data: dict[str, Any] = instance.model_dump()
    return data


@pytest.fixture(autouse=True)
def own_types(monkeypatch: pytest.MonkeyPatch) -> TypeRegistry:
    """The classes of one test: its ``demo`` package differs from the next test's."""
    types = TypeRegistry()
    monkeypatch.setattr(loader_module, "process_types", lambda: types)
    loader_module._shared_loader.cache_clear()
    return types


@pytest.fixture
def root(tmp_path: Path) -> Path:
    """A search-path folder holding the package ``demo``."""
    folder = tmp_path / "root"
    write(folder, "demo/msg/Pose2D.msg", POSE2D)
    write(folder, "demo/msg/Thing.msg", "int32 a\n")
    write(folder, "demo/srv/Thing.srv", "int32 a\n---\nint32 b\n")
    write(folder, "demo/srv/Move.srv", MOVE)
    write(folder, "demo/action/Go.action", GO)
    return folder


@pytest.fixture
def loader(root: Path) -> InterfaceLoader:
    return InterfaceLoader([root], use_default_path=False)


def message_of(excinfo: pytest.ExceptionInfo[BaseException]) -> str:
    return str(excinfo.value)


# --- the search path ------------------------------------------------------------------------


def test_bundled_interfaces_holds_the_standard_packages() -> None:
    folder = bundled_interfaces()
    assert folder in (ROOT / "interfaces", Path(loader_module.__file__).parent / "interfaces")
    assert (folder / "std_srvs" / "srv" / "Trigger.srv").is_file()


@pytest.mark.parametrize("installed", [True, False])
def test_bundled_interfaces_prefers_the_wheel_copy(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, installed: bool
) -> None:
    module = tmp_path / "src" / "srvwire" / "loader.py"
    write(tmp_path, "src/srvwire/loader.py", "")
    (tmp_path / "interfaces").mkdir()
    if installed:
        (module.parent / "interfaces").mkdir()
    monkeypatch.setattr(loader_module, "__file__", str(module))
    expected = module.parent / "interfaces" if installed else tmp_path / "interfaces"
    assert bundled_interfaces() == expected


def test_bundled_interfaces_without_any_copy(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    module = write(tmp_path, "src/srvwire/loader.py", "")
    monkeypatch.setattr(loader_module, "__file__", str(module))
    assert bundled_interfaces() == module.parent / "interfaces"
    assert InterfaceLoader([bundled_interfaces()], use_default_path=False).packages() == {}


def test_default_search_path_without_the_variable(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(ENV_VAR, raising=False)
    assert default_search_path() == [bundled_interfaces()]


def test_default_search_path_reads_the_variable_in_order(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    first, second = tmp_path / "first", tmp_path / "second"
    monkeypatch.setenv(ENV_VAR, os.pathsep.join(["", str(first), "", str(second), ""]))
    assert default_search_path() == [first, second, bundled_interfaces()]


def test_a_loader_takes_the_default_search_path_when_created(
    root: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv(ENV_VAR, str(root))
    loader = InterfaceLoader()
    monkeypatch.delenv(ENV_VAR)
    assert loader.search_path == (root, bundled_interfaces())
    assert loader.packages()["demo"] == root / "demo"
    assert "std_srvs" in loader.packages()


def test_search_path_entries_become_absolute_paths(
    root: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(root.parent)
    loader = InterfaceLoader(["root", root / "missing"], use_default_path=False)
    assert loader.search_path == (root, root / "missing")
    assert repr(loader) == f"InterfaceLoader([{root}, {root / 'missing'}])"


def test_a_lone_path_is_one_folder(root: Path) -> None:
    assert InterfaceLoader(str(root), use_default_path=False).search_path == (root,)


# --- packages and types ---------------------------------------------------------------------


def test_packages_are_folders_with_interface_subfolders(root: Path, tmp_path: Path) -> None:
    write(root, "docs/README.md", "not a package\n")
    write(root, ".hidden/msg/Secret.msg", "int32 a\n")
    write(root, "only_actions/action/Spin.action", "---\n---\n")
    write(root, "stray.msg", "int32 a\n")
    (root / "empty_pkg" / "msg").mkdir(parents=True)
    loader = InterfaceLoader(
        [tmp_path / "missing", root, root / "stray.msg"], use_default_path=False
    )
    assert loader.packages() == {
        "demo": root / "demo",
        "empty_pkg": root / "empty_pkg",
        "only_actions": root / "only_actions",
    }
    assert loader.types("empty_pkg") == []


def test_earlier_folders_overlay_later_ones_package_by_package(root: Path, tmp_path: Path) -> None:
    overlay = tmp_path / "overlay"
    write(overlay, "demo/msg/Pose2D.msg", "int32 overlaid\n")
    write(overlay, "extra/msg/Extra.msg", "int32 a\n")
    loader = InterfaceLoader([overlay, root], use_default_path=False)
    assert loader.packages() == {
        "demo": overlay / "demo",
        "extra": overlay / "extra",
    }
    # The overlay's demo hides the underlay's as a whole: no file of the underlay shows through.
    assert loader.types("demo") == ["demo/msg/Pose2D"]
    assert dump(loader.load_message("demo/Pose2D")()) == {"overlaid": 0}
    assert InterfaceLoader([root, overlay], use_default_path=False).types("demo") == [
        "demo/action/Go",
        "demo/msg/Pose2D",
        "demo/msg/Thing",
        "demo/srv/Move",
        "demo/srv/Thing",
    ]


def test_only_names_that_can_load_are_listed(
    root: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # A file or folder whose name the interface language refuses can never load, whatever it
    # holds: it is not listed. A valid name whose text is wrong is: loading it says what.
    write(root, "demo/msg/lower.msg", "int32 a\n")
    write(root, "demo/srv/Broken.srv", "int32 a\n")
    write(root, "Bad-Name/msg/X.msg", "int32 a\n")
    write(root, "bad_/msg/Z.msg", "int32 a\n")
    loader = InterfaceLoader([root], use_default_path=False, types=TypeRegistry())
    assert list(loader.packages()) == ["demo"]
    assert (
        loader.types()
        == loader.types("demo")
        == [
            "demo/action/Go",
            "demo/msg/Pose2D",
            "demo/msg/Thing",
            "demo/srv/Broken",
            "demo/srv/Move",
            "demo/srv/Thing",
        ]
    )
    assert loader.types("bad_") == []
    with pytest.raises(InterfaceSyntaxError, match="'Bad-Name' is an invalid package name"):
        loader.load("Bad-Name/msg/X")
    with pytest.raises(InterfaceSyntaxError, match="'lower' is an invalid message name"):
        loader.load("demo/msg/lower")
    assert main(["interface", "list", "--path", str(root)]) == 0
    listed = capsys.readouterr().out.split()
    assert "demo/srv/Broken" in listed
    assert not {"demo/msg/lower", "Bad-Name/msg/X", "bad_/msg/Z"} & set(listed)


def test_types_lists_full_names_sorted(loader: InterfaceLoader, root: Path) -> None:
    write(root, "another/srv/Zed.srv", "---\n")
    write(root, "another/msg/Alpha.msg", "")
    loader = InterfaceLoader([root], use_default_path=False)
    assert loader.types("another") == ["another/msg/Alpha", "another/srv/Zed"]
    assert loader.types() == [
        "another/msg/Alpha",
        "another/srv/Zed",
        "demo/action/Go",
        "demo/msg/Pose2D",
        "demo/msg/Thing",
        "demo/srv/Move",
        "demo/srv/Thing",
    ]


def test_path_of(loader: InterfaceLoader, root: Path) -> None:
    assert loader.path_of("demo/msg/Pose2D") == root / "demo" / "msg" / "Pose2D.msg"
    assert loader.path_of("demo/Move") == root / "demo" / "srv" / "Move.srv"
    assert loader.path_of("demo/Go") == root / "demo" / "action" / "Go.action"


# --- names ----------------------------------------------------------------------------------


def test_full_and_short_names(loader: InterfaceLoader) -> None:
    assert loader.resolve_name("demo/msg/Pose2D") == "demo/msg/Pose2D"
    assert loader.resolve_name("demo/Pose2D") == "demo/msg/Pose2D"
    assert loader.resolve_name("demo/Move") == "demo/srv/Move"
    assert loader.resolve_name("demo/Go", InterfaceKind.ACTION) == "demo/action/Go"
    assert loader.resolve_name("demo/Thing", InterfaceKind.MSG) == "demo/msg/Thing"
    assert loader.resolve_name("demo/Thing", InterfaceKind.SRV) == "demo/srv/Thing"


def test_a_short_name_shared_by_two_kinds_is_ambiguous(loader: InterfaceLoader) -> None:
    with pytest.raises(InterfaceError) as excinfo:
        loader.resolve_name("demo/Thing")
    assert message_of(excinfo) == (
        "ambiguous interface name 'demo/Thing': it could be demo/msg/Thing or demo/srv/Thing; "
        "write the full name"
    )
    with pytest.raises(InterfaceError) as excinfo:
        loader.load("demo/Thing")
    assert "ambiguous" in message_of(excinfo)
    # Asked for by kind, the short name is not ambiguous.
    assert loader.load_message("demo/Thing") is loader.load_message("demo/msg/Thing")
    assert loader.load_service("demo/Thing") is loader.load_service("demo/srv/Thing")


@pytest.mark.parametrize(
    ("name", "message"),
    [
        ("foo", "'foo'"),
        ("a/b/c/d", "'a/b/c/d'"),
        ("demo//Pose2D", "'demo//Pose2D'"),
        ("/demo/Pose2D", "'/demo/Pose2D'"),
        ("demo/", "'demo/'"),
        ("", "''"),
    ],
)
def test_malformed_names(loader: InterfaceLoader, name: str, message: str) -> None:
    with pytest.raises(InterfaceError) as excinfo:
        loader.resolve_name(name)
    assert type(excinfo.value) is InterfaceError
    assert message_of(excinfo) == (
        f"malformed interface name {message}: "
        "expected 'package/kind/Name' (kind: msg, srv or action) or 'package/Name'"
    )


def test_an_unknown_kind_is_malformed(loader: InterfaceLoader) -> None:
    with pytest.raises(InterfaceError) as excinfo:
        loader.resolve_name("demo/msgs/Pose2D")
    assert message_of(excinfo) == (
        "malformed interface name 'demo/msgs/Pose2D': "
        "the kind 'msgs' is not one of msg, srv, action"
    )


@pytest.mark.parametrize(
    ("call", "name", "message"),
    [
        ("load_service", "demo/msg/Pose2D", "'demo/msg/Pose2D' names a message, not a service"),
        ("load_service", "demo/Pose2D", "'demo/Pose2D' names a message, not a service"),
        ("load_message", "demo/srv/Move", "'demo/srv/Move' names a service, not a message"),
        ("load_message", "demo/Go", "'demo/Go' names an action, not a message"),
        ("load_action", "demo/Move", "'demo/Move' names a service, not an action"),
        # The kind written in the name is checked before the type is looked for.
        (
            "load_action",
            "nowhere/srv/Nothing",
            "'nowhere/srv/Nothing' names a service, not an action",
        ),
    ],
)
def test_asking_for_the_wrong_kind(
    loader: InterfaceLoader, call: str, name: str, message: str
) -> None:
    with pytest.raises(InterfaceError) as excinfo:
        getattr(loader, call)(name)
    assert type(excinfo.value) is InterfaceError
    assert message_of(excinfo) == message


def test_an_unknown_package_lists_close_package_names(root: Path) -> None:
    write(root, "demo_extra/msg/X.msg", "")
    write(root, "unrelated/msg/X.msg", "")
    loader = InterfaceLoader([root, root / "second"], use_default_path=False)
    with pytest.raises(InterfaceNotFoundError) as excinfo:
        loader.load_message("demo_ex/Pose2D")
    error = excinfo.value
    assert error.name == "demo_ex/Pose2D"
    assert error.candidates == ("demo_extra", "demo")
    assert message_of(excinfo) == (
        f"no interface package 'demo_ex' in {root}{os.pathsep}{root / 'second'} "
        "(did you mean: demo_extra, demo?)"
    )
    assert isinstance(error, LookupError)


def test_an_unknown_package_with_nothing_close(loader: InterfaceLoader, root: Path) -> None:
    with pytest.raises(InterfaceNotFoundError) as excinfo:
        loader.types("zzz")
    assert message_of(excinfo) == f"no interface package 'zzz' in {root}"
    assert excinfo.value.candidates == ()


def test_an_empty_search_path_says_so() -> None:
    with pytest.raises(InterfaceNotFoundError) as excinfo:
        InterfaceLoader([], use_default_path=False).load_service("std_srvs/Trigger")
    assert message_of(excinfo) == "no interface package 'std_srvs': the search path is empty"


@pytest.mark.parametrize(
    ("call", "name", "message"),
    [
        (
            "load_message",
            "demo/Pose2d",
            "no message 'Pose2d' in package 'demo' (did you mean: demo/msg/Pose2D?)",
        ),
        (
            "load_message",
            "demo/msg/Pose3D",
            "no message 'Pose3D' in package 'demo' (did you mean: demo/msg/Pose2D?)",
        ),
        (
            "load_service",
            "demo/Mve",
            "no service 'Mve' in package 'demo' (did you mean: demo/srv/Move?)",
        ),
        (
            "load_action",
            "demo/Goo",
            "no action 'Goo' in package 'demo' (did you mean: demo/action/Go?)",
        ),
        (
            "load",
            "demo/Thin",
            "no interface 'Thin' in package 'demo' (did you mean: demo/msg/Thing, demo/srv/Thing?)",
        ),
        ("load", "demo/Unrelated", "no interface 'Unrelated' in package 'demo'"),
    ],
)
def test_an_unknown_type_lists_close_type_names(
    loader: InterfaceLoader, call: str, name: str, message: str
) -> None:
    with pytest.raises(InterfaceNotFoundError) as excinfo:
        getattr(loader, call)(name)
    assert excinfo.value.name == name
    assert message_of(excinfo) == message


def test_an_unknown_type_suggests_the_same_name_in_other_packages(root: Path) -> None:
    write(root, "geometry/msg/Pose2D.msg", POSE2D)
    write(root, "nav/msg/Pose2DStamped.msg", "Pose2D pose\n")
    write(root, "nav/srv/Pose2D.srv", "---\n")
    loader = InterfaceLoader([root], use_default_path=False)
    with pytest.raises(InterfaceNotFoundError) as excinfo:
        loader.load_message("nav/msg/Pose2D")
    # Close names in the package first, then the very name in other packages.
    assert excinfo.value.candidates == (
        "nav/msg/Pose2DStamped",
        "demo/msg/Pose2D",
        "geometry/msg/Pose2D",
    )
    write(root, "bare/msg/Other.msg", "")
    loader = InterfaceLoader([root], use_default_path=False)
    with pytest.raises(InterfaceNotFoundError) as excinfo:
        loader.load_message("bare/Pose2D")
    assert message_of(excinfo) == (
        "no message 'Pose2D' in package 'bare' "
        "(did you mean: demo/msg/Pose2D, geometry/msg/Pose2D?)"
    )


# --- files that cannot be used --------------------------------------------------------------


def test_a_parse_error_names_the_file(loader: InterfaceLoader, root: Path) -> None:
    path = write(root, "demo/msg/Broken.msg", "int32 fine\nint32\n")
    with pytest.raises(InterfaceSyntaxError) as excinfo:
        loader.load_message("demo/Broken")
    assert excinfo.value.path == str(path)
    assert excinfo.value.line == 2
    assert message_of(excinfo).startswith(f"{path}:2:")


def test_a_file_name_that_is_not_a_type_name(root: Path) -> None:
    path = write(root, "demo/msg/lower_case.msg", "int32 a\n")
    loader = InterfaceLoader([root], use_default_path=False)
    assert "demo/msg/lower_case" not in loader.types("demo")  # it can never load
    with pytest.raises(InterfaceSyntaxError) as excinfo:
        loader.load_message("demo/lower_case")
    assert excinfo.value.path == str(path)
    assert "'lower_case'" in excinfo.value.message


def test_a_folder_name_that_is_not_a_package_name(root: Path) -> None:
    path = write(root, "Demo-Pkg/msg/Thing.msg", "int32 a\n")
    loader = InterfaceLoader([root], use_default_path=False)
    assert "Demo-Pkg" not in loader.packages()  # its types can never load
    with pytest.raises(InterfaceSyntaxError) as excinfo:
        loader.load_message("Demo-Pkg/Thing")
    assert excinfo.value.path == str(path)
    assert "'Demo-Pkg'" in excinfo.value.message


def test_a_file_that_is_not_utf8(loader: InterfaceLoader, root: Path) -> None:
    path = write(root, "demo/msg/Latin.msg", b'int8 a\nstring s "caf\xe9"\n')
    with pytest.raises(InterfaceSyntaxError) as excinfo:
        loader.load_message("demo/Latin")
    assert (excinfo.value.path, excinfo.value.line, excinfo.value.column) == (str(path), 2, 14)


def test_only_files_are_types(loader: InterfaceLoader, root: Path) -> None:
    (root / "demo" / "msg" / "Folder.msg").mkdir()
    assert "demo/msg/Folder" not in loader.types("demo")


def test_a_file_that_cannot_be_read(loader: InterfaceLoader, root: Path) -> None:
    gone = write(root, "demo/msg/Gone.msg", "int32 a\n")
    assert "demo/msg/Gone" in loader.types("demo")
    gone.unlink()  # after the listing, so the loader still believes in it
    with pytest.raises(InterfaceError) as excinfo:
        loader.load_message("demo/Gone")
    assert type(excinfo.value) is InterfaceError
    assert message_of(excinfo) == f"{gone}: cannot read the file: {os.strerror(errno.ENOENT)}"
    assert isinstance(excinfo.value.__cause__, FileNotFoundError)


# --- nested types ---------------------------------------------------------------------------


def test_nested_types_resolve_across_packages(root: Path) -> None:
    write(root, "robot/msg/Waypoint.msg", "demo/Pose2D pose\nLabel label\nLabel[] more\n")
    write(root, "robot/msg/Label.msg", 'string text "here"\n')
    write(root, "robot/srv/Visit.srv", "Waypoint[<=4] route\n---\ndemo/Pose2D reached\n")
    loader = InterfaceLoader([root], use_default_path=False)
    waypoint = loader.load_message("robot/Waypoint")
    assert dump(waypoint()) == {
        "pose": {"x": 0.0, "y": 0.0, "theta": 0.5},
        "label": {"text": "here"},
        "more": [],
    }
    instance = waypoint()
    assert isinstance(attribute(instance, "pose"), loader.load_message("demo/msg/Pose2D"))
    assert isinstance(attribute(instance, "label"), loader.load_message("robot/Label"))
    visit = loader.load_service("robot/Visit")
    assert dump(visit.Response()) == {"reached": {"x": 0.0, "y": 0.0, "theta": 0.5}}
    assert dump(visit.Request.model_validate({"route": [{"label": {"text": "a"}}]})) == {
        "route": [{"pose": {"x": 0.0, "y": 0.0, "theta": 0.5}, "label": {"text": "a"}, "more": []}]
    }


def test_nested_types_resolve_into_the_bundled_packages(root: Path) -> None:
    write(root, "robot/srv/Place.srv", "geometry_msgs/Pose pose\nstd_msgs/Header header\n---\n")
    loader = InterfaceLoader([root, bundled_interfaces()], use_default_path=False)
    request = dump(loader.load_service("robot/Place").Request())
    assert request == {
        "pose": {
            "position": {"x": 0.0, "y": 0.0, "z": 0.0},
            "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
        },
        "header": {"stamp": {"sec": 0, "nanosec": 0}, "frame_id": ""},
    }


def test_actions_load_with_nested_types(loader: InterfaceLoader) -> None:
    go = loader.load_action("demo/Go")
    assert go is loader.load("demo/action/Go")
    assert go.type_name == "demo/action/Go"


def test_a_missing_nested_type_points_at_the_field(loader: InterfaceLoader, root: Path) -> None:
    path = write(root, "demo/msg/Route.msg", "# a route\nint32 n\n  Nope[] stops\n")
    with pytest.raises(InterfaceSyntaxError) as excinfo:
        loader.load_message("demo/Route")
    assert message_of(excinfo) == (
        f"{path}:3:3: unknown type 'demo/Nope' of field 'stops': "
        "no message 'Nope' in package 'demo'"
    )
    assert isinstance(excinfo.value.__cause__, InterfaceNotFoundError)


def test_a_nested_type_in_a_missing_package(loader: InterfaceLoader, root: Path) -> None:
    path = write(root, "demo/srv/Far.srv", "int32 a\n---\nint32 b\ndemo_msgs/Pose2D pose\n")
    with pytest.raises(InterfaceSyntaxError) as excinfo:
        loader.load_service("demo/Far")
    assert message_of(excinfo) == (
        f"{path}:4:1: unknown type 'demo_msgs/Pose2D' of field 'pose': "
        f"no interface package 'demo_msgs' in {root} (did you mean: demo?)"
    )


def test_a_missing_type_nested_two_levels_down_points_at_its_own_file(
    loader: InterfaceLoader, root: Path
) -> None:
    write(root, "demo/msg/Outer.msg", "Inner inner\n")
    inner = write(root, "demo/msg/Inner.msg", "int32 a\ndemo/Pose2d pose\n")
    with pytest.raises(InterfaceSyntaxError) as excinfo:
        loader.load_message("demo/Outer")
    assert message_of(excinfo) == (
        f"{inner}:2:1: unknown type 'demo/Pose2d' of field 'pose': "
        "no message 'Pose2d' in package 'demo' (did you mean: demo/msg/Pose2D?)"
    )


def test_a_message_that_contains_itself(loader: InterfaceLoader, root: Path) -> None:
    path = write(root, "demo/msg/Tree.msg", "int32 value\nTree[] children\n")
    with pytest.raises(InterfaceSyntaxError) as excinfo:
        loader.load_message("demo/Tree")
    assert message_of(excinfo) == (
        f"{path}:2:1: field 'children' makes a message contain itself "
        "(demo/msg/Tree -> demo/msg/Tree); "
        "a message cannot nest itself, directly or through other messages"
    )


def test_a_cycle_across_packages(root: Path) -> None:
    write(root, "left/msg/A.msg", "right/B b\n")
    write(root, "right/msg/B.msg", "int8 pad\nright/C c\n")
    closing = write(root, "right/msg/C.msg", "# back to the start\nleft/A[<=2] a\n")
    write(root, "right/srv/UsesA.srv", "---\nleft/A a\n")
    loader = InterfaceLoader([root], use_default_path=False)
    with pytest.raises(InterfaceSyntaxError) as excinfo:
        loader.load_message("left/A")
    assert message_of(excinfo) == (
        f"{closing}:2:1: field 'a' makes a message contain itself "
        "(left/msg/A -> right/msg/B -> right/msg/C -> left/msg/A); "
        "a message cannot nest itself, directly or through other messages"
    )
    # Entered from the middle, the cycle is reported from there.
    with pytest.raises(InterfaceSyntaxError) as excinfo:
        loader.load_message("right/B")
    assert message_of(excinfo) == (
        f"{root / 'left' / 'msg' / 'A.msg'}:1:1: field 'b' makes a message contain itself "
        "(right/msg/B -> right/msg/C -> left/msg/A -> right/msg/B); "
        "a message cannot nest itself, directly or through other messages"
    )
    # A service is not part of the cycle, but needs a message that is.
    with pytest.raises(InterfaceSyntaxError) as excinfo:
        loader.load_service("right/UsesA")
    assert "(left/msg/A -> right/msg/B -> right/msg/C -> left/msg/A)" in message_of(excinfo)


def test_a_type_used_twice_is_not_a_cycle(loader: InterfaceLoader, root: Path) -> None:
    write(root, "demo/msg/Segment.msg", "Pose2D start\nPose2D end\nPose2D[2] both\n")
    segment = loader.load_message("demo/Segment")
    assert dump(segment())["both"] == [{"x": 0.0, "y": 0.0, "theta": 0.5}] * 2


# --- laziness and caching -------------------------------------------------------------------


def test_creating_a_loader_reads_nothing(tmp_path: Path) -> None:
    loader = InterfaceLoader([tmp_path / "does" / "not" / "exist"], use_default_path=False)
    assert loader.packages() == {}
    assert loader.types() == []


def test_a_broken_file_breaks_only_what_needs_it(loader: InterfaceLoader, root: Path) -> None:
    write(root, "demo/msg/Broken.msg", "this is not a field\n")
    write(root, "demo/msg/UsesBroken.msg", "Broken b\n")
    assert dump(loader.load_message("demo/Pose2D")()) == {"x": 0.0, "y": 0.0, "theta": 0.5}
    assert loader.load_service("demo/Move").type_name == "demo/srv/Move"
    with pytest.raises(InterfaceSyntaxError):
        loader.load_message("demo/UsesBroken")
    assert loader.load_message("demo/Thing") is loader.load_message("demo/msg/Thing")


def test_nothing_is_parsed_until_asked(
    loader: InterfaceLoader, monkeypatch: pytest.MonkeyPatch
) -> None:
    parsed: list[str] = []
    real = parser.parse_file

    def counting(path: Path, package: str | None = None) -> Spec:
        parsed.append(f"{package}/{path.stem}")
        return real(path, package)

    monkeypatch.setattr("srvwire.loader.parse_file", counting)
    assert loader.types()
    assert loader.resolve_name("demo/Pose2D") == "demo/msg/Pose2D"
    assert loader.path_of("demo/Move").is_file()
    assert parsed == []
    move = loader.load_service("demo/Move")
    assert parsed == ["demo/Move", "demo/Pose2D"]
    pose = loader.load_message("demo/Pose2D")
    assert loader.message_spec("demo/msg/Pose2D") is loader.message_spec("demo/Pose2D")
    assert loader.load_service("demo/srv/Move") is move
    assert loader.load_message("demo/msg/Pose2D") is pose
    assert loader.service_spec("demo/Move") is move.spec
    assert parsed == ["demo/Move", "demo/Pose2D"]


def test_specs_and_classes_are_built_once(loader: InterfaceLoader) -> None:
    assert loader.service_spec("demo/Move") is loader.service_spec("demo/srv/Move")
    assert loader.action_spec("demo/Go") is loader.action_spec("demo/action/Go")
    assert loader.load_service("demo/Move") is loader.load("demo/srv/Move")
    assert loader.load_action("demo/Go") is loader.load_action("demo/action/Go")
    assert loader.load("demo/Pose2D") is loader.load_message("demo/msg/Pose2D")
    # Another loader finds the same definitions: the process has one class per type.
    other = InterfaceLoader(loader.search_path)
    assert other.load_message("demo/Pose2D") is loader.load_message("demo/Pose2D")
    assert other.load_service("demo/Move") is loader.load_service("demo/Move")
    # A registry of its own is a world of its own.
    alone = InterfaceLoader(loader.search_path, types=TypeRegistry())
    assert alone.load_message("demo/Pose2D") is not loader.load_message("demo/Pose2D")


def test_spec_returns_whichever_kind_a_name_denotes(loader: InterfaceLoader) -> None:
    assert loader.spec("demo/Pose2D") is loader.message_spec("demo/msg/Pose2D")
    assert loader.spec("demo/srv/Move") is loader.service_spec("demo/Move")
    assert loader.spec("demo/Go") is loader.action_spec("demo/action/Go")
    with pytest.raises(InterfaceError) as excinfo:
        loader.spec("demo/Thing")
    assert message_of(excinfo).startswith("ambiguous interface name 'demo/Thing': ")


def test_failures_are_not_cached(loader: InterfaceLoader, root: Path) -> None:
    path = write(root, "demo/msg/Fixable.msg", "int32\n")
    with pytest.raises(InterfaceSyntaxError):
        loader.load_message("demo/Fixable")
    path.write_text("int32 fixed 7\n", encoding="utf-8")
    assert dump(loader.load_message("demo/Fixable")()) == {"fixed": 7}


def test_new_files_appear_in_a_new_loader(loader: InterfaceLoader, root: Path) -> None:
    assert loader.types("demo")
    write(root, "demo/msg/Late.msg", "int32 a\n")
    write(root, "late_pkg/msg/Late.msg", "int32 a\n")
    assert "demo/msg/Late" not in loader.types("demo")
    assert "late_pkg" not in loader.packages()
    fresh = InterfaceLoader([root], use_default_path=False)
    assert "demo/msg/Late" in fresh.types("demo")
    assert "late_pkg" in fresh.packages()


def test_the_package_map_is_a_copy(loader: InterfaceLoader) -> None:
    loader.packages().clear()
    assert "demo" in loader.packages()


# --- the module-level functions -------------------------------------------------------------


def test_module_functions_share_one_loader_per_search_path(root: Path, tmp_path: Path) -> None:
    move = load_service("demo/Move", [root])
    assert load_service("demo/srv/Move", [str(root)]) is move
    assert load_message("demo/Pose2D", (root,)) is load_message("demo/msg/Pose2D", [root])
    assert load_action("demo/Go", [root]) is load_action("demo/action/Go", [root])
    other = tmp_path / "other"
    write(other, "demo/srv/Move.srv", MOVE)
    write(other, "demo/msg/Pose2D.msg", POSE2D)
    # The same definitions in another folder: the same classes, from another shared loader.
    assert load_service("demo/Move", [other]) is move
    assert loader_module._loader_for([other]) is not loader_module._loader_for([root])
    assert loader_module._loader_for([other]) is loader_module._loader_for((str(other),))


def test_module_functions_read_the_variable_at_each_call(
    root: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    other = tmp_path / "other"
    write(other, "demo/msg/Pose2D.msg", "int64 only\n")
    monkeypatch.setenv(ENV_VAR, str(root))
    first = load_message("demo/Pose2D")
    assert dump(first()) == {"x": 0.0, "y": 0.0, "theta": 0.5}
    monkeypatch.setenv(ENV_VAR, os.pathsep.join([str(other), str(root)]))
    # The variable selected the other folder, whose Pose2D is another definition.
    with pytest.raises(InterfaceConflictError) as excinfo:
        load_message("demo/Pose2D")
    assert str(excinfo.value) == (
        f"two different definitions of demo/msg/Pose2D: {root / 'demo/msg/Pose2D.msg'} and "
        f"{other / 'demo/msg/Pose2D.msg'} (declaration 1: 'float64 x' against 'int64 only'); "
        "a type name has one definition per process"
    )
    monkeypatch.setenv(ENV_VAR, str(root))
    assert load_message("demo/Pose2D") is first
    assert load_message("demo/Pose2D", [root, bundled_interfaces()]) is first


def test_module_functions_load_the_bundled_interfaces(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(ENV_VAR, raising=False)
    trigger = load_service("std_srvs/Trigger")
    assert trigger is load_service("std_srvs/srv/Trigger")
    assert trigger.type_name == "std_srvs/srv/Trigger"
    assert dump(trigger.Response()) == {"success": False, "message": ""}


def test_a_search_path_adds_to_the_default_path(
    root: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv(ENV_VAR, raising=False)
    loader = InterfaceLoader([root])
    assert loader.search_path == (root, bundled_interfaces())
    assert loader.load_message("std_msgs/Header").type_name == "std_msgs/msg/Header"
    assert loader.load_message("demo/Pose2D").type_name == "demo/msg/Pose2D"


def test_use_default_path_false_searches_only_the_folders_given(root: Path) -> None:
    loader = InterfaceLoader([root], use_default_path=False)
    assert loader.search_path == (root,)
    with pytest.raises(InterfaceNotFoundError) as excinfo:
        loader.load_message("std_msgs/Header")
    assert message_of(excinfo) == f"no interface package 'std_msgs' in {root}"


def test_a_package_that_hides_a_bundled_one_is_named_in_the_error(tmp_path: Path) -> None:
    overlay = tmp_path / "overlay"
    write(overlay, "std_msgs/msg/Mine.msg", "int32 a\n")
    loader = InterfaceLoader([overlay])
    with pytest.raises(InterfaceNotFoundError) as excinfo:
        loader.load_message("std_msgs/Header")
    assert message_of(excinfo) == (
        f"no message 'Header' in package 'std_msgs' ({overlay / 'std_msgs'} hides the bundled "
        f"package 'std_msgs' in {bundled_interfaces()}, which has it: a package is taken whole "
        "from the first folder that holds it)"
    )


def test_a_nested_type_hidden_by_an_overlay_says_where(tmp_path: Path) -> None:
    overlay = tmp_path / "overlay"
    write(overlay, "std_msgs/msg/Mine.msg", "int32 a\n")
    path = write(overlay, "robot/msg/Status.msg", "std_msgs/Header header\n")
    with pytest.raises(InterfaceSyntaxError) as excinfo:
        InterfaceLoader([overlay]).load_message("robot/Status")
    assert str(excinfo.value).startswith(
        f"{path}:1:1: unknown type 'std_msgs/Header' of field 'header': no message 'Header' in "
        f"package 'std_msgs' ({overlay / 'std_msgs'} hides the bundled package"
    )


# --- fixed arrays of any size -----------------------------------------------------------------

HUGE_ARRAYS = """
import resource
import sys
from pathlib import Path

from srvwire.cli import main
from srvwire.loader import InterfaceLoader
from srvwire.typeregistry import TypeRegistry

MIB = 1024  # ru_maxrss and VmRSS are in KiB on Linux


def peak() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss


def now() -> int:
    status = Path("/proc/self/status").read_text(encoding="ascii")
    return int(status.split("VmRSS:")[1].split()[0])


root = Path(sys.argv[1])
start = peak()
cls = InterfaceLoader([root], types=TypeRegistry()).load_message("big/Huge")
assert main(["interface", "check", str(root)]) == 0
assert main(["interface", "show", "big/msg/Huge", "--path", str(root)]) == 0
assert main(["interface", "show", "big/srv/Biggest", "--path", str(root)]) == 0
loaded, before = peak(), now()
huge = cls()
made = now()
assert (len(huge.a), huge.a[-1], huge.b[:2], len(huge.b)) == (10_000_000, 0, bytes(2), 40_000_000)
print((loaded - start) // MIB, (made - before) // MIB)
"""


def test_loading_checking_and_showing_fixed_arrays_allocates_none_of_their_values(
    tmp_path: Path,
) -> None:
    # A fixed size can be 4294967295; the N zero values of its default are made only for an
    # instance that needs them. Before, loading the message below held 200 MiB more (its
    # default list, a tuple copy of it, and the bytes); the 4294967295 service did not load.
    write(tmp_path, "big/msg/Huge.msg", "int32[10000000] a\nuint8[40000000] b\n")
    write(tmp_path, "big/srv/Biggest.srv", "int32[4294967295] a\nPoint[4294967295] p\n---\n")
    write(tmp_path, "big/msg/Point.msg", "float64 x\n")
    script = tmp_path / "huge.py"
    script.write_text(HUGE_ARRAYS, encoding="utf-8")
    ran = subprocess.run(
        [sys.executable, str(script), str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert (ran.returncode, ran.stderr) == (0, "")
    loading, making = (int(word) for word in ran.stdout.splitlines()[-1].split())
    assert loading < 16, ran.stdout  # peak MiB: the classes, never their arrays' values
    # MiB now: the instance's 80 MB list (its bytes are zero pages, not resident until written).
    assert making > 60, ran.stdout
