"""A field named like a Python keyword: ``from`` in the interface file, ``from_`` in Python.

Run it with ``python examples/field_names.py``; it prints each step and checks what it shows.
"""

from __future__ import annotations

from typing import Any

from srvwire.models import build_service
from srvwire.parser import parse_service

MOVE_SRV = """\
uint32 from  # the waypoint to leave
uint32 to    # the waypoint to reach
---
bool ok
"""

# Built at run time from the text above, so a type checker only knows it is a service class;
# `srvwire gen` writes the same classes as a module that a type checker reads.
Move: Any = build_service(parse_service(MOVE_SRV, "my_robot", "Move"))

# --8<-- [start:names]
move = Move.Request.model_validate({"from": 3})  # JSON and dicts use the file's name
assert move.from_ == 3  # Python uses from_
assert Move.Request(from_=3) == move  # either name works as input
assert move.model_dump() == {"from": 3, "to": 0}  # output uses the file's name
# --8<-- [end:names]

print(move.model_dump_json())
