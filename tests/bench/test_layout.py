"""bench's layout: no import cycle inside it, and the command line assembled from its parts' commands."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _module(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(package: str) -> dict[str, set[str]]:
    """Module → the modules of ``package`` it imports (at any depth of the file, lazily or not)."""
    files = {_module(p): p for p in (ROOT / package).rglob("*.py")}
    graph: dict[str, set[str]] = {m: set() for m in files}
    for mod, path in files.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            else:
                continue
            graph[mod] |= {n for n in names if n in files and n != mod}
    return graph


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> list[str] | None:
        state[m] = 1
        stack.append(m)
        for n in sorted(graph[m]):
            if state.get(n) == 1:
                return stack[stack.index(n):] + [n]
            if n not in state and (found := visit(n)):
                return found
        stack.pop()
        state[m] = 2
        return None

    for m in sorted(graph):
        if m not in state and (found := visit(m)):
            return found
    return None


def test_bench_has_no_import_cycle():
    assert _cycle(_imports("bench")) is None


def test_the_server_commands_import_neither_client_nor_bench():
    tree = ast.parse((ROOT / "server" / "cli.py").read_text())
    names = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    names |= {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
    assert not {n for n in names if n.split(".")[0] in ("client", "bench", "walkstream", "moderngl")}


def test_the_root_app_has_every_command_in_order():
    from typer.main import get_command

    from walkstream.cli import app

    root = get_command(app)
    assert list(root.commands) == ["build", "inspect", "serve", "client", "kiosk", "demo", "loadtest", "eval",
                                  "bench"]
    assert list(root.commands["bench"].commands) == ["build", "select", "predict", "render", "benefit", "encoding", "hostile",
                                                   "soak", "sessions"]
