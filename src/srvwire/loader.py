"""Find interface packages on a search path, resolve the types they name, and cache them.

Theory of operation
-------------------

A *search path* is a sequence of folders. Each folder holds *packages*; a package is a
sub-folder holding at least one of ``msg/``, ``srv/`` or ``action/``, and a type is a file in one
of those (``geometry_msgs/msg/Pose.msg`` is the message ``geometry_msgs/msg/Pose``). Hidden
folders (``.git``) are never packages. A search-path folder that does not exist is skipped, as
``PATH`` entries are.

Invariants:

* **Search order.** A loader searches the folders it is given, then :func:`default_search_path`:
  the folders in ``SRVWIRE_INTERFACE_PATH`` (split on :data:`os.pathsep`, empty entries
  ignored), then :func:`bundled_interfaces`. ``use_default_path=False`` searches only the
  folders given. When two folders hold a package of the same name, the earlier one wins *as a
  whole* — its files are not merged with the later one's. This is ROS's overlay/underlay rule:
  a workspace that rebuilds a package hides the installed copy entirely. A type missing from a
  package that hides another is reported with the folder that hid which.
* **Laziness.** Building an :class:`InterfaceLoader` touches no file. Listing packages or types
  reads folders only. A file is read and parsed when its type, or a type that nests it, is asked
  for — so a broken file breaks only the types that need it.
* **Caching.** A loader scans each search-path folder once (the first time it needs to), parses
  each file at most once successfully, and builds each class at most once: asking twice returns
  the very same class object. Failures are not cached; fixing the file and asking again works
  on the same loader, but new files or packages appear only in a new loader.
* **One class per type per process.** Every class is interned in a
  :class:`~srvwire.typeregistry.TypeRegistry` (the process's by default) under its file's path:
  two loaders with different search paths that find the same definition return the same class,
  and a different definition of a type already loaded is an
  :class:`~srvwire.errors.InterfaceConflictError` naming both files.
* **Nesting.** A nested field type is resolved through the same loader, across packages. Every
  type a message nests is loaded before the message's own class is built, so an unknown nested
  type or a cycle (a message that contains itself, directly or through others) is reported as an
  :class:`~srvwire.errors.InterfaceSyntaxError` at the field that names it, never as a
  ``RecursionError``.
* **Threads.** One re-entrant lock guards a loader's caches, so concurrent calls still build
  each class once.

Names are ``package/kind/Name`` (``std_srvs/srv/Trigger``) or, when only one kind of interface
in the package has that name, ``package/Name``. A name that cannot be resolved is an
:class:`~srvwire.errors.InterfaceError` that says why; one that names nothing on the search path
is an :class:`~srvwire.errors.InterfaceNotFoundError` listing the closest names.

The module-level :func:`load_message`, :func:`load_service` and :func:`load_action` share one
loader per search path, kept in a small least-recently-used cache (:func:`_shared_loader`). That
cache is the only module-level state in srvwire: it is what makes the one-line convenience calls
cheap to repeat. (Two threads asking for a new search path at the same instant may each get a
loader of their own; every later call shares one.) Code that wants control creates and passes its
own :class:`InterfaceLoader`.
"""

from __future__ import annotations

import difflib
import functools
import os
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TypeAlias, TypeVar

from srvwire.errors import InterfaceError, InterfaceNotFoundError, InterfaceSyntaxError
from srvwire.idl import (
    ActionSpec,
    FieldSpec,
    InterfaceKind,
    MessageSpec,
    ServiceSpec,
    TypeSpec,
)
from srvwire.models import Action, Message, Service, build_action, build_message, build_service
from srvwire.parser import parse_file
from srvwire.scanner import PACKAGE_NAME, TYPE_NAME, split_lines
from srvwire.typeregistry import TypeRegistry, process_types

