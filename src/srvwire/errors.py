"""Every exception srvwire raises, and the JSON-RPC error-code table.

The tree::

    SrvwireError
    ├── InterfaceError
    │   ├── InterfaceSyntaxError
    │   ├── InterfaceNotFoundError
    │   └── InterfaceConflictError
    ├── RegistrationError
    └── RPCError
        ├── ParseError                  -32700
        ├── InvalidRequest              -32600
        ├── ServiceNotFound             -32601
        ├── InvalidParams               -32602
        ├── InternalError               -32603
        ├── DeadlineExceeded            -32001  (also a TimeoutError)
        ├── Cancelled                   -32002
        ├── ServiceUnavailable          -32003
        │   └── ConnectionLost          -32003  (raised by the client only)
        ├── ResourceExhausted           -32004
        ├── Unauthenticated             -32005
        ├── PermissionDenied            -32006
        ├── GoalRejected                -32007
        └── ServiceError                any code outside -32768..-32000

An :class:`RPCError` is what travels on the wire: it has a ``code``, a ``message``, optional
``data`` and the name of the ``service`` it concerns. :func:`error_from_code` turns a JSON-RPC
error object back into the matching class, so a client raises exactly what the server meant.
"""

from __future__ import annotations

from enum import IntEnum
from pathlib import Path
from typing import Any, ClassVar

__all__ = [
    "Cancelled",
    "ConnectionLost",
    "DeadlineExceeded",
    "ErrorCode",
    "GoalRejected",
    "InterfaceConflictError",
    "InterfaceError",
    "InterfaceNotFoundError",
    "InterfaceSyntaxError",
    "InternalError",
    "InvalidParams",
    "InvalidRequest",
    "ParseError",
    "PermissionDenied",
    "RPCError",
    "RegistrationError",
    "ResourceExhausted",
    "ServiceError",
    "ServiceNotFound",
    "ServiceUnavailable",
    "SrvwireError",
    "Unauthenticated",
    "error_class_for_code",
    "error_from_code",
    "is_reserved_code",
]


class ErrorCode(IntEnum):
    """The JSON-RPC error codes srvwire uses; ``error.data.status`` carries the name."""

    PARSE_ERROR = -32700
    INVALID_REQUEST = -32600
    SERVICE_NOT_FOUND = -32601
    INVALID_PARAMS = -32602
    INTERNAL = -32603
    DEADLINE_EXCEEDED = -32001
    CANCELLED = -32002
    UNAVAILABLE = -32003
    RESOURCE_EXHAUSTED = -32004
    UNAUTHENTICATED = -32005
    PERMISSION_DENIED = -32006
    GOAL_REJECTED = -32007


RESERVED_MIN = -32768
RESERVED_MAX = -32000


def is_reserved_code(code: int) -> bool:
    """Tell whether ``code`` lies in the range JSON-RPC 2.0 reserves for the protocol."""
    return RESERVED_MIN <= code <= RESERVED_MAX


class SrvwireError(Exception):
    """Raised for anything srvwire itself reports; the base of every other class here."""


# --- interface files --------------------------------------------------------------------------


class InterfaceError(SrvwireError):
    """Raised when an interface file or type cannot be read, found or turned into a model."""


class InterfaceSyntaxError(InterfaceError):
    """Raised when an interface file breaks the grammar; it knows the file, line and column."""

    def __init__(self, message: str, *, path: str | Path | None, line: int, column: int) -> None:
        self.message = message
        self.path = str(path) if path is not None else None
        self.line = line
        self.column = column
        super().__init__(message)

    def __str__(self) -> str:
        where = self.path if self.path is not None else "<string>"
        return f"{where}:{self.line}:{self.column}: {self.message}"


