"""The package's layers: geometry/core/io below pipeline below replay below ros/cli; no cycles.

Reads every module's imports (module level and inside functions) with :mod:`ast`; nothing is
imported, so the test is fast and needs no ROS.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[2] / 'ga_ros'
#: Rank of each top-level part of ga_ros: a module may import only parts of lower or equal rank.
RANK = {'arrays': 0, 'errors': 0, 'runtime': 0, 'topics': 0, 'safe_write': 0, 'domains': 0,
        'geometry': 1,
        'core': 2, 'io': 2, 'sim': 2, 'vo': 2, 'eval': 2,
        'pipeline': 3, 'inputs': 3, 'mapping': 3,
        'replay': 4, 'tools': 4, 'report': 4, 'bench': 4, 'ros': 5, 'cli': 6}
#: Known exceptions (importer, imported): ROS-free modules that still live in a higher folder.
ALLOWED: set[tuple[str, str]] = set()


def module_name(path: Path) -> str:
    parts = path.relative_to(PKG.parent).with_suffix('').parts
    return '.'.join(parts[:-1] if parts[-1] == '__init__' else parts)


def imports(path: Path) -> set[str]:
    """ga_ros modules imported by the file at ``path`` (anywhere in it)."""
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names if a.name.startswith('ga_ros'))
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0 \
                and node.module.startswith('ga_ros'):
            for a in node.names:  # `from ga_ros.x import y`: y may be a module
                sub = f'{node.module}.{a.name}'
                mod = sub if (PKG.parent / (sub.replace('.', '/') + '.py')).exists() \
                    or (PKG.parent / sub.replace('.', '/')).is_dir() else node.module
                out.add(mod)
    return out


GRAPH = {module_name(p): imports(p) for p in sorted(PKG.rglob('*.py'))}


def rank(module: str) -> int:
    parts = module.split('.')
    return RANK[parts[1]] if len(parts) > 1 else 0


@pytest.mark.parametrize('module', sorted(GRAPH))
def test_no_module_imports_a_layer_above_it(module: str) -> None:
    up = sorted(m for m in GRAPH[module] if rank(m) > rank(module)
                and (module, m) not in ALLOWED)
    assert not up, f'{module} (rank {rank(module)}) imports higher layers: {up}'


def test_every_part_has_a_rank() -> None:
    assert {m.split('.')[1] for m in GRAPH if '.' in m} <= set(RANK)


def test_no_import_cycles() -> None:
    """Depth-first search for a cycle among ga_ros modules (package __init__ edges ignored)."""
    graph = {m: {d for d in deps if d in GRAPH and d != m and not m.startswith(d + '.')}
             for m, deps in GRAPH.items()}
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> None:
        state[m] = 1
        stack.append(m)
        for d in sorted(graph[m]):
            if state.get(d) == 1:
                cycle = stack[stack.index(d):] + [d]
                raise AssertionError('import cycle: ' + ' -> '.join(cycle))
            if d not in state:
                visit(d)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)
