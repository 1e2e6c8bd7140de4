"""The ``conftest.py`` of a project tested with srvwire's pytest plugin: the server to test.

The plugin comes with srvwire: for each test that asks for ``srvwire_client``, ``srvwire_wire``
or ``srvwire_running``, it serves the server this fixture returns. The tests are in
``testing_with_the_plugin.py``; ``docs/testing.md`` describes every fixture.
"""

from __future__ import annotations

# --8<-- [start:conftest]
import pytest
import robot_state_server

import srvwire


@pytest.fixture
def srvwire_server() -> srvwire.Server:
    return robot_state_server.build_server()  # a new robot for each test


# --8<-- [end:conftest]