__all__ = [
    "ENV_VAR",
    "InterfaceLoader",
    "SearchPath",
    "bundled_interfaces",
    "default_search_path",
    "load_action",
    "load_message",
    "load_service",
    "search_path_of",
]

ENV_VAR = "SRVWIRE_INTERFACE_PATH"

SearchPath: TypeAlias = Sequence[str | os.PathLike[str]]

_KIND_WORDS = {
    InterfaceKind.MSG: "message",
    InterfaceKind.SRV: "service",
    InterfaceKind.ACTION: "action",
}
_KINDS_BY_NAME = {kind.value: kind for kind in InterfaceKind}
_SHAPES = "expected 'package/kind/Name' (kind: msg, srv or action) or 'package/Name'"
_SHARED_LOADERS = 16  # how many search paths the module-level functions remember
T = TypeVar("T")


def bundled_interfaces() -> Path:
    """Return the folder of interface packages that ships with srvwire.

    In an installed wheel it is ``srvwire/interfaces`` beside this module (the build copies the
    repository's top-level ``interfaces/`` there). In a source checkout or an editable install
    that folder does not exist, and the repository's own ``interfaces/`` is used instead
    (``src/srvwire/../../interfaces``). If neither exists the wheel location is returned; it
    simply holds no packages.
    """
    here = Path(__file__).resolve().parent
    installed = here / "interfaces"
    if installed.is_dir():
        return installed
    source_tree = here.parent.parent / "interfaces"
    if source_tree.is_dir():
        return source_tree
    return installed


def default_search_path() -> list[Path]:
    """Return ``SRVWIRE_INTERFACE_PATH``'s folders, in order, then :func:`bundled_interfaces`.

    The variable is read on every call. Its entries are separated by :data:`os.pathsep`
    (``:`` on POSIX, ``;`` on Windows); empty entries are ignored.
    """
    configured = os.environ.get(ENV_VAR, "")
    folders = [Path(entry) for entry in configured.split(os.pathsep) if entry]
    return [*folders, bundled_interfaces()]


def _normalize(search_path: SearchPath) -> tuple[Path, ...]:
    if isinstance(search_path, str | os.PathLike):
        # A lone str is a Sequence too: take it as one folder, not as one folder per character.
        search_path = [search_path]
    return tuple(Path(os.fspath(folder)).absolute() for folder in search_path)


def search_path_of(search_path: SearchPath | None, use_default_path: bool = True) -> list[Path]:
    """Return the folders to search: ``search_path``, then the default path unless told not to.

    ``search_path`` *adds* folders in front of :func:`default_search_path` (as the command
    line's ``--path`` does), so the bundled packages stay visible; ``use_default_path=False``
    searches only the folders given.
    """
    given = [] if search_path is None else list(_normalize(search_path))
    return [*given, *default_search_path()] if use_default_path else given