class InterfaceNotFoundError(InterfaceError, LookupError):
    """Raised when a package or type is not on the search path; it lists close names."""

    def __init__(self, name: str, message: str, *, candidates: tuple[str, ...] = ()) -> None:
        self.name = name
        self.message = message
        self.candidates = candidates
        super().__init__(message)

    def __str__(self) -> str:
        if not self.candidates:
            return self.message
        return f"{self.message} (did you mean: {', '.join(self.candidates)}?)"


class InterfaceConflictError(InterfaceError):
    """Raised when one type name is given two different definitions; it names both sources."""

    def __init__(self, name: str, first: str, second: str, difference: str) -> None:
        self.name = name
        self.first = first
        self.second = second
        self.difference = difference
        super().__init__(name, first, second, difference)

    def __str__(self) -> str:
        if self.first == self.second:  # one source that changed: a server upgraded, a file
            return (
                f"two different definitions of {self.name} from {self.first}: it changed "
                f"since this process built its class ({self.difference}); a type name has one "
                "definition per process: restart the process to use the new one"
            )
        return (
            f"two different definitions of {self.name}: {self.first} and {self.second} "
            f"({self.difference}); a type name has one definition per process"
        )


# --- registering services ---------------------------------------------------------------------


class RegistrationError(SrvwireError, ValueError):
    """Raised when a service is registered with a bad name, twice, or with an unusable handler."""


# --- remote calls -----------------------------------------------------------------------------


class RPCError(SrvwireError):
    """Raised when a call fails; carries the JSON-RPC ``code``, ``message``, ``data``, service."""

    code: int = ErrorCode.INTERNAL
    status: ClassVar[str] = "ERROR"

    def __init__(
        self,
        message: str,
        data: Any = None,
        *,
        service: str | None = None,
        code: int | None = None,
    ) -> None:
        if code is not None:
            self.code = code
        self.message = message
        self.data = data
        self.service = service
        super().__init__(message)

    def __str__(self) -> str:
        where = f" [{self.service}]" if self.service else ""
        return f"{self.status} ({self.code}){where}: {self.message}"

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(code={self.code}, message={self.message!r}, "
            f"data={self.data!r}, service={self.service!r})"
        )

    def to_error_object(self) -> dict[str, Any]:
        """Build the JSON-RPC ``error`` member for this error."""
        data = self.data
        if self.status != ServiceError.status:
            extra = data if isinstance(data, dict) else ({} if data is None else {"detail": data})
            data = {"status": self.status, **extra}
        error: dict[str, Any] = {"code": int(self.code), "message": self.message}
        if data is not None:
            error["data"] = data
        return error


class ParseError(RPCError):
    """Raised when a message is not JSON."""

    code = ErrorCode.PARSE_ERROR
    status = "PARSE_ERROR"


class InvalidRequest(RPCError):
    """Raised when a message is JSON but not a JSON-RPC 2.0 request."""

    code = ErrorCode.INVALID_REQUEST
    status = "INVALID_REQUEST"


class ServiceNotFound(RPCError):
    """Raised when no service has the name called; ``data.candidates`` lists close names."""

    code = ErrorCode.SERVICE_NOT_FOUND
    status = "SERVICE_NOT_FOUND"


class InvalidParams(RPCError):
    """Raised when a request does not validate; ``errors`` gives each field path and problem."""

    code = ErrorCode.INVALID_PARAMS
    status = "INVALID_PARAMS"

    @property
    def errors(self) -> list[dict[str, Any]]:
        """Each validation problem as ``{"path": ..., "message": ..., "type": ...}``."""
        if isinstance(self.data, dict):
            errors = self.data.get("errors")
            if isinstance(errors, list):
                return [e for e in errors if isinstance(e, dict)]
        return []


class InternalError(RPCError):
    """Raised when the handler failed on the server; the traceback stays in the server log."""

    code = ErrorCode.INTERNAL
    status = "INTERNAL"


class DeadlineExceeded(RPCError, TimeoutError):
    """Raised when the call's deadline passed before a response arrived."""

    code = ErrorCode.DEADLINE_EXCEEDED
    status = "DEADLINE_EXCEEDED"


