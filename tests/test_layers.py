"""The package's shape: imports point one way (down the layers below), no module imports itself
back through others, no module over 600 lines and no function over 80."""
import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# Lower layers first; a module may import its own layer's modules and any below. forms and
# meshes are installed as fem_dual.forms and fem_dual.meshes.
LAYERS = [
    {"errors", "quiet", "choices", "faults", "mpi", "compat", "jit_lock", "jit_header"},
    {"forms", "meshes", "expression", "reference", "output", "petsc_check", "native", "modes"},
    {"scenes"},
    {"slab", "continua"},
    {"config", "inputs"},
    {"integrate"},
    {"analysis", "plots"},
    {"cli"},
]
FOLDERS = {"fem_dual": "fem_dual", "forms": "fem_dual.forms", "meshes": "fem_dual.meshes"}


def _modules():
    """{dotted name: path} of every module of the package."""
    found = {}
    for folder, package in FOLDERS.items():
        for path in (ROOT / folder).rglob("*.py"):
            parts = list(path.relative_to(ROOT / folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            found[".".join([package, *parts])] = path
    return found


def _imports(path: Path, name: str, modules) -> set:
    """The package modules `path` imports (anywhere in it, function bodies included, but not
    under `if TYPE_CHECKING:`)."""
    tree = ast.parse(path.read_text())
    skip = {id(n) for node in ast.walk(tree) if isinstance(node, ast.If)
            and getattr(node.test, "id", None) == "TYPE_CHECKING" for n in ast.walk(node)}
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    out = set()
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package.split(".")[:len(package.split(".")) - node.level + 1]
                                + ([base] if base else []))
            targets = [f"{base}.{alias.name}" for alias in node.names] + [base]
        else:
            continue
        for target in targets:
            while target and target not in modules:
                target = target.rpartition(".")[0]
            if target and target != name:
                out.add(target)
    return out


def _layer(name: str) -> int:
    part = name.split(".")[1] if name.count(".") else ""
    for i, layer in enumerate(LAYERS):
        if part in layer:
            return i
    raise AssertionError(f"{name} is in no layer of tests/test_layers.py")


def _graph():
    modules = _modules()
    return {name: _imports(path, name, modules) for name, path in modules.items()}


def test_imports_point_down_the_layers():
    upward = [f"{a} imports {b}" for a, targets in _graph().items() if a != "fem_dual"
              for b in targets if b != "fem_dual" and _layer(b) > _layer(a)]
    assert not upward, "\n".join(sorted(upward))


def test_no_import_cycle():
    graph = {a: {b for b in t if b != "fem_dual"} for a, t in _graph().items()
             if a != "fem_dual"}
    cycles, state = [], {}

    def visit(node, stack):
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                cycles.append(" -> ".join(stack[stack.index(nxt):] + [nxt]))
            elif nxt not in state:
                visit(nxt, stack)
        stack.pop()
        state[node] = 2
    for node in sorted(graph):
        if node not in state:
            visit(node, [])
    assert not cycles, "\n".join(cycles)


@pytest.mark.parametrize("limit_module, limit_function", [(600, 80)])
def test_modules_and_functions_are_small(limit_module, limit_function):
    large = []
    for name, path in _modules().items():
        text = path.read_text()
        if text.count("\n") > limit_module:
            large.append(f"{name}: {text.count(chr(10))} lines")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                start = min([node.lineno] + [d.lineno for d in node.decorator_list])
                if node.end_lineno - start + 1 > limit_function:
                    large.append(f"{name}.{node.name}: {node.end_lineno - start + 1} lines")
    assert not large, "\n".join(large)