class InterfaceLoader:
    """Find, parse and build the interface types on one search path, caching what it builds.

    ``search_path`` lists folders that hold packages, searched first, earliest first; then
    comes :func:`default_search_path` as it is when the loader is created, unless
    ``use_default_path=False``, which searches only the folders given. Names may be given in
    full (``std_srvs/srv/Trigger``) or short (``std_srvs/Trigger``) when only one kind of
    interface in the package has that name. Classes are interned in ``types`` (by default
    :func:`~srvwire.typeregistry.process_types`), so every loader of the process returns the
    same class for the same type.
    """

    def __init__(
        self,
        search_path: SearchPath | None = None,
        *,
        use_default_path: bool = True,
        types: TypeRegistry | None = None,
    ) -> None:
        self.search_path: tuple[Path, ...] = _normalize(
            search_path_of(search_path, use_default_path)
        )
        self.types_registry = process_types() if types is None else types
        self._lock = threading.RLock()
        self._packages: dict[str, Path] | None = None
        self._types: dict[str, dict[str, Path]] = {}  # package -> full name -> file
        self._specs: dict[str, MessageSpec | ServiceSpec | ActionSpec] = {}
        self._messages: dict[str, type[Message]] = {}
        self._services: dict[str, type[Service]] = {}
        self._actions: dict[str, type[Action]] = {}

    def __repr__(self) -> str:
        folders = ", ".join(str(folder) for folder in self.search_path)
        return f"InterfaceLoader([{folders}])"

    # --- discovery ----------------------------------------------------------------------------

    def packages(self) -> dict[str, Path]:
        """Map each package name to its folder, sorted by name.

        A package is a folder holding ``msg/``, ``srv/`` or ``action/``. When several
        search-path folders hold a package of the same name, the earliest wins (overlay). A
        folder whose name is not a valid package name (``Bad-Name``) is left out, as its types
        can never load (loading one says why; ``srvwire interface check`` reports each).
        """
        with self._lock:
            return {name: folder for name, folder in self._package_map().items() if _valid(name)}

    def types(self, package: str | None = None) -> list[str]:
        """List the full names (``pkg/srv/Name``) of every type, or of one package's, sorted.

        Only names that can load: a file whose name is not a valid type name (``lower.msg``),
        or in a package whose name is not valid, is left out, as :meth:`packages` leaves such
        a package out. A file with a valid name is listed even if its text has an error, which
        loading it reports.
        """
        with self._lock:
            if package is None:
                folders = self._package_map().values()
                names = [name for folder in folders for name in self._index(folder)]
            else:
                names = list(self._index(self._package_folder(package, package)))
            return sorted(name for name in names if _valid(*name.split("/")[::2]))

    def resolve_name(self, name: str, kind: InterfaceKind | None = None) -> str:
        """Return the full name (``pkg/kind/Name``) for ``name``, checking that the type exists.

        ``name`` is ``pkg/kind/Name`` or the short ``pkg/Name``. With ``kind``, a name that
        denotes another kind of interface is an error.
        """
        with self._lock:
            parts = name.split("/")
            if len(parts) not in (2, 3) or not all(parts):
                raise InterfaceError(f"malformed interface name {name!r}: {_SHAPES}")
            if len(parts) == 3:
                return self._resolve_full(name, parts[0], parts[1], parts[2], kind)
            return self._resolve_short(name, parts[0], parts[1], kind)

    def path_of(self, name: str) -> Path:
        """Return the file that defines ``name``."""
        with self._lock:
            full = self.resolve_name(name)
            package = full.split("/")[0]
            return self._index(self._package_folder(package, name))[full]

    # --- specs --------------------------------------------------------------------------------

    def message_spec(self, name: str) -> MessageSpec:
        """Parse (once) and return the message ``name``."""
        spec = self._spec(name, InterfaceKind.MSG)
        assert isinstance(spec, MessageSpec)
        return spec

    def service_spec(self, name: str) -> ServiceSpec:
        """Parse (once) and return the service ``name``."""
        spec = self._spec(name, InterfaceKind.SRV)
        assert isinstance(spec, ServiceSpec)
        return spec

    def action_spec(self, name: str) -> ActionSpec:
        """Parse (once) and return the action ``name``."""
        spec = self._spec(name, InterfaceKind.ACTION)
        assert isinstance(spec, ActionSpec)
        return spec

    def spec(self, name: str) -> MessageSpec | ServiceSpec | ActionSpec:
        """Parse (once) and return whichever kind of interface ``name`` denotes."""
        with self._lock:
            full = self.resolve_name(name)
            return self._spec(full, _KINDS_BY_NAME[full.split("/")[1]])

    # --- classes ------------------------------------------------------------------------------

    def load_message(self, name: str) -> type[Message]:
        """Build (once) and return the message class for ``name``, with its nested types."""
        with self._lock:
            full = self.resolve_name(name, InterfaceKind.MSG)
            return self._load_message(full, (full,))

    def load_service(self, name: str) -> type[Service]:
        """Build (once) and return the service class for ``name``, with its nested types."""
        with self._lock:
            full = self.resolve_name(name, InterfaceKind.SRV)
            cached = self._services.get(full)
            if cached is None:
                spec = self.service_spec(full)
                self._load_nested(full, (spec.request, spec.response), ())
                cached = self._services[full] = self._intern(
                    spec, lambda: build_service(spec, self._resolve)
                )
            return cached

    def load_action(self, name: str) -> type[Action]:
        """Build (once) and return the action class for ``name``, with its nested types."""
        with self._lock:
            full = self.resolve_name(name, InterfaceKind.ACTION)
            cached = self._actions.get(full)
            if cached is None:
                spec = self.action_spec(full)
                self._load_nested(full, (spec.goal, spec.result, spec.feedback), ())
                cached = self._actions[full] = self._intern(
                    spec, lambda: build_action(spec, self._resolve)
                )
            return cached

    def load(self, name: str) -> type[Message] | type[Service] | type[Action]:
        """Build and return whichever kind of interface ``name`` denotes."""
        full = self.resolve_name(name)
        kind = _KINDS_BY_NAME[full.split("/")[1]]
        if kind is InterfaceKind.MSG:
            return self.load_message(full)
        if kind is InterfaceKind.SRV:
            return self.load_service(full)
        return self.load_action(full)

    # --- internals ----------------------------------------------------------------------------

    def _package_map(self) -> dict[str, Path]:
        if self._packages is None:
            found: dict[str, Path] = {}
            for root in self.search_path:
                for folder in _subfolders(root):
                    if folder.name in found or folder.name.startswith("."):
                        continue
                    if any((folder / kind.value).is_dir() for kind in InterfaceKind):
                        found[folder.name] = folder
            self._packages = dict(sorted(found.items()))
        return self._packages

    def _package_folder(self, package: str, name: str) -> Path:
        packages = self._package_map()
        folder = packages.get(package)
        if folder is not None:
            return folder
        if not self.search_path:
            raise InterfaceNotFoundError(
                name, f"no interface package {package!r}: the search path is empty"
            )
        where = os.pathsep.join(str(root) for root in self.search_path)
        raise InterfaceNotFoundError(
            name,
            f"no interface package {package!r} in {where}",
            candidates=tuple(difflib.get_close_matches(package, packages)),
        )

    def _resolve_full(
        self, name: str, package: str, kind_name: str, type_name: str, kind: InterfaceKind | None
    ) -> str:
        written = _KINDS_BY_NAME.get(kind_name)
        if written is None:
            raise InterfaceError(
                f"malformed interface name {name!r}: "
                f"the kind {kind_name!r} is not one of msg, srv, action"
            )
        if kind is not None and written is not kind:
            raise InterfaceError(_wrong_kind(name, written, kind))
        if name in self._index(self._package_folder(package, name)):
            return name
        raise self._not_found(name, package, type_name, written)

    def _resolve_short(
        self, name: str, package: str, type_name: str, kind: InterfaceKind | None
    ) -> str:
        index = self._index(self._package_folder(package, name))
        matches = {
            k: f"{package}/{k.value}/{type_name}"
            for k in InterfaceKind
            if f"{package}/{k.value}/{type_name}" in index
        }
        if kind is not None:
            if kind in matches:
                return matches[kind]
            if matches:
                raise InterfaceError(_wrong_kind(name, next(iter(matches)), kind))
            raise self._not_found(name, package, type_name, kind)
        if len(matches) == 1:
            return next(iter(matches.values()))
        if matches:
            raise InterfaceError(
                f"ambiguous interface name {name!r}: it could be "
                f"{' or '.join(matches.values())}; write the full name"
            )
        raise self._not_found(name, package, type_name, None)

    def _index(self, folder: Path) -> dict[str, Path]:
        package = folder.name
        index = self._types.get(package)
        if index is None:
            index = {}
            for kind in InterfaceKind:
                for path in sorted((folder / kind.value).glob(f"*.{kind.value}")):
                    if path.is_file():
                        index[f"{package}/{kind.value}/{path.stem}"] = path
            self._types[package] = index
        return index

    def _not_found(
        self, name: str, package: str, type_name: str, kind: InterfaceKind | None
    ) -> InterfaceNotFoundError:
        packages = self._package_map()
        index = self._index(packages[package])
        kinds = [kind] if kind is not None else list(InterfaceKind)
        by_name: dict[str, list[str]] = {}
        for full in index:
            _, kind_name, short = full.split("/")
            if _KINDS_BY_NAME[kind_name] in kinds:
                by_name.setdefault(short, []).append(full)
        close = difflib.get_close_matches(type_name, by_name)
        candidates = [full for short in close for full in by_name[short]]
        # The same name in another package is the likeliest slip of all (std_msgs/Point).
        for other, folder in packages.items():
            if other != package:
                others = self._index(folder)
                candidates += [
                    f"{other}/{k.value}/{type_name}"
                    for k in kinds
                    if f"{other}/{k.value}/{type_name}" in others
                ]
        what = _KIND_WORDS[kind] if kind is not None else "interface"
        return InterfaceNotFoundError(
            name,
            f"no {what} {type_name!r} in package {package!r}{self._hidden(package, type_name)}",
            candidates=tuple(candidates),
        )

    def _hidden(self, package: str, type_name: str) -> str:
        """Say which folder's package hid a later one that has ``type_name`` (overlay)."""
        folder = self._package_map()[package]
        later = self.search_path[self.search_path.index(folder.parent) + 1 :]
        for root in later:
            other = root / package
            if any((other / k.value / f"{type_name}.{k.value}").is_file() for k in InterfaceKind):
                which = "the bundled" if root.resolve() == bundled_interfaces() else "the"
                return (
                    f" ({folder} hides {which} package {package!r} in {root}, which has it: "
                    "a package is taken whole from the first folder that holds it)"
                )
        return ""

    def _spec(self, name: str, kind: InterfaceKind) -> MessageSpec | ServiceSpec | ActionSpec:
        with self._lock:
            full = self.resolve_name(name, kind)
            spec = self._specs.get(full)
            if spec is None:
                spec = self._specs[full] = _parse(self.path_of(full), full.split("/")[0])
            return spec

    def _resolve(self, type_: TypeSpec) -> type[Message]:
        # Every nested type is loaded before a class is built, so this is a cache hit; going
        # through load_message keeps it correct even if a builder asks for something else.
        return self.load_message(type_.qualified_name)

    def _load_message(self, full: str, chain: tuple[str, ...]) -> type[Message]:
        cached = self._messages.get(full)
        if cached is None:
            spec = self.message_spec(full)
            self._load_nested(full, (spec,), chain)
            cached = self._messages[full] = self._intern(
                spec, lambda: build_message(spec, self._resolve)
            )
        return cached

    def _intern(self, spec: MessageSpec | ServiceSpec | ActionSpec, build: Callable[[], T]) -> T:
        """The process's class for ``spec``: built here, or the one another source built."""
        return self.types_registry.intern(spec, str(self.path_of(spec.type_name)), build)

    def _load_nested(
        self, owner: str, parts: tuple[MessageSpec, ...], chain: tuple[str, ...]
    ) -> None:
        """Load every message the ``parts`` of ``owner`` nest, before ``owner`` is built.

        ``chain`` is the path of messages being loaded that led here (``owner`` last, for a
        message); meeting one of them again is a cycle.
        """
        for part in parts:
            for field in part.fields:
                if field.type.is_primitive:
                    continue
                nested = field.type.qualified_name
                if nested in chain:
                    cycle = " -> ".join((*chain[chain.index(nested) :], nested))
                    raise self._field_error(
                        owner,
                        field,
                        f"field {field.name!r} makes a message contain itself ({cycle}); "
                        "a message cannot nest itself, directly or through other messages",
                    )
                try:
                    self.resolve_name(nested, InterfaceKind.MSG)
                except InterfaceError as exc:
                    where = f"{field.type.package}/{field.type.name}"
                    raise self._field_error(
                        owner, field, f"unknown type {where!r} of field {field.name!r}: {exc}"
                    ) from exc
                self._load_message(nested, (*chain, nested))

    def _field_error(self, owner: str, field: FieldSpec, message: str) -> InterfaceSyntaxError:
        path = self.path_of(owner)
        return InterfaceSyntaxError(
            message, path=path, line=field.line, column=_column_of(path, field.line)
        )


