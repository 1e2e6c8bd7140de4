# mypy: disable-error-code="top-level-await"
# ruff: noqa: F704, E402, B018
# %% [markdown]
# # The robot from a Jupyter notebook
#
# The cells of a notebook, in the percent format that Jupyter, VS Code and jupytext read: each
# `# %%` line starts a cell. Top-level `await` works in a notebook, so this is not a script;
# `tests/test_notebook.py` runs it in a Jupyter kernel. Open it next to `robot_state_server.py`.

# %%
# --8<-- [start:server]
# The tutorial's robot, served from a thread of its own: a cell that blocks holds the kernel's
# event loop, so a server on that loop could not answer a blocking call.
import threading

import robot_state_server

import srvwire

listening = threading.Event()
urls: list[str] = []


def ready(running: srvwire.RunningServer) -> None:
    urls.append(running.url)
    listening.set()


robot = robot_state_server.build_server()
threading.Thread(
    target=robot.run, args=("127.0.0.1", 0), kwargs={"ready": ready}, daemon=True
).start()
listening.wait(10)
url = urls[0]
# --8<-- [end:server]

# %%
# --8<-- [start:await]
# The kernel runs an event loop: await the async client at the top level of a cell.
client = await srvwire.connect(url)
position = await client.call("/get_robot_state", {"query_type": "position"})
position
# --8<-- [end:await]

# %%
await client.close()

# %%
# --8<-- [start:sync]
# The blocking client works here too: its event loop is in a thread of its own.
with srvwire.sync.connect(url) as blocking:
    status = blocking.call("/get_robot_state", {"query_type": "status"})
print(type(status).__name__, "->", status.message)
# --8<-- [end:sync]

# %%
# --8<-- [start:asyncio-run]
# asyncio.run() starts an event loop, and this thread already runs the kernel's.
import asyncio

try:
    asyncio.run(srvwire.connect(url))
except RuntimeError as exc:
    print(exc)
# --8<-- [end:asyncio-run]
