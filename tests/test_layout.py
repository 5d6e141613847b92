"""The layout promise: imports flow one way with no cycles, and nothing in the repository names a machine's paths."""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "lerobot_pdp"


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports() -> dict[str, set[str]]:
    """Every ``lerobot_pdp`` module -> the ``lerobot_pdp`` modules it imports, at any depth of its code."""
    modules = {_module_name(p): p for p in PKG.rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        deps: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join(anchor + ([base] if base else []))
                # `from pkg import sub` imports the submodule when there is one
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]
            else:
                continue
            for t in targets:
                while t and t not in modules:  # `import lerobot_pdp.envs.suite.X` -> its module
                    t = t.rpartition(".")[0]
                if t.startswith("lerobot_pdp") and t != name:
                    deps.add(t)
        graph[name] = deps
    return graph


def test_no_import_cycles_in_the_package():
    graph = _imports()
    # package __init__ files re-export their submodules: an edge into a package's own __init__ from
    # inside it is how Python loads packages, not a design cycle
    def own_package(a: str, b: str) -> bool:
        return a.startswith(b + ".")

    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(n: str) -> None:
        state[n] = 1
        stack.append(n)
        for m in sorted(graph.get(n, ())):
            if own_package(n, m):
                continue
            if state.get(m) == 1:
                cycle = stack[stack.index(m):] + [m]
                raise AssertionError(f"import cycle: {' -> '.join(cycle)}")
            if m not in state:
                visit(m)
        stack.pop()
        state[n] = 2

    for n in sorted(graph):
        if n not in state:
            visit(n)


def test_imports_flow_one_way():
    """The model never imports the benchmark or the simulators; the simulators (the envs, and the simulated
    robot and teleoperator built on them) never import the benchmark. The explorer (an app, like the CLI) may roll
    out in the simulators. (The package's ``__init__`` registers everything with LeRobot, so it imports every
    layer.)"""
    bad = []
    for name, deps in _imports().items():
        if name == "lerobot_pdp":
            continue
        layer = name.split(".")[1] if name.count(".") else ""
        for d in deps:
            if layer not in ("benchmark", "cli") and d.startswith("lerobot_pdp.benchmark"):
                bad.append(f"{name} -> {d}")
            if layer not in ("benchmark", "cli", "envs", "robots", "teleoperators", "explorer", "explorer_app") \
                    and d.startswith("lerobot_pdp.envs"):
                bad.append(f"{name} -> {d}")
    assert not bad, bad


# A machine's absolute paths: home folders, the work tree, temporary folders.
MACHINE_PATH = re.compile(r"(?<![\w.])/(?:work|root|home|Users|tmp|mnt|opt)/[\w.-]+")
TEXT_SUFFIXES = {".md", ".json", ".jsonl", ".py", ".sh", ".txt", ".yaml", ".yml", ".toml", ".cfg"}


def test_no_absolute_machine_paths_in_docs_results_and_scripts():
    roots = [ROOT / "README.md", ROOT / "docs", ROOT / "benchmarks", ROOT / "examples", ROOT / "scripts"]
    offenders = []
    for root in roots:
        files = [root] if root.is_file() else [p for p in root.rglob("*") if p.suffix in TEXT_SUFFIXES]
        for f in files:
            for i, line in enumerate(f.read_text(errors="replace").splitlines(), 1):
                m = MACHINE_PATH.search(line)
                if m:
                    offenders.append(f"{f.relative_to(ROOT)}:{i}: {m.group(0)}")
    assert not offenders, "\n".join(offenders[:40]) + (f"\n... {len(offenders)} in all" if len(offenders) > 40 else "")


def test_figure_folders_hold_figures_and_result_files_only():
    allowed = {".png", ".json", ".jsonl", ".md"}
    stray = [str(p.relative_to(ROOT)) for p in (ROOT / "docs").rglob("*") if p.is_file() and p.suffix not in allowed]
    assert not stray, stray
