"""Time how long srvwire takes to load every interface it can see, in a fresh process.

The corpus is srvwire's bundled ``interfaces/`` plus ROS 2's own test interfaces
(``shared/ros_test_interfaces`` beside the checkout, or ``SRVWIRE_ROS_TEST_INTERFACES``) when
they are there. Every type of every package is built: parsed, cross-references resolved, pydantic
classes created. Prints ``{"event": "result", "import_s": ..., "load_s": ..., "types": N}``.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

from common import ROOT, emit


def ros_test_interfaces() -> Path | None:
    configured = os.environ.get("SRVWIRE_ROS_TEST_INTERFACES")
    folder = Path(configured) if configured else ROOT.parent / "shared" / "ros_test_interfaces"
    return folder if (folder / "msg").is_dir() else None


def main() -> None:
    started = time.perf_counter()
    from srvwire.loader import InterfaceLoader, bundled_interfaces

    imported = time.perf_counter()
    search_path = [bundled_interfaces()]
    ros = ros_test_interfaces()
    if ros is not None:
        # The corpus folder is itself a package (its name is the package name), so the search
        # path names the folder that holds it.
        search_path.append(ros.parent)
    loader = InterfaceLoader(search_path)
    names = [name for package in loader.packages() for name in loader.types(package)]
    for name in names:
        loader.load(name)
    loaded = time.perf_counter()
    emit(
        "result",
        import_s=imported - started,
        load_s=loaded - imported,
        types=len(names),
        ros_corpus=ros is not None,
    )


if __name__ == "__main__":
    main()
