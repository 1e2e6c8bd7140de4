"""The benchmark harness runs both implementations end to end and reports what they did.

Nothing here judges speed (timing claims live in ``benchmarks/``, as ratios): a quick run must
measure srvwire and the baseline (or the floor) on the same workloads, with the same number of
calls and as many values in every large reply, and report medians and ratios that follow from its
own runs.
"""

from __future__ import annotations

import asyncio
import functools
import importlib
import importlib.util
import json
import os
import statistics
import subprocess
import sys
from collections.abc import Iterator
from contextlib import AsyncExitStack
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest
from picows import ws_create_server
from websockets.asyncio.client import connect
from websockets.asyncio.server import serve

from support import ROOT, run_benchmark, scaled

RUN = ROOT / "benchmarks" / "run.py"


def harness(*argv: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, str(RUN), *argv],
        capture_output=True,
        text=True,
        timeout=scaled(300),
        cwd=ROOT,
        check=False,
    )


def large_reply_bytes() -> int:
    spec = importlib.util.spec_from_file_location("bench_common", ROOT / "benchmarks" / "common.py")
    assert spec is not None and spec.loader is not None
    common = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(common)
    size: int = common.large_reply_bytes()
    return size


def check_quick_runs(runs: list[dict[str, Any]], impls: list[str]) -> None:
    """Every implementation ran quick W1 and W4 alike: the calls, the CPU, the large replies."""
    for workload, calls in (("W1", 20_000 // 20), ("W4", 3)):
        mine = [run for run in runs if run["workload"] == workload]
        assert sorted(run["impl"] for run in mine) == impls
        assert all(run["calls"] == calls for run in mine), mine
        assert all(run["client_cpu_s"] > 0 and run["server_cpu_s"] > 0 for run in mine)
    large = [run for run in runs if run["workload"] == "W4"]
    assert [run["reply_values"] for run in large] == [100_000] * len(impls)  # counted in each
    assert [run["reply_bytes"] for run in large] == [large_reply_bytes()] * len(impls)  # MB/s


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict[str, Any], str]:
    # Other processes (this suite) may be busy: do not wait for a quiet machine here.
    out: Path = tmp_path_factory.mktemp("bench") / "report.json"
    done = harness(
        "--quick", "--repeat", "2", "--workloads", "W1,W4", "--loop", "asyncio",
        "--no-pin", "--max-other-load", "64", "--json", str(out),
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(out.read_text()), done.stdout


def test_both_implementations_run_every_workload_alike(
    quick_run: tuple[dict[str, Any], str],
) -> None:
    report, _ = quick_run
    assert report["repeat"] == 2 and report["quick"] is True
    check_quick_runs(report["asyncio"]["runs"], ["baseline"] * 2 + ["srvwire"] * 2)


def test_medians_and_ratios_follow_from_the_runs(quick_run: tuple[dict[str, Any], str]) -> None:
    report, table = quick_run
    runs = report["asyncio"]["runs"]
    (rate,) = [
        row
        for row in report["asyncio"]["summary"]
        if (row["workload"], row["metric"]) == ("W1", "calls/s")
    ]
    for impl in ("baseline", "srvwire"):
        rates = [
            run["calls"] / run["elapsed_s"]
            for run in runs
            if (run["workload"], run["impl"]) == ("W1", impl)
        ]
        assert sorted(rate["runs"][impl]) == pytest.approx(sorted(rates))
        assert rate[impl] == pytest.approx(statistics.median(rates))
    assert rate["ratio"] == pytest.approx(rate["srvwire"] / rate["baseline"])
    assert "== asyncio event loop: medians of 2 run(s), quick" in table
    assert f"{rate['ratio']:.2f}" in table


def test_the_floor_and_the_json_rpc_peer_run_every_workload_like_srvwire(tmp_path: Path) -> None:
    # The peer (aiohttp-json-rpc serving, jsonrpc-websocket calling) makes the same calls and
    # gets the same replies as srvwire, so a full run's ratios against it compare like with like.
    # One pass for both pairs: srvwire is measured once, and both tables read that run.
    out = tmp_path / "report.json"
    done = harness(
        "--quick", "--repeat", "1", "--workloads", "W1,W4", "--loop", "asyncio",
        "--compare", "floor,srvwire", "--compare", "peer,srvwire",
        "--no-pin", "--max-other-load", "64", "--json", str(out),
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads(out.read_text())["asyncio"]
    check_quick_runs(report["runs"], ["floor", "peer", "srvwire"])
    assert list(report["summaries"]) == ["floor,srvwire", "peer,srvwire"]
    assert "ratio = srvwire / floor" in done.stdout
    assert "ratio = srvwire / peer" in done.stdout


def test_the_picows_pairs_run_every_workload_alike_from_the_same_runs(tmp_path: Path) -> None:
    out = tmp_path / "report.json"
    done = harness(
        "--quick", "--repeat", "1", "--workloads", "W1,W4", "--loop", "asyncio",
        "--compare", "picows,srvwire-picows", "--compare", "baseline,srvwire-picows",
        "--no-pin", "--max-other-load", "64", "--json", str(out),
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads(out.read_text())["asyncio"]
    # Three implementations, each measured once: both tables read srvwire-picows' one run.
    check_quick_runs(report["runs"], ["baseline", "picows", "srvwire-picows"])
    assert list(report["summaries"]) == ["picows,srvwire-picows", "baseline,srvwire-picows"]
    assert report["summary"] == report["summaries"]["picows,srvwire-picows"]
    rates = {
        pair: next(row for row in rows if (row["workload"], row["metric"]) == ("W1", "calls/s"))
        for pair, rows in report["summaries"].items()
    }
    assert (
        rates["picows,srvwire-picows"]["srvwire-picows"]
        == rates["baseline,srvwire-picows"]["srvwire-picows"]
    )
    assert "ratio = srvwire-picows / picows" in done.stdout
    assert "ratio = srvwire-picows / baseline" in done.stdout


def test_a_bad_choice_is_refused_before_anything_runs() -> None:
    done = harness("--compare", "baseline,nothing")
    assert done.returncode == 2
    assert (
        "--compare takes two of: baseline, floor, srvwire, picows, srvwire-picows, peer"
        in done.stderr
    )
    assert "srvwire-picows-heap, floor-picows, floor-picows-bare" in done.stderr
    done = harness("--workloads", "W9")
    assert done.returncode == 2 and "unknown workload 'W9'" in done.stderr


def printed_ratio_agrees(ratio: str, numerator: str, denominator: str) -> bool:
    """Whether ``ratio`` can be ``numerator / denominator`` rounded, each as printed: the
    true values lie within half a unit of each one's last printed digit, so the recomputed
    ratio is an interval, and the printed one must round a value inside it. (Recomputing from
    the printed figures alone is off by more than the ratio's last digit when a figure is
    small: rates of 110.4 and 9.99 messages/s print as 110 and 10, their ratio as 11.05.)"""

    def bounds(cell: str) -> tuple[float, float]:
        digits = len(cell.partition(".")[2])
        value, half = float(cell.replace(",", "")), 0.5 * 10.0**-digits
        return value - half, value + half

    low, high = bounds(ratio)
    num_low, num_high = bounds(numerator)
    den_low, den_high = bounds(denominator)
    assert den_low > 0, denominator
    return num_low / den_high <= high + 1e-9 and num_high / den_low >= low - 1e-9


def test_printed_ratio_agrees_within_the_printed_precision_only() -> None:
    assert printed_ratio_agrees("11.05", "110", "10")  # 110.4 / 9.99
    assert not printed_ratio_agrees("11.70", "110", "10")  # past 110.5 / 9.5 = 11.63
    assert printed_ratio_agrees("11.06", "1,100", "100")  # 1,100.5 / 99.5 = 11.06
    assert not printed_ratio_agrees("11.07", "1,100", "100")
    assert not printed_ratio_agrees("10.93", "1,100", "100")  # below 1,099.5 / 100.5 = 10.94
    assert printed_ratio_agrees("2.00", "1.0", "0.5")  # 0.95 / 0.55 to 1.05 / 0.45
    assert not printed_ratio_agrees("2.40", "1.0", "0.5")


def test_the_topic_benchmark_runs_both_sides() -> None:
    # A smoke run: both sides deliver every message to 1 and to 10 subscribers (srvwire's
    # side asserts that none was dropped); the figures themselves are not judged here.
    result = run_benchmark(ROOT / "benchmarks" / "topics.py", "--quick")
    lines = result.stdout.splitlines()
    rows = [line.split() for line in lines[2:4]]
    assert [row[0] for row in rows] == ["1", "10"], result.stdout
    for row in rows:
        raw, ours, ratio = row[1:4]
        assert float(raw.replace(",", "")) > 0 and float(ours.replace(",", "")) > 0
        assert printed_ratio_agrees(ratio, ours, raw), row
        assert row[4:] == [f"({ratio})"]  # one run: the ratio of each run is the median
    # CPU per message on each side, and the ratios that follow from it.
    cpu = [line.split() for line in lines[7:9]]
    assert [row[0] for row in cpu] == ["1", "10"], result.stdout
    for row in cpu:
        raw_client, our_client, client_ratio, raw_server, our_server, server_ratio = row[1:]
        assert min(float(cell) for cell in (raw_client, our_client, raw_server, our_server)) > 0
        assert printed_ratio_agrees(client_ratio, our_client, raw_client), row
        assert printed_ratio_agrees(server_ratio, our_server, raw_server), row
    assert "other processes kept" in lines[-2], result.stdout


@pytest.mark.parametrize(
    ("option", "error"),
    [
        (["--messages", "10000"], "--messages must be from 1 to 9990"),
        (["--messages", "0"], "--messages must be from 1 to 9990"),
        (["--subscribers", "1,x"], "--subscribers takes positive integers, such as 1,10"),
        (["--subscribers", "0"], "--subscribers takes positive integers, such as 1,10"),
    ],
)
def test_the_topic_benchmark_refuses_what_it_cannot_run(option: list[str], error: str) -> None:
    result = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "topics.py"), *option],
        capture_output=True,
        text=True,
        timeout=scaled(60),
        cwd=ROOT,
        check=False,
    )
    assert result.returncode == 2
    assert error in result.stderr
    assert "messages of about 1 KB" not in result.stdout  # nothing was measured


def test_the_blocking_client_benchmark_measures_each_way_of_calling(tmp_path: Path) -> None:
    out = tmp_path / "sync.json"
    result = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "sync_client.py"), "--quick", "--json", out],
        capture_output=True,
        text=True,
        timeout=scaled(300),
        cwd=ROOT,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    rows = json.loads(out.read_text(encoding="utf-8"))
    assert [row["measurement"] for row in rows] == [
        "async",
        "sync",
        "async, 4 tasks",
        "sync, 4 threads",
        "sync, a connection per call",
        "the hand-off alone, no call",
    ]
    [baseline] = [row["us_per_call"] for row in rows if row["measurement"] == "async"]
    for row in rows:
        assert row["rounds"] == 1
        assert row["ratio_to_async"] == pytest.approx(row["us_per_call"] / baseline)
        assert row["calls_per_second"] == pytest.approx(1e6 / row["us_per_call"])
        assert f"{row['measurement']:<30} {row['us_per_call']:>12.1f}" in result.stdout


