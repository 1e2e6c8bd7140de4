"""``examples/notebook.py`` run for real as a Jupyter notebook, in an IPython kernel (nbclient).

The file holds the cells in the percent format (``# %%`` starts a cell); the test makes a
notebook of them and runs it, as Jupyter would, with ``examples/`` as the kernel's directory.
"""

from __future__ import annotations

import re

import nbclient
import nbformat
import pytest

from support import ROOT, scaled

EXAMPLES = ROOT / "examples"
CELL = re.compile(r"^# %%(.*)$", re.MULTILINE)


def notebook_of(text: str) -> nbformat.NotebookNode:
    """A notebook of the ``# %%`` cells of ``text`` (a markdown cell's lines lose their ``# ``)."""
    cells = []
    parts = CELL.split(text)
    for marker, body in zip(parts[1::2], parts[2::2], strict=True):
        source = body.strip("\n")
        if marker.strip() == "[markdown]":
            lines = [line.removeprefix("#").removeprefix(" ") for line in source.splitlines()]
            cells.append(nbformat.v4.new_markdown_cell("\n".join(lines)))
        else:
            cells.append(nbformat.v4.new_code_cell(source))
    return nbformat.v4.new_notebook(cells=cells)


def text_of(cell: nbformat.NotebookNode) -> str:
    """What a code cell showed: its printed text and the text of its result, in order."""
    shown = []
    for output in cell.outputs:
        if output.output_type == "stream":
            shown.append(output.text)
        elif output.output_type == "execute_result":
            shown.append(output.data["text/plain"] + "\n")
        elif output.output_type == "error":
            pytest.fail(f"the cell raised {output.ename}: {output.evalue}\n{cell.source}")
    return "".join(shown)


@pytest.mark.timeout(scaled(120))
def test_the_notebook_calls_the_robot_with_await_and_with_the_blocking_client() -> None:
    notebook = notebook_of((EXAMPLES / "notebook.py").read_text(encoding="utf-8"))
    nbclient.NotebookClient(
        notebook,
        timeout=scaled(60),
        kernel_name="python3",
        resources={"metadata": {"path": str(EXAMPLES)}},
    ).execute()
    code = [cell for cell in notebook.cells if cell.cell_type == "code"]
    shown = [text_of(cell) for cell in code]
    # With logging not configured, run() says where it listens and who can reach it, on stderr.
    assert re.fullmatch(
        r"\S+ \S+ INFO srvwire\.server: serving 2 services and 1 action on ws://127\.0\.0\.1:\d+\n"
        r"\S+ \S+ INFO srvwire\.server: only programs on this machine can connect \(loopback\); "
        r"no authentication; unencrypted\n",
        shown[0],
    ), shown[0]
    assert shown[1:] == [
        "RobotStateQuery_Response(success=True, message='Current joint positions', "
        "values=[0.0, 0.0, 0.0, 0.0, 0.0], "
        "names=['joint_0', 'joint_1', 'joint_2', 'joint_3', 'joint_4'])\n",
        "",
        "RobotStateQuery_Response -> Robot status: IDLE\n",
        "asyncio.run() cannot be called from a running event loop\n",
    ]
    assert notebook.cells[0].cell_type == "markdown"
    assert notebook.cells[0].source.startswith("# The robot from a Jupyter notebook\n")