def _subfolders(root: Path) -> list[Path]:
    try:
        return sorted(child for child in root.iterdir() if child.is_dir())
    except OSError:  # missing, not a folder, or unreadable: skipped, as PATH entries are
        return []


def _wrong_kind(name: str, actual: InterfaceKind, wanted: InterfaceKind) -> str:
    return f"{name!r} names {_a(_KIND_WORDS[actual])}, not {_a(_KIND_WORDS[wanted])}"


def _a(word: str) -> str:
    return f"an {word}" if word[0] in "aeiou" else f"a {word}"


def _parse(path: Path, package: str) -> MessageSpec | ServiceSpec | ActionSpec:
    """Read and parse one file; the parser checks the names and reports bad text or bytes."""
    try:
        return parse_file(path, package)
    except OSError as exc:
        raise InterfaceError(f"{path}: cannot read the file: {exc.strerror}") from exc


def _column_of(path: Path, line: int) -> int:
    """Return the 1-based column where the text of ``line`` in ``path`` starts.

    Lines and whitespace are cut as the parser cuts them, so the column matches its own.
    """
    try:
        text = path.read_text(encoding="utf-8").removeprefix("\ufeff")
    except (OSError, UnicodeDecodeError):
        return 1
    lines = split_lines(text)
    if not 1 <= line <= len(lines):
        return 1
    declaration = lines[line - 1]
    return len(declaration) - len(declaration.lstrip(" \t")) + 1


