"""The package's data flow as the brief states it: acquisition -> clustering -> retarget, each
stage importing only earlier stages and the shared core (``mocaptk/``), and every import that
leaves a stage written absolute (``from mocaptk.errors import ...``), so a reader of
``clustering/x.py`` sees where it points without opening pyproject.toml."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
STAGES = ("acquisition", "clustering", "retarget")
#: what the shared core may not import: every stage (the CLI and batch are the edges that join them)
EDGES = ("cli", "batch", "__main__")


def modules() -> list[tuple[Path, list[str]]]:
    """Every package module with its installed package path (``["mocaptk", "clustering"]``)."""
    out = []
    for top in (*STAGES, "mocaptk"):
        for path in sorted((REPO / top).rglob("*.py")):
            parts = list(path.relative_to(REPO).with_suffix("").parts)
            out.append((path, (["mocaptk"] if top != "mocaptk" else []) + parts[:-1]))
    return out


def imported(path: Path, package: list[str]) -> list[tuple[int, str, int]]:
    """(line, absolute module, dots) of every ``import`` / ``from ... import`` in the file."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom):
            base = package[:len(package) - node.level + 1] if node.level else []
            name = ".".join(base + ([node.module] if node.module else []))
            found.append((node.lineno, name, node.level))
        elif isinstance(node, ast.Import):
            found += [(node.lineno, alias.name, 0) for alias in node.names]
    return found


def stage_of(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[0] == "mocaptk" and parts[1] in STAGES else None


MODULES = modules()


@pytest.mark.parametrize("path, package", MODULES, ids=[str(path.relative_to(REPO)) for path, _ in MODULES])
def test_imports_follow_the_data_flow_and_leave_a_stage_absolutely(path, package):
    here = stage_of(".".join(package + ["x"]))
    rel = path.relative_to(REPO)
    problems = []
    for line, module, dots in imported(path, package):
        there = stage_of(module)
        if dots >= 2 and not module.startswith(".".join(package[:2]) + "."):
            problems.append(f"{rel}:{line}: relative import of {module} leaves {'.'.join(package[:2])}")
        if there is None:
            continue
        if here is None and rel.parts[1] not in EDGES:
            problems.append(f"{rel}:{line}: the shared core imports the stage {module}")
        if here is not None and STAGES.index(there) > STAGES.index(here):
            problems.append(f"{rel}:{line}: {here} imports the later stage {module}")
    assert not problems, "\n".join(problems)


def module_name(path: Path, package: list[str]) -> str:
    return ".".join(package if path.stem == "__init__" else package + [path.stem])


def test_no_module_imports_itself_through_others():
    """No import cycle among the package's modules, counting imports inside functions: a cycle
    hidden in a lazy import still ties the modules' jobs together (the brief's rule)."""
    names = {module_name(path, package): (path, package) for path, package in MODULES}
    graph: dict[str, set[str]] = {}
    for name, (path, package) in names.items():
        targets = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom):
                base = ".".join((package[:len(package) - node.level + 1] if node.level else [])
                                + ([node.module] if node.module else []))
                targets |= {base, *(f"{base}.{alias.name}" for alias in node.names)}
            elif isinstance(node, ast.Import):
                targets |= {alias.name for alias in node.names}
        graph[name] = {t for t in targets if t in names and t != name}

    def cycle_from(start: str) -> list[str] | None:
        stack, seen = [(start, [start])], set()
        while stack:
            node, trail = stack.pop()
            for nxt in sorted(graph[node]):
                if nxt == start:
                    return trail + [start]
                if nxt not in seen:
                    seen.add(nxt)
                    stack.append((nxt, trail + [nxt]))
        return None

    cycles = {frozenset(c): c for c in map(cycle_from, sorted(graph)) if c}
    assert not cycles, "\n".join(" -> ".join(c) for c in cycles.values())