def test_the_servers_path_in_one_process_answers_every_call(tmp_path: Path) -> None:
    # A smoke run of both modes; the script itself exits unless every call got its reply.
    script = ROOT / "benchmarks" / "server_path.py"
    result = run_benchmark(script, "--calls", "300", "--repeat", "2", "--json")
    rows = [json.loads(line) for line in result.stdout.splitlines()]
    assert [row["mode"] for row in rows] == ["pipelined", "one-by-one"]
    for row in rows:
        assert 0 < row["min_us"] <= row["median_us"]


def test_the_servers_path_counts_the_python_steps_of_a_call() -> None:
    # --steps: the bytecode instructions each function runs per call, exactly. A call read in
    # one pass runs the call runner, and looks its service up in C, with no step of its own.
    script = ROOT / "benchmarks" / "server_path.py"
    options = ["--steps", "--calls", "200", "--mode", "one-by-one", "--push", "--json"]
    [row] = [json.loads(line) for line in run_benchmark(script, *options).stdout.splitlines()]
    assert row["mode"] == "one-by-one"
    steps = row["steps"]
    assert {"serving.py:run_call", "session.py:_admit", "models.py:read"} <= set(steps)
    assert all(n >= 0.5 for n in steps.values())
    assert "dispatch.py:get" not in steps


