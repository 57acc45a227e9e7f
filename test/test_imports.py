"""The package's import graph: no cycles, no ROS below the nodes, no node importing the CLI."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "robot_ct_ros"


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path, modules: set) -> set:
    """Every robot_ct_ros module ``path`` imports, at module level or inside a function."""
    name = _module_name(path)
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1] + ([base] if base else []))
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]
        else:
            continue
        out.update(t for t in targets if t in modules and t != name)
    return out


def _graph() -> dict:
    files = {_module_name(p): p for p in PACKAGE.rglob("*.py")}
    return {m: _imports(p, set(files)) for m, p in files.items()}


def _cycle(graph: dict):
    state, stack = {}, []

    def visit(m):
        state[m] = "open"
        stack.append(m)
        for n in sorted(graph[m]):
            if state.get(n) == "open":
                return stack[stack.index(n):] + [n]
            if n not in state and (found := visit(n)):
                return found
        state[m] = "done"
        stack.pop()
        return None

    for m in sorted(graph):
        if m not in state and (found := visit(m)):
            return found
    return None


def test_the_import_graph_has_no_cycle():
    graph = _graph()
    assert len(graph) > 30
    assert _cycle(graph) is None, " -> ".join(_cycle(graph))


def test_the_cycle_finder_finds_one():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]


def test_no_node_imports_the_cli_and_the_core_imports_no_ros():
    graph = _graph()
    for m, deps in graph.items():
        if m.startswith("robot_ct_ros.nodes"):
            assert "robot_ct_ros.cli" not in deps, m
        if m.startswith(("robot_ct_ros.ct", "robot_ct_ros.jobs", "robot_ct_ros.hardware", "robot_ct_ros.bag",
                         "robot_ct_ros.parameters")):
            assert not any(d.startswith(("robot_ct_ros.nodes", "robot_ct_ros.testing", "robot_ct_ros.cli"))
                           for d in deps), (m, deps)
            text = (PACKAGE.parent / (m.replace(".", "/") + ".py")).read_text() if not (
                PACKAGE.parent / m.replace(".", "/")).is_dir() else ""
            assert "import rclpy" not in text and "from rclpy" not in text, m


def test_no_science_module_is_a_notebook():
    """One topic per module: nothing in ct/ over about 700 lines."""
    long = {str(p.relative_to(PACKAGE)): n for p in (PACKAGE / "ct").rglob("*.py")
            if (n := len(p.read_text().splitlines())) > 750}
    assert not long, long
