"""Shared by the notebook builders: cells to an executed notebook file."""

import pathlib

import nbformat
from nbclient import NotebookClient

HERE = pathlib.Path(__file__).parent


def build(cells, name, *, timeout=900):
    """Execute ``cells`` (``[("md" | "code", text)]``) and write ``notebooks/<name>``."""
    nb = nbformat.v4.new_notebook()
    for kind, text in cells:
        new = nbformat.v4.new_markdown_cell if kind == "md" else nbformat.v4.new_code_cell
        nb.cells.append(new(text))
    nb.metadata["kernelspec"] = {
        "name": "python3",
        "display_name": "Python 3",
        "language": "python",
    }
    client = NotebookClient(
        nb, timeout=timeout, kernel_name="python3", resources={"metadata": {"path": str(HERE)}}
    )
    client.execute()
    path = HERE / name
    nbformat.write(nb, path)
    print(f"wrote {path}")