@pytest.mark.parametrize(
    ("options", "shapes"),
    [
        ([], ["pipelined", "sequential"]),
        (["--push"], ["pipelined", "sequential"]),
        (["--proxy", "--shapes", "sequential,fan-in"], ["sequential", "fan-in"]),
        (["--server", "websockets"], ["pipelined", "sequential"]),
    ],
    ids=["recv", "push", "proxy-fan-in", "server"],
)
def test_the_client_path_benchmark_compares_source_trees(
    options: list[str], shapes: list[str]
) -> None:
    # A smoke run of the in-process client benchmark, the same tree twice: every call got
    # its typed reply (the child asserts it), and each tree has a figure and a ratio. With
    # --server, the calls go to a real server over the transport, which is stopped after.
    # Ten calls of warm-up on each connection, not 200: fan-in's 100 connections each make them.
    src = str(ROOT / "src")
    sources = ["--repeat", "1", "--warmup", "10", "--src", src, "--src", src, *options]
    result = run_benchmark(ROOT / "benchmarks" / "client_path.py", "--calls", "800", *sources)
    lines = result.stdout.splitlines()
    assert [line.split(" ")[0] for line in lines if not line.startswith(" ")] == shapes
    rows = [line.split() for line in lines if line.startswith(" ")]
    assert len(rows) == 4
    for row in rows:
        assert float(row[0]) > 0 and row[1] == "ratio" and row[3] == src
    assert rows[0][2] == rows[2][2] == "1.000"


def test_the_client_path_benchmark_measures_the_raw_client_beside() -> None:
    # --raw adds the harness's raw websockets client as one more row, calling the same real
    # server in the same shape (its child asserts every reply); here with the heap kept and
    # on uvloop, which the child must have been able to do.
    src = str(ROOT / "src")
    options = ["--calls", "800", "--repeat", "1", "--warmup", "10", "--src", src,
               "--server", "websockets", "--shapes", "fan-in", "--raw", "--keep-heap",
               "--loop", "uvloop"]  # fmt: skip
    result = run_benchmark(ROOT / "benchmarks" / "client_path.py", *options)
    lines = result.stdout.splitlines()
    assert [line.split(" ")[0] for line in lines if not line.startswith(" ")] == ["fan-in"]
    rows = [line.split() for line in lines if line.startswith(" ")]
    assert [row[3:-1] for row in rows] == [[src], ["raw", "websockets"]]
    assert all(float(row[0]) > 0 and row[1] == "ratio" for row in rows)


