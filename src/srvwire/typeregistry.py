"""One class per interface type per process, whoever asks for it and wherever it was found.

A :class:`TypeRegistry` maps a type name (``std_msgs/msg/Header``, ``pkg/srv/Name``,
``pkg/action/Name``) to the one class built for it and the *source* that defined it first: a
file's path, ``server ws://...`` for a type a client built from a server's description, or
``module m`` for a class a generated module declares.

Invariants:

* **One class per name and definition.** :meth:`TypeRegistry.intern` returns the class already
  recorded for a name when the new definition is the same, and builds a class only for a name
  it has not seen. Every loader (whatever its search path), every client's reflection and every
  server's registry share :func:`process_types`, so ``Header`` is one class in the process.
* **Same definition** means the same constants and fields, in order: each one's type, name and
  default or value. Comments, blank lines and where the file lives do not count. A nested type
  is compared by its name only; it is interned itself, so a difference in it is caught there.
* **One definition per name.** A different definition under a recorded name is an
  :class:`~srvwire.errors.InterfaceConflictError` that names both sources and the first line
  that differs. Nothing is replaced: the first definition stays.
* **Failures are not recorded.** A build that raises leaves the registry as it was.
* **Threads.** One re-entrant lock; a build runs under it, and may intern the types it nests.
* **A fingerprint stands for a full definition.** :func:`fingerprint` digests the definitions
  (as above) of a service or action and of every message it nests, by name: two classes have
  the same fingerprint exactly when all of those are the same. A server announces its
  services' fingerprints, so that a client can compare its own classes with no round trip.

:func:`process_types` is module-level state, like the loader's shared cache: one class per type
*per process* cannot live anywhere else. Code that wants a separate world (a test of conflicting
definitions) passes its own :class:`TypeRegistry`.
"""

from __future__ import annotations

import hashlib
import threading
import typing
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, TypeVar

from srvwire.errors import InterfaceConflictError
from srvwire.idl import ActionSpec, MessageSpec, ServiceSpec

__all__ = [
    "Interned",
    "Spec",
    "TypeRegistry",
    "definition_lines",
    "fingerprint",
    "full_definition",
    "process_types",
]

Spec = MessageSpec | ServiceSpec | ActionSpec
T = TypeVar("T")


def definition_lines(spec: Spec) -> tuple[str, ...]:
    """Return what makes ``spec``'s definition: one line per constant and field, parts split.

    Lines read like the file's declarations without comments (``int32 x 0``, ``uint8 A=1``);
    the parts of a service or action are separated by ``---``.
    """
    if isinstance(spec, MessageSpec):
        constants = tuple(f"{c.type} {c.name}={c.value!r}" for c in spec.constants)
        fields = tuple(
            f"{f.type} {f.name}" if f.default is None else f"{f.type} {f.name} {f.default!r}"
            for f in spec.fields
        )
        return constants + fields
    parts = (
        (spec.request, spec.response)
        if isinstance(spec, ServiceSpec)
        else (spec.goal, spec.result, spec.feedback)
    )
    lines: list[str] = []
    for index, part in enumerate(parts):
        if index:
            lines.append("---")
        lines.extend(definition_lines(part))
    return tuple(lines)


def full_definition(cls: Any) -> dict[str, tuple[str, ...]] | None:
    """Return the :func:`definition_lines` of ``cls`` and of every message it nests, by name.

    ``cls`` is a message, service or action class carrying its ``spec``; the nested messages
    are found through its (and its parts') fields. None when ``cls`` has no spec (a class
    written by hand): it has no definition to compare. A nested class without a spec is left
    out. An action's goal service (no spec of its own, its ``action`` has one) stands for its
    action, so that a served action has its action's fingerprint.
    """
    spec = getattr(cls, "spec", None)
    if spec is None and isinstance(getattr(getattr(cls, "action", None), "spec", None), ActionSpec):
        cls = cls.action
        spec = cls.spec
    if not isinstance(spec, MessageSpec | ServiceSpec | ActionSpec):
        return None
    found: dict[str, tuple[str, ...]] = {spec.type_name: definition_lines(spec)}
    parts = ("Request", "Response", "Goal", "Result", "Feedback")
    todo: list[Any] = [cls, *(getattr(cls, part) for part in parts if hasattr(cls, part))]
    while todo:
        fields = getattr(todo.pop(), "model_fields", None) or {}
        for info in fields.values():
            for nested in _classes_in(info.annotation):
                nested_spec = getattr(nested, "spec", None)
                if isinstance(nested_spec, MessageSpec) and nested_spec.type_name not in found:
                    found[nested_spec.type_name] = definition_lines(nested_spec)
                    todo.append(nested)
    return found


