"""Griffe extension for the docs build: fence the doctest examples of the package's
docstrings (Gymnasium's ``Example:`` sections, indented ``>>>`` lines) as Python code, so that
Markdown does not read them as text and their ``x["a"]["b"]`` as reference links."""

from __future__ import annotations

import griffe


def fence_doctests(text: str) -> str:
    out: list[str] = []
    block: list[str] = []
    indent = ""

    def flush() -> None:
        if block:  # at the docstring's own margin: indented, Markdown reads a code block
            out.extend(["", "```python", *(b[len(indent):] for b in block), "```", ""])
            block.clear()

    for line in text.splitlines():
        stripped = line.lstrip()
        header = stripped.startswith(("Change logs", "Example"))
        if stripped.startswith(">>>") or (block and stripped and not header):
            if not block:
                indent = line[: len(line) - len(stripped)]
            block.append(line)
        else:
            flush()
            out.append(line)
    flush()
    return "\n".join(out)


class DoctestFences(griffe.Extension):
    def on_instance(self, *, obj: griffe.Object, **kwargs) -> None:
        if obj.docstring is not None and ">>>" in obj.docstring.value:
            obj.docstring.value = fence_doctests(obj.docstring.value)
