"""srvwire: ROS 2 style services in plain Python, over JSON-RPC 2.0 on WebSockets."""

from srvwire import sync  # the blocking client: srvwire.sync.connect(url)
from srvwire.actions import ClientGoal, GoalHandle, GoalResult
from srvwire.auth import Identity, TokenAuth
from srvwire.client import Client, ServiceInfo, ServiceProxy, Subscription, TopicInfo, connect
from srvwire.dispatch import Context
from srvwire.errors import (
    Cancelled,
    ConnectionLost,
    DeadlineExceeded,
    ErrorCode,
    GoalRejected,
    InterfaceConflictError,
    InterfaceError,
    InterfaceNotFoundError,
    InterfaceSyntaxError,
    InternalError,
    InvalidParams,
    InvalidRequest,
    ParseError,
    PermissionDenied,
    RegistrationError,
    ResourceExhausted,
    RPCError,
    ServiceError,
    ServiceNotFound,
    ServiceUnavailable,
    SrvwireError,
    Unauthenticated,
)
from srvwire.heap import keep_freed_heap
from srvwire.loader import (
    InterfaceLoader,
    default_search_path,
    load_action,
    load_message,
    load_service,
)
from srvwire.models import Action, InfNan, Message, Service, ServiceRequest, TypedService
from srvwire.pubsub import Publisher
from srvwire.server import RunningServer, Server, serve
from srvwire.threads import HandlerThreads
from srvwire.topics import QoS
from srvwire.transports.base import Handshake, Transport
from srvwire.transports.memory import MemoryTransport
from srvwire.typeregistry import TypeRegistry
from srvwire.version import __version__

__all__ = [
    "Action",
    "Cancelled",
    "Client",
    "ClientGoal",
    "ConnectionLost",
    "Context",
    "DeadlineExceeded",
    "ErrorCode",
    "GoalHandle",
    "GoalRejected",
    "GoalResult",
    "HandlerThreads",
    "Handshake",
    "Identity",
    "InfNan",
    "InterfaceConflictError",
    "InterfaceError",
    "InterfaceLoader",
    "InterfaceNotFoundError",
    "InterfaceSyntaxError",
    "InternalError",
    "InvalidParams",
    "InvalidRequest",
    "MemoryTransport",
    "Message",
    "ParseError",
    "PermissionDenied",
    "Publisher",
    "QoS",
    "RPCError",
    "RegistrationError",
    "ResourceExhausted",
    "RunningServer",
    "Server",
    "Service",
    "ServiceError",
    "ServiceInfo",
    "ServiceNotFound",
    "ServiceProxy",
    "ServiceRequest",
    "ServiceUnavailable",
    "SrvwireError",
    "Subscription",
    "TokenAuth",
    "TopicInfo",
    "Transport",
    "TypeRegistry",
    "TypedService",
    "Unauthenticated",
    "__version__",
    "connect",
    "default_search_path",
    "keep_freed_heap",
    "load_action",
    "load_message",
    "load_service",
    "serve",
    "sync",
]