class Cancelled(RPCError):
    """Raised when the caller cancelled the call."""

    code = ErrorCode.CANCELLED
    status = "CANCELLED"


class ServiceUnavailable(RPCError):
    """Raised when the server is shutting down, unreachable, or a service never appeared."""

    code = ErrorCode.UNAVAILABLE
    status = "UNAVAILABLE"


class ConnectionLost(ServiceUnavailable):
    """Raised when the connection dropped while the call was pending or being sent."""


class ResourceExhausted(RPCError):
    """Raised when the server refused the call: too many calls in flight on its connection.

    Also raised by the client itself, before sending, for a request larger than its
    ``max_message_size`` (``data`` holds ``size`` and ``max_message_size``). An oversized
    message that is sent is not answered with this error: the side that refuses it closes the
    connection with 1009 (message too big), so the client sees :class:`ConnectionLost`.
    """

    code = ErrorCode.RESOURCE_EXHAUSTED
    status = "RESOURCE_EXHAUSTED"


class Unauthenticated(RPCError):
    """Raised when the server wants credentials it did not get, or they expired."""

    code = ErrorCode.UNAUTHENTICATED
    status = "UNAUTHENTICATED"


class PermissionDenied(RPCError):
    """Raised when the connection's identity lacks a scope the service requires."""

    code = ErrorCode.PERMISSION_DENIED
    status = "PERMISSION_DENIED"


class GoalRejected(RPCError):
    """Raised when an action's server refused a goal; the message says why.

    An action's handler (or its ``accept`` function) raises it to refuse the goal it was
    given, before or after it started; the client's ``send_goal`` raises it back.
    """

    code = ErrorCode.GOAL_REJECTED
    status = "GOAL_REJECTED"


class ServiceError(RPCError):
    """Raised by a handler to send an application error with its own code and data."""

    status = "APPLICATION_ERROR"

    def __init__(
        self,
        code: int,
        message: str,
        data: Any = None,
        *,
        service: str | None = None,
    ) -> None:
        if isinstance(code, bool) or not isinstance(code, int):
            raise TypeError(f"ServiceError code must be an int, not {type(code).__name__}")
        if is_reserved_code(code):
            raise ValueError(
                f"ServiceError code {code} lies in {RESERVED_MIN}..{RESERVED_MAX}, "
                "which JSON-RPC reserves; pick a code outside it"
            )
        super().__init__(message, data, service=service, code=code)

    def __str__(self) -> str:
        where = f" [{self.service}]" if self.service else ""
        return f"application error ({self.code}){where}: {self.message}"

    def __reduce__(self) -> tuple[Any, ...]:
        return (type(self), (self.code, self.message, self.data), {"service": self.service})


_BY_CODE: dict[int, type[RPCError]] = {
    cls.code: cls
    for cls in (
        ParseError,
        InvalidRequest,
        ServiceNotFound,
        InvalidParams,
        InternalError,
        DeadlineExceeded,
        Cancelled,
        ServiceUnavailable,
        ResourceExhausted,
        Unauthenticated,
        PermissionDenied,
        GoalRejected,
    )
}


def error_class_for_code(code: int) -> type[RPCError]:
    """Return the class that stands for ``code``: a table entry, or ServiceError/RPCError."""
    known = _BY_CODE.get(code)
    if known is not None:
        return known
    return RPCError if is_reserved_code(code) else ServiceError


def error_from_code(
    code: int, message: str, data: Any = None, *, service: str | None = None
) -> RPCError:
    """Build the exception for a JSON-RPC error object received from a peer."""
    cls = error_class_for_code(code)
    if cls is ServiceError:
        return ServiceError(code, message, data, service=service)
    if isinstance(data, dict) and data.get("status") == cls.status and cls is not RPCError:
        data = {k: v for k, v in data.items() if k != "status"} or None
    return cls(message, data, service=service, code=code)
