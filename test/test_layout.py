"""The package layout docs/architecture.md describes, checked against the code: nothing loose at the
top of lln_ros/ but __init__ and errors, no module over 500 lines, no import circle, and the
module-level imports between subpackages exactly as the architecture page lists them."""

from __future__ import annotations

import ast
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PKG = REPO / 'lln_ros'
MAX_LINES = 500


def modules() -> dict[str, tuple[Path, bool]]:
    """dotted name -> (file, is a package __init__)."""
    out = {}
    for f in PKG.rglob('*.py'):
        parts = list(f.relative_to(REPO).with_suffix('').parts)
        is_pkg = parts[-1] == '__init__'
        out['.'.join(parts[:-1] if is_pkg else parts)] = (f, is_pkg)
    return out


def module_imports(name: str, f: Path, is_pkg: bool, known: dict) -> set[str]:
    """lln_ros modules that `name` imports at module level (not inside functions)."""
    pkg = name.split('.') if is_pkg else name.split('.')[:-1]
    found = set()
    for node in ast.parse(f.read_text()).body:
        if isinstance(node, ast.ImportFrom):
            base = pkg[: len(pkg) - node.level + 1] if node.level else []
            mod = '.'.join(base + ([node.module] if node.module else []))
            for alias in node.names:
                sub = f'{mod}.{alias.name}'
                found.add(sub if sub in known else mod)
        elif isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
    return {m for m in found if m in known and m != name}


def graph() -> dict[str, set[str]]:
    known = modules()
    return {name: module_imports(name, f, is_pkg, known) for name, (f, is_pkg) in known.items()}


def subpackage(module: str) -> str:
    parts = module.split('.')
    return parts[1] if len(parts) > 1 else 'lln_ros'


def test_top_level_holds_only_init_errors_and_subpackages():
    loose = sorted(p.name for p in PKG.glob('*.py') if p.name not in ('__init__.py', 'errors.py'))
    assert loose == [], f'modules loose at lln_ros/: {loose} (move each into the subpackage of its role)'


def test_no_module_over_the_line_limit():
    long = {
        str(f.relative_to(REPO)): n for f in PKG.rglob('*.py') if (n := len(f.read_text().splitlines())) > MAX_LINES
    }
    assert long == {}, f'modules over {MAX_LINES} lines: {long}'


def test_no_import_circle():
    g, state, circles = graph(), {}, []

    def visit(u, stack):
        state[u] = 'open'
        stack.append(u)
        for v in sorted(g[u]):
            if state.get(v) == 'open':
                circles.append(stack[stack.index(v) :] + [v])
            elif v not in state:
                visit(v, stack)
        stack.pop()
        state[u] = 'done'

    for u in sorted(g):
        if u not in state:
            visit(u, [])
    assert circles == []


def documented_edges() -> dict[str, set[str]]:
    text = (REPO / 'docs' / 'architecture.md').read_text()
    block = re.search(r'```text\n(core\s+->.*?)```', text, re.S)
    assert block, 'docs/architecture.md has no import block (```text ... core -> ...```)'
    edges = {}
    for line in block.group(1).strip().splitlines():
        src, _, dsts = line.partition('->')
        edges[src.strip()] = set(dsts.split())
    return edges


def test_architecture_page_lists_the_imports_between_subpackages():
    edges: dict[str, set[str]] = {}
    for u, vs in graph().items():
        for v in vs:
            a, b = subpackage(u), subpackage(v)
            if a != b and a != 'lln_ros' and a != 'errors':
                edges.setdefault(a, set()).add(b)
    assert edges == documented_edges()


def test_module_imports_counts_module_level_imports_only(tmp_path):
    """The graph code finds module-level imports (relative and absolute) and ignores lazy ones."""
    (tmp_path / 'a.py').write_text('from .b import x\n\ndef f():\n    from .c import y\n')
    known = {'lln_ros.x.a': None, 'lln_ros.x.b': None, 'lln_ros.x.c': None}
    assert module_imports('lln_ros.x.a', tmp_path / 'a.py', False, known) == {'lln_ros.x.b'}


def test_every_import_in_the_package_resolves():
    """Imports inside functions too (lazy ones that only fail when called): each names a module
    that exists and a name that module has."""
    import importlib

    known, missing = modules(), []
    for name, (f, is_pkg) in known.items():
        pkg = name.split('.') if is_pkg else name.split('.')[:-1]
        for node in ast.walk(ast.parse(f.read_text())):
            if not isinstance(node, ast.ImportFrom):
                continue
            base = pkg[: len(pkg) - node.level + 1] if node.level else []
            mod = '.'.join(base + ([node.module] if node.module else []))
            if not mod.startswith('lln_ros'):
                continue
            try:
                module = importlib.import_module(mod)
            except ImportError as e:
                missing.append(f'{f.name}:{node.lineno}: {mod} ({e})')
                continue
            for alias in node.names:
                if alias.name != '*' and not hasattr(module, alias.name) and f'{mod}.{alias.name}' not in known:
                    missing.append(f'{f.name}:{node.lineno}: {mod} has no {alias.name}')
    assert missing == []