def test_the_large_reply_steps_agree_both_ways_and_are_measured() -> None:
    # Each way runs in a process of its own, which exits unless both ways make the same.
    script = ROOT / "benchmarks" / "large_path.py"
    for keep in ([], ["--keep-heap"]):
        result = run_benchmark(script, "--calls", "2", *keep)
        rows = [line.split() for line in result.stdout.splitlines()[2:]]
        assert [row[:2] for row in rows] == [
            ["write", "two-step"],
            ["write", "one-pass"],
            ["read", "slice"],
            ["read", "whole"],
            ["carry", "websockets"],
            ["carry", "srvwire"],
        ]
        assert all(float(row[2]) >= 0 and float(row[3]) > 0 for row in rows)


def test_the_deadline_cost_benchmark_measures_every_way_of_waiting() -> None:
    # A smoke run: each way of waiting ran in its child (each awaited its future) and has a
    # figure, the ones after the first beside what they cost more than awaiting alone.
    options = ["--cpu", "--calls", "200", "--repeat", "1"]
    result = run_benchmark(ROOT / "benchmarks" / "deadline_cost.py", *options)
    header, *lines = result.stdout.splitlines()
    assert header.startswith("Python 3.") and "µs of CPU per await" in header
    rows = [line.split() for line in lines]
    assert [row[0] for row in rows] == ["await", "wait_for", "timeout", "timer", "wait_for-done"]
    for row in rows:
        assert float(row[1]) > 0 and row[2] == "extra"
    assert float(rows[0][3]) == 0.0


