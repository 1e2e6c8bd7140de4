"""What the typed sides share: the generated ``RobotStateQuery`` and how a client checks a reply."""

from __future__ import annotations

from typing import Any

from srvwire.loader import load_service

from common import SRV_TYPE

RobotStateQuery = load_service(SRV_TYPE)


def make_request(fields: dict[str, Any]) -> Any:
    """Return the typed request a caller passes."""
    return RobotStateQuery.Request(**fields)


def values_of(reply: Any) -> int:
    """Return how many values a reply holds; exit unless it is a typed ``Response``."""
    if not isinstance(reply, RobotStateQuery.Response):
        raise SystemExit(f"expected a typed {SRV_TYPE} response, got {type(reply).__name__}")
    values: list[float] = reply.model_dump()["values"]
    return len(values)
