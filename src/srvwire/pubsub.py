"""A server's topics: their message classes, the handlers of what clients publish, publishers.

A :class:`TopicEntry` is what the server keeps with each :class:`~srvwire.topics.Topic`: the
message class, its JSON writer (a message is written once, however many subscribe), the
handlers of ``@server.subscription`` and the topic's description for ``rpc.discover``. A
:class:`Publisher` is what ``server.topic(...)`` returns: ``publish`` is synchronous and never
waits for a subscriber.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

from pydantic import BaseModel, ValidationError

from srvwire.dispatch import _standalone_schema, nested_messages_of
from srvwire.errors import InvalidParams, RegistrationError
from srvwire.models import (
    error_data,
    json_writer,
    summarize_errors,
    validate_python,
    validate_wire,
)
from srvwire.topics import QoS, Topic
from srvwire.typeregistry import fingerprint, full_definition

__all__ = [
    "Publisher",
    "TopicEntry",
    "TopicHandler",
    "check_handler",
    "message_definitions",
    "qos_of",
]

M = TypeVar("M", bound=BaseModel)

TopicHandler = Callable[[Any], Any]
"""A handler of client-published messages: ``def f(msg)`` or ``async def f(msg)``."""


def qos_of(qos: QoS | Mapping[str, Any] | None) -> QoS:
    """A topic's QoS from a :class:`QoS`, a mapping of its fields, or None (ROS's defaults)."""
    if qos is None:
        return QoS()
    if isinstance(qos, QoS):
        return qos
    if isinstance(qos, Mapping):
        return QoS(**qos)
    raise TypeError(f"qos must be a QoS or a mapping of its settings, not {qos!r}")


def message_definitions(msg_type: type[BaseModel]) -> dict[str, str]:
    """The definition text of a message type and of every message it nests, by full name."""
    texts: dict[str, str] = {}
    for cls in (msg_type, *nested_messages_of(msg_type)):
        text: object = getattr(getattr(cls, "spec", None), "text", None)
        name = getattr(cls, "type_name", None)
        if isinstance(text, str) and text and isinstance(name, str):
            texts[name] = text
    return dict(sorted(texts.items()))


@dataclass(eq=False)
class TopicEntry:
    """What a server keeps with one topic (see the module)."""

    name: str
    msg_type: type[BaseModel]
    write: Callable[[Any], bytes]
    handlers: list[TopicHandler] = field(default_factory=list)
    _description: dict[str, Any] = field(default_factory=dict, repr=False)
    fingerprint: str | None = None
    """Of the message type's full definition, for ``$/topics``; None for a class with no spec."""
    qos_given: bool = False
    """Whether a declaration gave the QoS (else it is the default, which a later one may set)."""
    scopes_given: bool = False
    """Whether a declaration gave scopes (else none, which a later one may set)."""

    @classmethod
    def of(cls, name: str, msg_type: type[BaseModel]) -> TopicEntry:
        if not (isinstance(msg_type, type) and issubclass(msg_type, BaseModel)):
            raise RegistrationError(
                f"the type of the topic {name} must be a message type (such as "
                f"load_message('sensor_msgs/msg/JointState')), not {msg_type!r}"
            )
        definition = full_definition(msg_type)
        digest = None if definition is None else fingerprint(definition)
        return cls(name, msg_type, json_writer(msg_type), fingerprint=digest)

    @property
    def type_name(self) -> str:
        return str(getattr(self.msg_type, "type_name", self.msg_type.__name__))

    def validate(self, message: Any, *, wire: bool = False) -> BaseModel:
        """Build the message from ``message``, or raise InvalidParams with the field paths.

        ``wire``: a peer sent it, and names each field by its JSON name only (see
        :func:`~srvwire.models.validate_wire`)."""
        if type(message) is self.msg_type:
            validated: BaseModel = message
            return validated
        if isinstance(message, BaseModel):
            message = message.model_dump(by_alias=True)
        try:
            return (validate_wire if wire else validate_python)(self.msg_type, message)
        except ValidationError as exc:
            data = error_data(exc)
            for error in data["errors"]:
                error["path"] = (
                    "message"
                    + ("." if error["path"][:1] not in ("", "[") else "")
                    + (error["path"])
                )
            raise InvalidParams(
                f"invalid message for {self.name}: "
                f"{summarize_errors(data['errors'], exc.error_count())}",
                data,
                service=self.name,
            ) from None

    def describe(self, topic: Topic[Any]) -> dict[str, Any]:
        """This topic's entry in ``rpc.discover`` (an OpenRPC method object, marked a topic)."""
        if not self._description:
            self._description.update(
                {
                    "name": self.name,
                    "params": [],
                    "result": {"name": "message", "schema": _standalone_schema(self.msg_type)},
                    "x-srvwire-kind": "topic",
                    "x-srvwire-type": self.type_name,
                    "x-srvwire-definitions": message_definitions(self.msg_type),
                }
            )
            if self.fingerprint is not None:
                self._description["x-srvwire-fingerprint"] = self.fingerprint
        return {
            **self._description,
            "x-srvwire-qos": topic.qos.to_json(),
            "x-srvwire-publish": topic.accepts,
        }


def check_handler(name: str, handler: TopicHandler) -> None:
    """Raise RegistrationError when ``handler`` cannot take one message."""
    if not callable(handler):
        raise RegistrationError(f"the handler for the topic {name} must be callable")
    try:
        inspect.signature(handler).bind(None)
    except TypeError:
        raise RegistrationError(
            f"the handler for the topic {name} must take one argument, the message"
        ) from None
    except ValueError:  # no signature (a builtin): let it be tried
        pass


class Publisher(Generic[M]):
    """Publishes on one topic of a server: what :meth:`srvwire.Server.topic` returns.

    Use it on the server's event loop. :meth:`publish` writes the message once and queues it
    for every subscriber; it never waits for one.
    """

    __slots__ = ("_topic",)

    def __init__(self, topic: Topic[TopicEntry]) -> None:
        self._topic = topic

    @property
    def name(self) -> str:
        return self._topic.name

    @property
    def qos(self) -> QoS:
        return self._topic.qos

    @property
    def subscription_count(self) -> int:
        """How many subscriptions the topic has now (on every connection)."""
        return len(self._topic.subscriptions)

    def publish(self, message: M | Mapping[str, Any]) -> int:
        """Publish ``message`` (the topic's message, or a mapping of its fields); return how
        many subscribers it reached. Raise InvalidParams for a mapping that does not fit."""
        topic = self._topic
        entry = topic.entry
        typed = message if type(message) is entry.msg_type else entry.validate(message)
        return topic.publish(entry.write(typed))

    def __repr__(self) -> str:
        return f"<Publisher {self.name} ({self._topic.entry.type_name})>"
