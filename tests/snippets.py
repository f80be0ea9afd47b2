"""README's and the user guide's Python snippets, read from their Markdown."""

import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"
DOCS = README.parent / "docs"
#: the user guide's pages, in the order docs/guide.md lists them
GUIDE_PAGES = tuple(
    DOCS / f"{name}.md"
    for name in (
        "network",
        "evidence",
        "parameters",
        "fitting",
        "queries",
        "compiled",
        "pyro",
        "interop",
        "pictures",
    )
)
#: a page whose ```python blocks run on their own (its outlines use ```{code-block})
EXPERIMENTS = DOCS / "experiments.md"


def blocks(text: str) -> list[str]:
    """The bodies of the ```python blocks of a Markdown text, in order, de-indented."""
    found = re.findall(r"^( *)```python\n(.*?)^\1```", text, re.S | re.M)
    out = []
    for indent, body in found:
        lines = [
            line[len(indent) :] if line.startswith(indent) else line for line in body.splitlines()
        ]
        out.append("\n".join(lines))
    return out


def snippets(path: Path = README) -> list[str]:
    """A Markdown file's snippets, in order."""
    return blocks(path.read_text())


def guide_text() -> str:
    """README and the user guide's pages, as one text (the names they teach)."""
    return "\n".join(path.read_text() for path in (README, *GUIDE_PAGES))
