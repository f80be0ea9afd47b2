"""The sim2d package's layout: its modules import each other without a circle, never by a
private name, and each concept has one home."""

import ast
from pathlib import Path

from effect_networks import sim2d

PACKAGE = Path(sim2d.__file__).parent
MODULES = {p.stem: ast.parse(p.read_text()) for p in PACKAGE.glob("*.py") if p.stem != "__init__"}


def sim2d_imports(tree: ast.Module) -> list[tuple[str, str | None]]:
    """``(module, name)`` for every import of a sim2d module (``name`` None: the module)."""
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("sim2d"):
            for alias in node.names:
                if node.module == "sim2d":
                    out.append((alias.name, None))
                else:
                    out.append((node.module.split(".")[1], alias.name))
        elif isinstance(node, ast.Import):
            out += [(a.name.split(".")[1], None) for a in a_names(node) if "." in a.name]
    return out


def a_names(node: ast.Import):
    return [a for a in node.names if a.name.startswith("sim2d.")]


def test_no_import_circle():
    graph = {name: {m for m, _ in sim2d_imports(tree)} for name, tree in MODULES.items()}
    done: set[str] = set()

    def visit(name: str, path: tuple[str, ...]) -> None:
        assert name not in path, f"import circle: {' -> '.join(path + (name,))}"
        if name in done:
            return
        for other in graph.get(name, ()):
            visit(other, path + (name,))
        done.add(name)

    for name in graph:
        visit(name, ())


def test_no_private_name_across_modules():
    offences = []
    for name, tree in MODULES.items():
        offences += [f"{name} imports {m}.{n}" for m, n in sim2d_imports(tree) if n and n[0] == "_"]
        aliases = {a.asname or a.name for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)
                   and n.module == "sim2d" for a in n.names}  # fmt: skip
        for node in ast.walk(tree):
            if (
                isinstance(node, ast.Attribute)
                and isinstance(node.value, ast.Name)
                and node.value.id in aliases
                and node.attr.startswith("_")
            ):
                offences.append(f"{name} uses {node.value.id}.{node.attr}")
    assert not offences


def test_each_public_name_has_one_home():
    homes: dict[str, list[str]] = {}
    for name in MODULES:
        module = __import__(f"sim2d.{name}", fromlist=["__all__"])
        for public in getattr(module, "__all__", ()):
            homes.setdefault(public, []).append(name)
    assert {k: v for k, v in homes.items() if len(v) > 1} == {}