def test_the_typed_floor_on_picows_runs_every_workload_with_and_without_its_deadline(
    tmp_path: Path,
) -> None:
    # One pass of both: the typed floor on picows, each wait under asyncio.wait_for, and the
    # same awaiting its futures bare; each makes every call and gets every typed reply.
    out = tmp_path / "report.json"
    done = harness(
        "--quick", "--repeat", "1", "--workloads", "W1,W2,W3,W4", "--loop", "asyncio",
        "--compare", "floor-picows,floor-picows-bare",
        "--no-pin", "--max-other-load", "64", "--json", str(out),
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    report = json.loads(out.read_text())["asyncio"]
    impls = ["floor-picows", "floor-picows-bare"]
    check_quick_runs(report["runs"], impls)
    pipelined = [run for run in report["runs"] if run["workload"] == "W2"]
    assert [run["calls"] for run in pipelined] == [100_000 // 20] * 2
    fan_in = [run for run in report["runs"] if run["workload"] == "W3"]
    assert sorted(run["impl"] for run in fan_in) == impls
    assert all(run["calls"] > 0 and run["server_cpu_s"] > 0 for run in fan_in)
    assert list(report["summaries"]) == ["floor-picows,floor-picows-bare"]
    assert "ratio = floor-picows-bare / floor-picows" in done.stdout


def test_the_bare_typed_floor_on_picows_is_the_floor_with_its_deadline_switched_off(
    floors: dict[str, ModuleType], monkeypatch: pytest.MonkeyPatch
) -> None:
    run, client = floors["run"], floors["floor_picows_client"]
    server, script, options = run.IMPLEMENTATIONS["floor-picows-bare"]
    assert (server, script) == run.IMPLEMENTATIONS["floor-picows"][:2]
    assert options == ("--no-deadline",) and run.IMPLEMENTATIONS["floor-picows"][2] == ()
    command = ["floor_picows_client.py", "--url", "ws://127.0.0.1:1", "--workload", "W1"]
    monkeypatch.setattr(sys, "argv", command)
    assert client.deadline_asked()
    monkeypatch.setattr(sys, "argv", [*command, *options])
    assert not client.deadline_asked()
    # The corked pair: the same scripts, both sides told --cork (the server holds a read's
    # replies, the client a turn's calls), the second without its deadline.
    for name, deadline in (("floor-picows-corked", True), ("floor-picows-corked-bare", False)):
        server_script, client_script, options = run.IMPLEMENTATIONS[name]
        assert (server_script, client_script) == (server, script)
        monkeypatch.setattr(sys, "argv", [*command, *options])
        assert client.asked().cork and client.deadline_asked() == deadline


async def test_the_harness_samples_the_load_only_where_the_limit_can_be_passed(
    floors: dict[str, ModuleType], monkeypatch: pytest.MonkeyPatch
) -> None:
    # The smoke runs above give --max-other-load 64: no machine is busier than its CPUs, so the
    # harness measures at once instead of sampling /proc/stat over a window before each run.
    run = floors["run"]
    samples: list[float] = []

    def quiet_machine() -> float:
        samples.append(0.0)
        return 0.0

    monkeypatch.setattr(run, "machine_busy_seconds", quiet_machine)
    monkeypatch.setattr(run, "QUIET_WINDOW", 0.001)
    cpus = os.cpu_count() or 1
    await run.wait_for_quiet(cpus + 0.5, "smoke")
    assert samples == []
    await run.wait_for_quiet(cpus, "every CPU")  # a limit that can be reached: sampled
    assert len(samples) == 2  # one window of a quiet machine: before and after
    await run.wait_for_quiet(0.25, "quiet")
    assert len(samples) == 4


@pytest.fixture
def floors(monkeypatch: pytest.MonkeyPatch) -> Iterator[dict[str, ModuleType]]:
    """The floor's server and the typed floor on picows' server and client, imported from
    benchmarks/ as its scripts import one another, and forgotten afterwards."""
    folder = ROOT / "benchmarks"
    monkeypatch.syspath_prepend(str(folder))
    names = (
        "floor_server", "floor_picows_server", "floor_picows_client",
        "picows_server", "picows_client", "run",
    )  # fmt: skip
    yield {name: importlib.import_module(name) for name in names}
    for name, module in list(sys.modules.items()):
        if Path(getattr(module, "__file__", None) or "/").parent == folder:
            del sys.modules[name]


AFTER = '{"jsonrpc":"2.0","id":"after","method":"/get_robot_state","params":{}}'
"""A call sent after each message: the replies before its own are that message's."""
FLOOR_ERRORS = [
    ("not json", [-32700]),
    ("[]", []),  # a batch: out of the floor's scope, no reply
    ('{"jsonrpc":"2.0","method":"/get_robot_state"}', []),  # a notification
    ('{"jsonrpc":"2.0","id":[1],"method":"/get_robot_state"}', [-32600]),
    ('{"jsonrpc":"1.0","id":1,"method":"/get_robot_state"}', [-32600]),
    ('{"jsonrpc":"2.0","id":"a\\"b","method":"/nothing"}', [-32601]),
    ('{"jsonrpc":"2.0","id":2,"method":"/get_robot_state","params":[1]}', [-32602]),
    ('{"jsonrpc":"2.0","id":3,"method":"get_robot_state","params":{"_meta":1}}', [-32602]),
    ('{"jsonrpc":"2.0","id":4,"method":"/get_robot_state","params":{"_meta":{"timeout":-1}}}',
     [-32602]),
    ('{"jsonrpc":"2.0","id":5,"method":"/get_robot_state","params":{"query_type":5}}', [-32602]),
    ('{"jsonrpc":"2.0","id":6,"method":"/get_robot_state","params":{"_meta":{"timeout":0}}}',
     [-32001]),  # its deadline has passed once the params are validated
    ('{"jsonrpc":"2.0","id":null,"method":"/get_robot_state","params":{"query_type":"x"}}', [0]),
]  # fmt: skip


async def exchange(url: str, messages: list[str]) -> list[list[bytes]]:
    """Send each message, then AFTER; return the replies each message got, as sent."""
    got: list[list[bytes]] = []
    async with connect(url, compression=None) as websocket:
        for message in messages:
            await websocket.send(message)
            await websocket.send(AFTER)
            replies: list[bytes] = []
            while json.loads(reply := await websocket.recv(decode=False)).get("id") != "after":
                replies.append(reply)
            got.append(replies)
    return got


@pytest.mark.parametrize("cork", [False, True], ids=["each reply alone", "corked"])
async def test_the_typed_floor_on_picows_answers_every_message_as_the_floor_does(
    floors: dict[str, ModuleType], cork: bool
) -> None:
    messages = [message for message, _ in FLOOR_ERRORS]
    floor = floors["floor_server"]
    async with serve(floor.respond, "127.0.0.1", 0, compression=None) as server:
        port = next(iter(server.sockets)).getsockname()[1]
        on_websockets = await exchange(f"ws://127.0.0.1:{port}", messages)
    accept = functools.partial(floors["floor_picows_server"].accept, cork=cork)
    picows_server = await ws_create_server(accept, "127.0.0.1", 0)
    try:
        port = picows_server.sockets[0].getsockname()[1]
        on_picows = await exchange(f"ws://127.0.0.1:{port}", messages)
    finally:
        picows_server.close()
        await picows_server.wait_closed()
    assert on_picows == on_websockets  # byte for byte
    codes = [
        [json.loads(reply).get("error", {"code": 0})["code"] for reply in replies]
        for replies in on_picows
    ]
    assert codes == [expected for _, expected in FLOOR_ERRORS]
    assert json.loads(on_picows[-1][0])["result"]["values"] == [
        1.0 / 3.0, -2.718281828459045, 0.001, 3.141592653589793, 98.5
    ]  # fmt: skip


async def test_the_typed_floor_on_picows_finishes_a_waiting_handler_and_deadlines_its_waits(
    floors: dict[str, ModuleType], monkeypatch: pytest.MonkeyPatch
) -> None:
    floor, client = floors["floor_server"], floors["floor_picows_client"]
    picows_server = floors["floor_picows_server"]
    arrived, release = asyncio.Event(), asyncio.Event()

    async def held(request: Any) -> Any:
        # The benchmark's handler, except that a call for the frame "hold" waits to be let go,
        # and its reply holds one value (the others' hold five): a reply that reached the
        # wrong call would show.
        response = await floor.get_robot_state(request)
        if request.target_frame == "hold":
            arrived.set()
            await release.wait()
            return response.model_copy(update={"values": response.values[:1]})
        return response

    # What the server schedules: a task only for an answer whose handler waits (the rest of
    # it, in floor_picows_server.finish); an answer that does not is sent inside on_ws_frame.
    tasks: list[Any] = []
    ensure_future = asyncio.ensure_future

    def counted(awaitable: Any) -> Any:
        if getattr(awaitable, "cr_code", None) is picows_server.finish.__code__:
            tasks.append(awaitable)
        return ensure_future(awaitable)

    monkeypatch.setattr(picows_server.asyncio, "ensure_future", counted)

    robot_state = floor.ROBOT_STATE
    monkeypatch.setitem(
        floor.SERVICES, "/get_robot_state",
        floor.Service(robot_state.validate, held, robot_state.serialize),
    )  # fmt: skip
    held_request = client.make_request({"query_type": "position", "target_frame": "hold"})
    request = client.make_request({"query_type": "position", "target_frame": ""})
    server = await ws_create_server(picows_server.accept, "127.0.0.1", 0)
    url = f"ws://127.0.0.1:{server.sockets[0].getsockname()[1]}"
    # A deadline far shorter than the held handler's wait: only a wait without one gets the
    # held reply. Above zero, so that wait_for arms its timer and the timer ends the wait.
    monkeypatch.setattr(client, "CALL_TIMEOUT", 0.05)
    try:
        async with AsyncExitStack() as stack:
            # Bare waits: the server answers another call while the held handler waits, then
            # finishes the held one once it is let go.
            call = await client.adapter(deadline=False).open(url, stack)
            assert client.values_of(await call(request)) == 5
            assert tasks == []  # answered inside the callback
            waiting = asyncio.ensure_future(call(held_request))
            await arrived.wait()
            assert len(tasks) == 1  # the held answer, finished by a task
            assert client.values_of(await call(request)) == 5
            assert not waiting.done()
            release.set()
            assert client.values_of(await waiting) == 1
            assert len(tasks) == 1
            # Waits under asyncio.wait_for: a reply later than the deadline is a TimeoutError,
            # and that reply, when it comes, is dropped without disturbing the next call.
            arrived.clear()
            release.clear()
            call = await client.adapter(deadline=True).open(url, stack)
            with pytest.raises(TimeoutError):
                await call(held_request)
            await arrived.wait()
            release.set()
            monkeypatch.setattr(client, "CALL_TIMEOUT", 30.0)
            assert client.values_of(await call(request)) == 5
            assert client.values_of(await call(request)) == 5
    finally:
        server.close()
        await server.wait_closed()


def count_writes(
    floors: dict[str, ModuleType], monkeypatch: pytest.MonkeyPatch
) -> tuple[list[int], list[int]]:
    """Count each write the holding caller and responder make (raw picows' with ``--cork``, and
    the typed floor's, which build on them): the client's and the server's, each as the
    messages it holds (a lone message sent through picows' own send counts as one)."""
    client_writes: list[int] = []
    server_writes: list[int] = []
    caller = floors["picows_client"].HoldingCaller
    responder = floors["picows_server"].HoldingResponder
    caller_flush, responder_flush = caller.flush, responder.flush

    def counted_caller_flush(self: Any) -> None:
        if self._held:
            client_writes.append(len(self._held))
        caller_flush(self)

    def counted_responder_flush(self: Any, transport: Any) -> None:
        if self._held:
            server_writes.append(len(self._held) // 2)  # a header and a reply each
        responder_flush(self, transport)

    monkeypatch.setattr(caller, "flush", counted_caller_flush)
    monkeypatch.setattr(responder, "flush", counted_responder_flush)
    return client_writes, server_writes


async def test_the_corked_typed_floor_on_picows_writes_a_turns_calls_and_a_reads_replies_at_once(
    floors: dict[str, ModuleType], monkeypatch: pytest.MonkeyPatch
) -> None:
    floor = floors["floor_server"]
    client, picows_server = floors["floor_picows_client"], floors["floor_picows_server"]

    async def echoed(request: Any) -> Any:
        # The benchmark's handler, whose reply names the frame its request asked for: a reply
        # that reached the wrong call would show.
        response = await floor.get_robot_state(request)
        return response.model_copy(update={"message": request.target_frame})

    robot_state = floor.ROBOT_STATE
    monkeypatch.setitem(
        floor.SERVICES, "/get_robot_state",
        floor.Service(robot_state.validate, echoed, robot_state.serialize),
    )  # fmt: skip
    client_writes, server_writes = count_writes(floors, monkeypatch)
    accept = functools.partial(picows_server.accept, cork=True)
    server = await ws_create_server(accept, "127.0.0.1", 0)
    url = f"ws://127.0.0.1:{server.sockets[0].getsockname()[1]}"
    frames = [f"frame{index}" for index in range(8)]
    try:
        async with AsyncExitStack() as stack:
            call = await client.adapter(deadline=True, cork=True).open(url, stack)

            async def answered(frame: str) -> str:
                request = client.make_request({"query_type": "position", "target_frame": frame})
                response = await call(request)
                assert client.values_of(response) == 5
                return str(response.message)

            # Eight calls made in one turn: one write of eight masked frames, which picows'
            # server unmasks (a wrong mask would be a parse error, and every wait a TimeoutError),
            # and each reply reaches its own call.
            assert await asyncio.gather(*map(answered, frames)) == frames
            assert client_writes == [8]
            assert sum(server_writes) == 8 and max(server_writes) > 1
            # One call at a time: the first, after a read of several replies, is held to the
            # turn's end; each after a read of one reply is written at once, not held. Each
            # read brings the server one call, whose reply is written alone.
            client_writes.clear()
            server_writes.clear()
            assert [await answered(frame) for frame in frames[:3]] == frames[:3]
            assert client_writes == [1] and server_writes == [1, 1, 1]
    finally:
        server.close()
        await server.wait_closed()


RAW_MESSAGES = [
    "not json",
    "[]",  # a batch: no reply from the raw server
    '{"jsonrpc":"2.0","method":"/get_robot_state","params":{}}',  # a notification: none either
    '{"jsonrpc":"2.0","id":1,"method":"/nothing","params":{}}',
    '{"jsonrpc":"2.0","id":2,"method":"/get_robot_state","params":{"query_type":"position"}}',
]


async def test_raw_picows_corked_answers_every_message_as_raw_picows_does(
    floors: dict[str, ModuleType],
) -> None:
    # The corked raw server holds a read's replies and frames them itself: what reaches the
    # client is the same, byte for byte, as what the raw server sends a reply at a time.
    raw = floors["picows_server"]
    got = []
    for cork in (False, True):
        server = await ws_create_server(functools.partial(raw.accept, cork=cork), "127.0.0.1", 0)
        try:
            url = f"ws://127.0.0.1:{server.sockets[0].getsockname()[1]}"
            got.append(await exchange(url, RAW_MESSAGES))
        finally:
            server.close()
            await server.wait_closed()
    assert got[1] == got[0]
    codes = [[json.loads(reply).get("error", {"code": 0})["code"] for reply in r] for r in got[1]]
    assert codes == [[-32700], [], [], [-32601], [0]]


async def test_raw_picows_corked_writes_a_turns_calls_and_a_reads_replies_at_once(
    floors: dict[str, ModuleType], monkeypatch: pytest.MonkeyPatch
) -> None:
    raw_server, raw_client = floors["picows_server"], floors["picows_client"]
    # The raw server's handler, with the reply naming the frame its request asked for: a
    # reply that reached the wrong call would show.
    monkeypatch.setitem(
        raw_server.HANDLERS, "/get_robot_state",
        lambda params: {**raw_server.get_robot_state(params), "message": params["target_frame"]},
    )  # fmt: skip
    client_writes, server_writes = count_writes(floors, monkeypatch)
    # Each wait under asyncio.wait_for, with the client's deadline: counted.
    deadlines: list[float] = []
    wait_for = asyncio.wait_for

    def counted_wait_for(awaitable: Any, timeout: float) -> Any:
        deadlines.append(timeout)
        return wait_for(awaitable, timeout)

    monkeypatch.setattr(raw_client.asyncio, "wait_for", counted_wait_for)
    accept = functools.partial(raw_server.accept, cork=True)
    server = await ws_create_server(accept, "127.0.0.1", 0)
    url = f"ws://127.0.0.1:{server.sockets[0].getsockname()[1]}"
    frames = [f"frame{index}" for index in range(8)]
    try:
        async with AsyncExitStack() as stack:
            call = await raw_client.holding_adapter(deadline=True, cork=True).open(url, stack)

            async def answered(frame: str) -> str:
                request = raw_client.make_request({"query_type": "position", "target_frame": frame})
                reply = await call(request)
                assert raw_client.values_of(reply) == 5
                return str(reply["message"])

            # Eight calls of one turn: one write of eight masked frames (a wrong mask would be a
            # parse error at picows' server), answered in writes of several replies.
            assert await asyncio.gather(*map(answered, frames)) == frames
            assert client_writes == [8]
            assert sum(server_writes) == 8 and max(server_writes) > 1
            assert deadlines == [raw_client.CALL_TIMEOUT] * 8
            # One call at a time: each after a read of one reply is written at once.
            client_writes.clear()
            server_writes.clear()
            assert [await answered(frame) for frame in frames[:3]] == frames[:3]
            assert client_writes == [1] and server_writes == [1, 1, 1]
            # Without the deadline, the same calls wait bare.
            deadlines.clear()
            call = await raw_client.holding_adapter(deadline=False, cork=True).open(url, stack)
            assert await asyncio.gather(*map(answered, frames)) == frames
            assert deadlines == []
    finally:
        server.close()
        await server.wait_closed()


async def test_raw_picows_with_its_deadline_ends_a_wait_the_server_never_answers(
    floors: dict[str, ModuleType], monkeypatch: pytest.MonkeyPatch
) -> None:
    raw_client = floors["picows_client"]
    monkeypatch.setattr(raw_client, "CALL_TIMEOUT", 0.05)
    received = asyncio.Event()

    async def silent(websocket: Any) -> None:
        async for _ in websocket:
            received.set()

    async with serve(silent, "127.0.0.1", 0, compression=None) as server:
        url = f"ws://127.0.0.1:{next(iter(server.sockets)).getsockname()[1]}"
        async with AsyncExitStack() as stack:
            call = await raw_client.holding_adapter(deadline=True, cork=True).open(url, stack)
            with pytest.raises(TimeoutError):
                await call(raw_client.make_request({"query_type": "position"}))
            assert received.is_set()


def test_raw_picows_corked_with_and_without_its_deadline_runs_the_small_call_workloads(
    tmp_path: Path,
) -> None:
    out = tmp_path / "report.json"
    done = harness(
        "--quick", "--repeat", "1", "--workloads", "W1,W2,W3", "--loop", "asyncio",
        "--compare", "picows-corked,picows-corked-deadline",
        "--no-pin", "--max-other-load", "64", "--json", str(out),
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    runs = json.loads(out.read_text())["asyncio"]["runs"]
    impls = ["picows-corked", "picows-corked-deadline"]
    for workload, calls in (("W1", 20_000 // 20), ("W2", 100_000 // 20)):
        mine = [run for run in runs if run["workload"] == workload]
        assert sorted(run["impl"] for run in mine) == impls
        assert all(run["calls"] == calls and run["server_cpu_s"] > 0 for run in mine), mine
    fan_in = [run for run in runs if run["workload"] == "W3"]
    assert sorted(run["impl"] for run in fan_in) == impls
    assert all(run["calls"] > 0 for run in fan_in)
    assert "ratio = picows-corked-deadline / picows-corked" in done.stdout


def test_raw_picows_corked_pair_is_raw_picows_told_to_cork_with_and_without_its_deadline(
    floors: dict[str, ModuleType], monkeypatch: pytest.MonkeyPatch
) -> None:
    run, raw_client = floors["run"], floors["picows_client"]
    scripts = run.IMPLEMENTATIONS["picows"][:2]
    command = ["picows_client.py", "--url", "ws://127.0.0.1:1", "--workload", "W1"]
    monkeypatch.setattr(sys, "argv", command)
    assert not raw_client.asked().cork and not raw_client.asked().deadline
    for name, deadline in (("picows-corked", False), ("picows-corked-deadline", True)):
        server_script, client_script, options = run.IMPLEMENTATIONS[name]
        assert (server_script, client_script) == scripts
        monkeypatch.setattr(sys, "argv", [*command, *options])
        assert raw_client.asked().cork and raw_client.asked().deadline == deadline


def test_the_corked_typed_floor_on_picows_masks_each_frame_with_its_own_key(
    floors: dict[str, ModuleType],
) -> None:
    client = floors["floor_picows_client"]
    written: list[bytes] = []

    class Underlying:
        def write(self, data: bytes) -> None:
            written.append(data)

    class Transport:
        underlying_transport = Underlying()
        is_close_frame_sent = False

    caller = client.TypedCaller.__new__(client.TypedCaller)
    caller.transport = Transport()
    caller._held, caller._held_size = [b"x" * 3, b"y" * 125, b"z" * 300], 0
    caller.flush()
    assert caller._held == [] and len(written) == 1
    data, payloads, keys = written[0], [], []
    while data:  # RFC 6455, 5.2: final text frames, masked, 7- or 16-bit lengths
        assert data[0] == 0x81 and data[1] & 0x80
        size, data = data[1] & 0x7F, data[2:]
        if size == 126:
            size, data = int.from_bytes(data[:2], "big"), data[2:]
        key, payload, data = data[:4], data[4 : 4 + size], data[4 + size :]
        assert len(payload) == size
        payloads.append(bytes(byte ^ key[index % 4] for index, byte in enumerate(payload)))
        keys.append(key)
    assert payloads == [b"x" * 3, b"y" * 125, b"z" * 300]
    assert len(set(keys)) == 3


def test_the_defaults_benchmark_measures_each_operation_in_each_tree() -> None:
    # A smoke run on CPU time: each operation ran in its children, on each tree given (the
    # same one twice here), and has a positive figure.
    src = str(ROOT / "src")
    options = ["--cpu", "--ops", "50", "--src", src, "--src", f"{src}/"]
    result = run_benchmark(ROOT / "benchmarks" / "defaults.py", *options)
    outcome = json.loads(result.stdout.splitlines()[-1])
    assert outcome["unit"] == "µs of CPU"
    assert list(outcome["results"]) == ["corpus", "add", "covariance", "uuid"]
    for figures in outcome["results"].values():
        assert list(figures) == [src, f"{src}/"] and all(value > 0 for value in figures.values())


def test_the_bare_requests_benchmark_measures_both_kinds_of_request() -> None:
    # A smoke run: each kind's requests are all held (or the script would wait) and answered.
    result = run_benchmark(
        ROOT / "benchmarks" / "bare_requests.py", "--calls", "2", "--size", "4000"
    )
    rows = [line.split() for line in result.stdout.splitlines()]
    assert [row[0] for row in rows] == ["bare", "full"]
    assert int(rows[0][2]) < 100 < int(rows[1][2]) <= 4000
