"""What loading types and filling in a left-out field cost, in several source trees side by side.

Each operation runs in a child process of its own, with ``--src`` first on ``PYTHONPATH``:

* **corpus**: loading every type ``benchmarks/corpus.py`` loads (its figure: a run that loads
  them less one that only lists them);
* **add**: ``AddTwoInts.Request.model_validate_json('{"a": 1, "b": 2}')``, no default made;
* **covariance**: ``PoseWithCovariance.model_validate_json("{}")``, whose fixed array
  ``float64[36] covariance`` is made from its default;
* **uuid**: ``UUID.model_validate_json("{}")``, whose ``uint8[16] uuid`` is made likewise.

The figure is instructions counted by valgrind (per operation: a run of ``3 * --ops`` less one
of ``--ops``, over ``2 * --ops``), which other processes cannot disturb, with
``PYTHONHASHSEED=0``; with ``--cpu``, µs of CPU per operation instead (the minimum of 5).

    python benchmarks/defaults.py --src OLD/src --src src   # OLD: an older checkout
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from corpus import ros_test_interfaces

HERE = Path(__file__).resolve().parent
OPERATIONS = ["corpus", "add", "covariance", "uuid"]
VALGRIND = ["valgrind", "--tool=cachegrind", "--cache-sim=no", "--cachegrind-out-file=/dev/null"]


def operation(name: str) -> Callable[[], Any]:
    """The operation ``name`` (not ``corpus``), its types loaded."""
    from srvwire.loader import load_message, load_service

    if name == "add":
        request = load_service("example_interfaces/srv/AddTwoInts").Request
        return lambda: request.model_validate_json('{"a": 1, "b": 2}')
    cls = load_message(
        "geometry_msgs/msg/PoseWithCovariance"
        if name == "covariance"
        else "unique_identifier_msgs/msg/UUID"
    )
    return lambda: cls.model_validate_json("{}")


def child(name: str, ops: int, cpu: bool) -> None:
    """Run ``name`` ``ops`` times (the corpus: load it when ``ops``); print µs per op."""
    if name == "corpus":
        from srvwire.loader import InterfaceLoader, bundled_interfaces

        ros = ros_test_interfaces()
        loader = InterfaceLoader([bundled_interfaces(), *([ros.parent] if ros else [])])
        names = [type_ for package in loader.packages() for type_ in loader.types(package)]
        started = time.process_time()
        for type_ in names if ops else ():
            loader.load(type_)
        print(json.dumps({"us": (time.process_time() - started) * 1e6}))
        return
    run = operation(name)
    best = float("inf")
    for _ in range(5 if cpu else 1):
        started = time.process_time()
        for _ in range(ops):
            run()
        best = min(best, (time.process_time() - started) / max(ops, 1) * 1e6)
    print(json.dumps({"us": best}))


def spawn(src: str, name: str, ops: int, cpu: bool) -> tuple[float, int]:
    """Run a child on ``src``; return its µs figure and, under valgrind, its instructions."""
    env = {**os.environ, "PYTHONPATH": src, "PYTHONHASHSEED": "0"}
    command = [sys.executable, str(Path(__file__)), "--child", name, "--ops", str(ops)]
    command += ["--cpu"] if cpu else []
    done = subprocess.run(
        command if cpu else [*VALGRIND, *command],
        env=env,
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode != 0:
        raise SystemExit(f"{name} on {src} failed:\n{done.stderr}")
    found = re.search(r"I\s+refs:\s+([0-9,]+)", done.stderr)
    count = int(found[1].replace(",", "")) if found else 0
    return json.loads(done.stdout.splitlines()[-1])["us"], count


def measure(src: str, name: str, ops: int, cpu: bool) -> float:
    """Instructions (or µs of CPU) of one ``name``; the corpus's figure is its whole load."""
    if cpu:
        return spawn(src, name, 1 if name == "corpus" else ops, cpu)[0]
    if name == "corpus":
        return float(spawn(src, name, 1, cpu)[1] - spawn(src, name, 0, cpu)[1])
    return (spawn(src, name, 3 * ops, cpu)[1] - spawn(src, name, ops, cpu)[1]) / (2 * ops)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--src", action="append", help="a source tree (repeatable)")
    parser.add_argument("--ops", type=int, default=3000, help="operations of the shorter run")
    parser.add_argument("--operations", default=",".join(OPERATIONS))
    parser.add_argument("--cpu", action="store_true", help="µs of CPU instead of instructions")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(args.child, args.ops, args.cpu)
        return
    if not args.cpu and shutil.which("valgrind") is None:
        raise SystemExit("valgrind is not on the path: install it, or pass --cpu")
    sources = args.src or [str(HERE.parent / "src")]
    unit = "µs of CPU" if args.cpu else "instructions"
    results: dict[str, dict[str, float]] = {}
    for name in args.operations.split(","):
        results[name] = {src: measure(src, name, args.ops, args.cpu) for src in sources}
        figures = ", ".join(f"{src}: {value:,.0f}" for src, value in results[name].items())
        print(f"{name} ({unit}): {figures}")
    print(json.dumps({"event": "result", "unit": unit, "results": results}))


if __name__ == "__main__":
    main()