def _valid(package: str, type_name: str = "Name") -> bool:
    """Whether a type ``package/kind/type_name`` can load by its names (see the parser's)."""
    return bool(PACKAGE_NAME.fullmatch(package) and TYPE_NAME.fullmatch(type_name))


@functools.lru_cache(maxsize=_SHARED_LOADERS)
def _shared_loader(search_path: tuple[Path, ...]) -> InterfaceLoader:
    """Return the loader the module-level functions share for one search path."""
    return InterfaceLoader(search_path, use_default_path=False)


def _loader_for(search_path: SearchPath | None) -> InterfaceLoader:
    return _shared_loader(_normalize(search_path_of(search_path)))


def load_message(name: str, search_path: SearchPath | None = None) -> type[Message]:
    """Return the message class for ``name`` from a loader shared per search path.

    ``search_path`` adds folders in front of :func:`default_search_path`, which is read at each
    call, so changing ``SRVWIRE_INTERFACE_PATH`` selects another shared loader.
    """
    return _loader_for(search_path).load_message(name)


def load_service(name: str, search_path: SearchPath | None = None) -> type[Service]:
    """Return the service class for ``name`` from a loader shared per search path.

    ``search_path`` adds folders in front of :func:`default_search_path`, which is read at each
    call, so changing ``SRVWIRE_INTERFACE_PATH`` selects another shared loader.
    """
    return _loader_for(search_path).load_service(name)


def load_action(name: str, search_path: SearchPath | None = None) -> type[Action]:
    """Return the action class for ``name`` from a loader shared per search path.

    ``search_path`` adds folders in front of :func:`default_search_path`, which is read at each
    call, so changing ``SRVWIRE_INTERFACE_PATH`` selects another shared loader.
    """
    return _loader_for(search_path).load_action(name)