def _classes_in(annotation: Any) -> Iterator[type]:
    if isinstance(annotation, type) and hasattr(annotation, "model_fields"):
        yield annotation
    for argument in typing.get_args(annotation):
        yield from _classes_in(argument)


def fingerprint(definition: dict[str, tuple[str, ...]]) -> str:
    """A short digest (16 hex digits) of a :func:`full_definition`: equal definitions, equal
    digests; a digest says nothing of comments, blank lines or where the files live."""
    digest = hashlib.sha256()
    for name in sorted(definition):
        digest.update(name.encode())
        for line in definition[name]:
            digest.update(b"\n" + line.encode())
        digest.update(b"\n\n")
    return digest.hexdigest()[:16]


def first_difference(
    ours: dict[str, tuple[str, ...]], theirs: dict[str, tuple[str, ...]]
) -> tuple[str, str]:
    """Say where two full definitions first part: the type's name, and the line each has
    there (``declaration 2: 'int64 b' against 'int32 b'``), or that one of them lacks it."""
    names = [name for name in ours if name in theirs] + sorted(set(ours) ^ set(theirs))
    for name in names:
        mine, other = ours.get(name), theirs.get(name)
        if mine is None:
            return name, "only the second defines it"
        if other is None:
            return name, "only the first defines it"
        if mine != other:
            return name, _difference(Interned(None, mine, ""), other)
    return "", "the same declarations"


@dataclass(frozen=True, slots=True)
class Interned:
    """One recorded type: its class, what defines it, and where that definition came from."""

    cls: Any
    definition: tuple[str, ...]
    source: str


class TypeRegistry:
    """The classes of one process (or of one isolated world), by type name."""

    def __init__(self) -> None:
        self._lock = threading.RLock()
        self._types: dict[str, Interned] = {}

    def __repr__(self) -> str:
        return f"<TypeRegistry of {len(self._types)} types>"

    def get(self, name: str) -> Interned | None:
        """Return what is recorded for the full type name ``name``, or None."""
        with self._lock:
            return self._types.get(name)

    def intern(self, spec: Spec, source: str, build: Callable[[], T]) -> T:
        """Return the class of ``spec``: the recorded one, or ``build()``'s, recorded now.

        Raise :class:`~srvwire.errors.InterfaceConflictError` when ``spec``'s name is recorded
        with another definition, or when ``build`` records another one itself (a builder that
        interns what it finds elsewhere, such as a loader).
        """
        name = spec.type_name
        definition = definition_lines(spec)
        with self._lock:
            known = self._types.get(name)
            if known is not None:
                return _same(name, known, definition, source)  # type: ignore[no-any-return]
            cls = build()
            known = self._types.get(name)  # the builder may have recorded it
            if known is not None:
                return _same(name, known, definition, source)  # type: ignore[no-any-return]
            self._types[name] = Interned(cls, definition, source)
            return cls

    def adopt(self, cls: T, source: str) -> T:
        """Record a class declared elsewhere (a generated module's) and return the process's.

        ``cls`` must carry its ``spec``. When its name is recorded with the same definition,
        the recorded class is returned; another definition is a conflict, as for
        :meth:`intern`.
        """
        spec = getattr(cls, "spec", None)
        if not isinstance(spec, MessageSpec | ServiceSpec | ActionSpec):
            raise TypeError(f"{cls!r} has no interface spec to record")
        return self.intern(spec, source, lambda: cls)


def _same(name: str, known: Interned, definition: tuple[str, ...], source: str) -> Any:
    if known.definition == definition:
        return known.cls
    raise InterfaceConflictError(name, known.source, source, _difference(known, definition))


def _difference(known: Interned, definition: tuple[str, ...]) -> str:
    """Say where two definitions first part: the line each has there."""
    for index in range(max(len(known.definition), len(definition))):
        theirs = repr(known.definition[index]) if index < len(known.definition) else "nothing"
        ours = repr(definition[index]) if index < len(definition) else "nothing"
        if theirs != ours:
            return f"declaration {index + 1}: {theirs} against {ours}"
    return "the same declarations"  # pragma: no cover - only called when they differ


_PROCESS = TypeRegistry()


def process_types() -> TypeRegistry:
    """Return the registry every loader, client and server of this process shares."""
    return _PROCESS
