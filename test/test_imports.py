# SPDX-License-Identifier: Apache-2.0
"""The package's import graph, read with ast: no import cycle (imports inside functions count),
and no import inside a function except of an optional extra.

An import inside a function hides a cycle from Python (the import runs late, when both modules
are loaded) but not from a reader; and it hides a missing dependency until that function runs.
So only the optional extras, which a user may not have installed, are imported where they are
used.
"""

import ast
import sys
from pathlib import Path

import pytest

from conftest import REPO

PACKAGE = 'gp_ground_segmentation'

# top-level module -> the extra (setup.py extras_require) that brings it; only these may be
# imported inside a function
OPTIONAL_EXTRAS = {
    'matplotlib': 'plot',  # tools/plot.py
    'dask': 'scale',  # tools/engine.py, batch and tune --jobs/--scheduler
    'distributed': 'scale',
    'optuna': 'tune',  # tools/tune.py
    'velodyne_decoder': 'packets',  # tools/packets.py: Velodyne packet bags and .pcap
    'dpkt': 'packets',
}

# Function-level imports of required modules in ros/, which another change of issue 30 owns;
# each entry must still be in the code (a moved import fails here until its line goes too).
NOT_YET_MOVED = {
    ('gp_ground_segmentation.ros.cloud', 'sensor_msgs.msg'),
    ('gp_ground_segmentation.ros.cloud', 'types'),
    ('gp_ground_segmentation.ros.config', 'yaml'),
    ('gp_ground_segmentation.ros.diagnostics', 'diagnostic_msgs.msg'),
    ('gp_ground_segmentation.ros.shutdown', 'rclpy'),
    ('gp_ground_segmentation.ros.shutdown', 'rclpy.impl.implementation_singleton'),
}


def module_names(root: Path, package: str) -> dict:
    """{dotted module name: path} of every .py file of ``package`` under ``root``."""
    out = {}
    for path in sorted((root / package).rglob('*.py')):
        parts = path.relative_to(root).with_suffix('').parts
        name = '.'.join(parts[:-1] if parts[-1] == '__init__' else parts)
        out[name] = path
    return out


def _imported(node, module: str, is_package: bool) -> list:
    """Dotted names an Import / ImportFrom node brings in (``from X import y`` gives X.y and X:
    y may be a submodule or a name in X)."""
    if isinstance(node, ast.Import):
        return [alias.name for alias in node.names]
    if node.level:  # relative: resolved against the importing module's package
        base = module.split('.') if is_package else module.split('.')[:-1]
        base = base[:len(base) - node.level + 1]
        target = '.'.join(base + ([node.module] if node.module else []))
    else:
        target = node.module
    return [target] + [f'{target}.{alias.name}' for alias in node.names]


def _in_functions(tree) -> set:
    """ids of the import nodes that sit inside a function body."""
    inside = set()
    for fn in ast.walk(tree):
        if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            inside.update(id(n) for n in ast.walk(fn)
                          if isinstance(n, (ast.Import, ast.ImportFrom)))
    return inside


def import_graph(root: Path, package: str) -> tuple:
    """(edges {module: set of package modules it imports}, [(module, line, imported name)] of
    every import inside a function), for ``package`` under ``root``."""
    modules = module_names(root, package)
    edges = {name: set() for name in modules}
    function_level = []
    for name, path in modules.items():
        tree = ast.parse(path.read_text(), str(path))
        inside = _in_functions(tree)
        is_package = path.name == '__init__.py'
        for node in ast.walk(tree):
            if not isinstance(node, (ast.Import, ast.ImportFrom)):
                continue
            names = _imported(node, name, is_package)
            if id(node) in inside:
                function_level.append((name, node.lineno, names[0]))
            if isinstance(node, ast.Import):
                found = [n for n in names if n in modules]
            else:  # 'from X import y': an edge to X.y when that is a module, else to X
                found = ([n for n in names[1:] if n in modules]
                         or [n for n in names[:1] if n in modules])
            edges[name].update(f for f in found if f != name)
    return edges, function_level


def find_cycle(edges: dict):
    """One import cycle as a list of modules (first == last), or None."""
    state = {}  # module -> 1 on the current path, 2 done
    path = []

    def visit(module):
        state[module] = 1
        path.append(module)
        for nxt in sorted(edges.get(module, ())):
            if state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            if nxt not in state:
                cycle = visit(nxt)
                if cycle:
                    return cycle
        path.pop()
        state[module] = 2
        return None

    for module in sorted(edges):
        if module not in state:
            cycle = visit(module)
            if cycle:
                return cycle
    return None


def not_optional(function_level) -> list:
    """The function-level imports that are neither an optional extra nor NOT_YET_MOVED."""
    return [(m, line, name) for m, line, name in function_level
            if name.split('.')[0] not in OPTIONAL_EXTRAS and (m, name) not in NOT_YET_MOVED]


def test_the_package_has_no_import_cycle():
    edges, _ = import_graph(REPO, PACKAGE)
    assert len(edges) > 30 and any(edges.values())  # the package was read
    assert find_cycle(edges) is None, ' -> '.join(find_cycle(edges))


def test_only_optional_extras_are_imported_inside_functions():
    _, function_level = import_graph(REPO, PACKAGE)
    assert not_optional(function_level) == []
    still_there = {(m, name) for m, _, name in function_level}
    assert NOT_YET_MOVED <= still_there, NOT_YET_MOVED - still_there


def test_the_extras_are_declared_in_setup_py():
    setup = (REPO / 'setup.py').read_text()
    for extra in set(OPTIONAL_EXTRAS.values()):
        assert f"'{extra}':" in setup, extra


def _write(root, files):
    for rel, text in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)


def test_the_checker_finds_a_cycle_hidden_in_a_function(tmp_path):
    # a imports b at module level; b imports a inside a function (Python would not mind)
    _write(tmp_path, {'pkg/__init__.py': '', 'pkg/sub/__init__.py': '',
                      'pkg/a.py': 'from .sub import b\n',
                      'pkg/sub/b.py': 'def f():\n    from .. import a\n    import json\n',
                      'pkg/c.py': 'from .sub.b import f\nimport pkg.a\n'})
    edges, function_level = import_graph(tmp_path, 'pkg')
    assert edges['pkg.a'] == {'pkg.sub.b'} and edges['pkg.sub.b'] == {'pkg.a'}
    assert edges['pkg.c'] == {'pkg.sub.b', 'pkg.a'}
    assert find_cycle(edges) in (['pkg.a', 'pkg.sub.b', 'pkg.a'],
                                 ['pkg.sub.b', 'pkg.a', 'pkg.sub.b'])
    assert not_optional(function_level) == [('pkg.sub.b', 2, 'pkg'), ('pkg.sub.b', 3, 'json')]


def test_the_checker_lets_optional_extras_be_imported_late(tmp_path):
    _write(tmp_path, {'pkg/__init__.py': 'from . import a\n',
                      'pkg/a.py': 'def plot():\n    import matplotlib.pyplot as plt\n'})
    edges, function_level = import_graph(tmp_path, 'pkg')
    assert find_cycle(edges) is None
    assert function_level == [('pkg.a', 2, 'matplotlib.pyplot')]
    assert not_optional(function_level) == []


if __name__ == '__main__':  # print the graph: python test/test_imports.py
    graph, late = import_graph(REPO, PACKAGE)
    for module, targets in sorted(graph.items()):
        print(module, '->', ', '.join(sorted(targets)))
    for item in late:
        print('function-level:', *item)
    sys.exit(pytest.main([__file__, '-q']))
