"""srvwire: ROS 2 style services in plain Python, over JSON-RPC 2.0 on WebSockets."""

from srvwire.errors import (
    Cancelled,
    ConnectionLost,
    DeadlineExceeded,
    ErrorCode,
    InterfaceError,
    InterfaceNotFoundError,
    InterfaceSyntaxError,
    InternalError,
    InvalidParams,
    InvalidRequest,
    ParseError,
    RegistrationError,
    ResourceExhausted,
    RPCError,
    ServiceError,
    ServiceNotFound,
    ServiceUnavailable,
    SrvwireError,
    Unauthenticated,
)

__version__ = "0.1.0"

__all__ = [
    "Cancelled",
    "ConnectionLost",
    "DeadlineExceeded",
    "ErrorCode",
    "InterfaceError",
    "InterfaceNotFoundError",
    "InterfaceSyntaxError",
    "InternalError",
    "InvalidParams",
    "InvalidRequest",
    "ParseError",
    "RPCError",
    "RegistrationError",
    "ResourceExhausted",
    "ServiceError",
    "ServiceNotFound",
    "ServiceUnavailable",
    "SrvwireError",
    "Unauthenticated",
    "__version__",
]
