"""The package's boundaries, read from the source with ``ast`` (nothing is imported): no import
cycles among ncfix modules (function-local imports count: one used to hide a cycle is still a
cycle), no package using another package's private names, and function-local imports only where
a heavy dependency is loaded lazily on purpose (the allow-list below says why for each)."""

from __future__ import annotations

import ast
import functools
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "ncfix"

# (importing module, imported module or package) -> why the import sits inside a function. Only
# heavy dependencies, loaded when a run needs them: torch (the CPU path never imports it,
# test_startup), CoACD, rich, and ncfix's own numeric stack (numpy, numba kernels, coal, trimesh:
# seconds), which ``import ncfix``, ``ncfix --help`` and a run without ``--head`` never load.
_LIGHT_START = "`import ncfix` and `ncfix --help` load no numpy/numba; a run loads them"
_NO_HEAD = "the checker's stack (coal, trimesh, compiled kernels: seconds) loads only with --head"
_WARM = ("trimesh (with scipy and networkx: about a second) loads only to read a mesh or build a model the "
         "cache does not hold: a warm-cache check never imports it (test_startup)")
_KD_TREES = "scipy's k-d trees load only where a run searches points with them, never in a warm-cache check"
_WARM_FIX = ("trimesh and scipy's qhull load only to hull the head or decompose a part the cache does not hold: "
             "a warm-cache fix never imports them (test_startup)")
_NO_NUMBA = ("numba (with the scipy.linalg it loads: about 0.5 s with its compiler's start) loads only with a "
             "compiled kernel's first call: a pass-through never imports it (test_startup)")
LAZY_IMPORTS = {
    ("ncfix.api", "ncfix.pipeline"): _LIGHT_START,
    ("ncfix.api", "ncfix.profiles"): _LIGHT_START,
    ("ncfix.api", "ncfix.report.html"): _LIGHT_START + " (--html)",
    ("ncfix.cli", "ncfix.profiles"): _LIGHT_START + " (--list-machines)",
    ("ncfix.cli", "ncfix.report.summary"): "rich and numpy load only when a summary is printed",
    ("ncfix.cli", "rich"): "rich loads only when a progress bar is shown",
    ("ncfix.config", "ncfix.geometry.place"): _LIGHT_START + " (a mesh placement)",
    ("ncfix.geometry.frames", "ncfix.geometry.rodrigues"): _NO_NUMBA + " (the profiles' kinematics import frames)",
    ("ncfix.nc.modal", "ncfix.nc.plain_jit"): _NO_NUMBA + " (the numpy reader reads a short program)",
    ("ncfix.pipeline", "ncfix.collision"): _NO_HEAD,
    ("ncfix.pipeline", "ncfix.correct"): _NO_HEAD,
    ("ncfix.pipeline", "ncfix.geometry"): _NO_HEAD,
    ("ncfix.collision.checker", "torch"): "the CPU path never imports torch (test_startup)",
    ("ncfix.collision.deposit", "torch"): "the CPU path never imports torch (test_startup)",
    ("ncfix.collision.grid", "torch"): "the CPU path never imports torch (test_startup)",
    ("ncfix.correct.decompose", "coacd"): "CoACD loads only when a head is decomposed (a cache miss)",
    ("ncfix.geometry.mesh", "trimesh"): _WARM,
    ("ncfix.geometry.meshdata", "trimesh"): _WARM,
    ("ncfix.collision.exact", "trimesh"): _WARM,
    ("ncfix.collision.proximity", "trimesh"): _WARM,
    ("ncfix.collision.head", "scipy"): _KD_TREES,
    ("ncfix.collision.deposit", "scipy"): _KD_TREES,
    ("ncfix.collision.implied", "scipy"): _KD_TREES,
    ("ncfix.correct.candidates", "scipy"): _KD_TREES,
    ("ncfix.correct.graph", "scipy"): _KD_TREES,
    ("ncfix.correct.decompose", "trimesh"): _WARM_FIX,
    ("ncfix.correct.epa", "trimesh"): _WARM_FIX,
    ("ncfix.correct.epa", "scipy"): _WARM_FIX,
}


def _allowed(importer: str, target: str) -> bool:
    """Whether LAZY_IMPORTS lists this import (an entry names a module or a package of them)."""
    return any(importer == who and (target == what or target.startswith(what + "."))
               for who, what in LAZY_IMPORTS)


@dataclass(frozen=True)
class Import:
    importer: str  # module name
    target: str  # module name (``from a import b`` names module a.b when it is one, else a)
    names: tuple[str, ...]  # the names taken by ``from ... import``
    line: int
    local: bool  # inside a function
    typing_only: bool  # under ``if TYPE_CHECKING:``


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {_module_name(path): path for path in sorted(PACKAGE.rglob("*.py"))}


def _package_of(module: str, modules: dict[str, Path]) -> str:
    """The package a module belongs to (a package's ``__init__`` belongs to itself)."""
    if modules[module].name == "__init__.py":
        return module
    return module.rpartition(".")[0]


@functools.cache
def _tree(path: Path) -> ast.Module:
    return ast.parse(path.read_text(encoding="utf-8"), str(path))


def _imports(module: str, path: Path, modules: dict[str, Path]) -> list[Import]:
    tree = _tree(path)
    package = _package_of(module, modules)
    found: list[Import] = []

    def visit(node: ast.AST, local: bool, typing_only: bool) -> None:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            local = True
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for child in node.body:
                visit(child, local, True)
            for child in node.orelse:
                visit(child, local, typing_only)
            return
        if isinstance(node, ast.Import):
            for alias in node.names:
                found.append(Import(module, alias.name, (), node.lineno, local, typing_only))
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            names = tuple(alias.name for alias in node.names)
            submodules = [name for name in names if f"{source}.{name}" in modules]
            for name in submodules:
                found.append(Import(module, f"{source}.{name}", (), node.lineno, local, typing_only))
            rest = tuple(name for name in names if name not in submodules)
            if rest or not submodules:
                found.append(Import(module, source, rest, node.lineno, local, typing_only))
        for child in ast.iter_child_nodes(node):
            visit(child, local, typing_only)

    visit(tree, False, False)
    return found


def _all_imports() -> tuple[dict[str, Path], list[Import]]:
    modules = _modules()
    found = []
    for module, path in modules.items():
        found.extend(_imports(module, path, modules))
    return modules, found


def _cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), and self-imports."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []

    def connect(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for succ in sorted(edges.get(node, ())):
            if succ not in index:
                connect(succ)
                low[node] = min(low[node], low[succ])
            elif succ in on_stack:
                low[node] = min(low[node], index[succ])
        if low[node] == index[node]:
            component = []
            while True:
                top = stack.pop()
                on_stack.discard(top)
                component.append(top)
                if top == node:
                    break
            if len(component) > 1 or node in edges.get(node, ()):
                out.append(sorted(component))

    for node in sorted(edges):
        if node not in index:
            connect(node)
    return out


def test_no_import_cycles_among_ncfix_modules():
    """Module-level and function-local imports alike (an import inside a function that would loop
    at module level is the same loop, only hidden); ``if TYPE_CHECKING:`` imports never run."""
    modules, found = _all_imports()
    edges: dict[str, set[str]] = {}
    where: dict[tuple[str, str], Import] = {}
    for imp in found:
        if imp.target in modules and not imp.typing_only and imp.target != imp.importer:
            edges.setdefault(imp.importer, set()).add(imp.target)
            where.setdefault((imp.importer, imp.target), imp)
    cycles = _cycles(edges)
    lines = []
    for component in cycles:
        members = set(component)
        links = [f"{a} -> {b} (line {where[a, b].line}{', in a function' if where[a, b].local else ''})"
                 for a in component for b in sorted(edges.get(a, ())) if b in members]
        lines.append("cycle among " + ", ".join(component) + ":\n    " + "\n    ".join(links))
    assert not cycles, "\n".join(lines)


def _private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def test_no_package_uses_another_packages_private_names():
    """``from ncfix.x.y import _name`` and ``y._name`` (y an ncfix module) only within one package:
    what another package needs is public."""
    modules, found = _all_imports()
    bad = []
    for imp in found:
        if imp.target not in modules:
            continue
        own, theirs = _package_of(imp.importer, modules), _package_of(imp.target, modules)
        if own == theirs:
            continue
        for name in imp.names:
            if _private(name):
                bad.append(f"{imp.importer} line {imp.line}: from {imp.target} import {name}")
    for module, path in modules.items():
        tree = _tree(path)
        own = _package_of(module, modules)
        bound: dict[str, str] = {}  # local name -> ncfix module it names
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for alias in node.names:
                    if alias.name in modules:
                        bound[alias.asname or alias.name] = alias.name
            elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
                for alias in node.names:
                    if f"{node.module}.{alias.name}" in modules:
                        bound[alias.asname or alias.name] = f"{node.module}.{alias.name}"
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and _private(node.attr):
                target = bound.get(ast.unparse(node.value))
                if target is not None and _package_of(target, modules) != own:
                    bad.append(f"{module} line {node.lineno}: {ast.unparse(node)}")
    assert not bad, "private names used across packages:\n  " + "\n  ".join(sorted(set(bad)))


def _private_members_by_package(modules: dict[str, Path]) -> dict[str, set[str]]:
    """Per package, the private names its classes define (methods, ``self._x`` attributes)."""
    out: dict[str, set[str]] = {}
    for module, path in modules.items():
        names = out.setdefault(_package_of(module, modules), set())
        for node in ast.walk(_tree(path)):
            if isinstance(node, ast.ClassDef):
                for item in ast.walk(node):
                    if isinstance(item, (ast.FunctionDef, ast.AsyncFunctionDef)) and _private(item.name):
                        names.add(item.name)
                    elif (isinstance(item, ast.Attribute) and isinstance(item.ctx, ast.Store)
                          and _private(item.attr)):
                        names.add(item.attr)
                    elif isinstance(item, ast.AnnAssign) and isinstance(item.target, ast.Name) \
                            and _private(item.target.id):
                        names.add(item.target.id)
    return out


def test_no_package_calls_another_packages_private_methods():
    """``obj._name`` (obj not ``self``/``cls``) where only another package's classes define
    ``_name``: the corrector reaches the checker through its public methods."""
    modules = _modules()
    members = _private_members_by_package(modules)
    bad = []
    for module, path in modules.items():
        own = _package_of(module, modules)
        for node in ast.walk(_tree(path)):
            if not (isinstance(node, ast.Attribute) and _private(node.attr)):
                continue
            if isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"):
                continue
            if node.attr in members.get(own, ()):
                continue
            owners = sorted(pkg for pkg, names in members.items() if pkg != own and node.attr in names)
            if owners:
                bad.append(f"{module} line {node.lineno}: {ast.unparse(node)} (defined in {', '.join(owners)})")
    assert not bad, "private members used across packages:\n  " + "\n  ".join(bad)


def test_function_local_imports_are_deliberate_lazy_loads():
    """An import inside a function is either a heavy dependency loaded only when needed (listed in
    ``LAZY_IMPORTS`` with the reason) or belongs at the top of the module."""
    _, found = _all_imports()
    bad = sorted({f"{imp.importer} line {imp.line}: {imp.target}" for imp in found
                  if imp.local and not _allowed(imp.importer, imp.target)})
    assert not bad, "function-local imports not in LAZY_IMPORTS:\n  " + "\n  ".join(bad)


@pytest.mark.parametrize("entry", sorted(LAZY_IMPORTS))
def test_every_lazy_import_listed_is_still_used(entry):
    """The allow-list stays short: an entry whose import is gone is removed."""
    _, found = _all_imports()
    who, what = entry
    assert any(imp.local and imp.importer == who and (imp.target == what or imp.target.startswith(what + "."))
               for imp in found), entry


# Hard dependencies (pyproject.toml) imported as plain imports: no fallback for their absence.
# torch is left out: the checker says in one line that --device cuda needs it.
REQUIRED = {"numba", "numpy", "scipy", "edt", "trimesh", "coal", "manifold3d", "rtree", "rich", "coacd"}


def test_required_dependencies_have_no_import_fallbacks():
    """``try: import numba ... except ImportError`` gives a second, untested code path for a
    package the install always has: one decision per dependency."""
    bad = []
    for module, path in _modules().items():
        for node in ast.walk(_tree(path)):
            if not isinstance(node, ast.Try):
                continue
            caught = {ast.unparse(h.type) for h in node.handlers if h.type is not None}
            if not caught & {"ImportError", "ModuleNotFoundError"}:
                continue
            for inner in (n for stmt in node.body for n in ast.walk(stmt)):
                names = ([a.name for a in inner.names] if isinstance(inner, ast.Import)
                         else [inner.module or ""] if isinstance(inner, ast.ImportFrom) else [])
                for name in names:
                    if name.split(".")[0] in REQUIRED:
                        bad.append(f"{module} line {node.lineno}: {name}")
    assert not bad, "fallbacks for required packages:\n  " + "\n  ".join(bad)


def test_dialect_names_are_compared_only_in_the_dialects_module():
    """What a controller family spells differently lives in ``ncfix.nc.dialects``: elsewhere code
    asks the profile's Dialect, never ``profile.dialect == "heidenhain"``."""
    modules = _modules()
    names = {call.args[0].value for call in ast.walk(_tree(modules["ncfix.nc.dialects"]))
             if isinstance(call, ast.Call) and ast.unparse(call.func) == "Dialect"}
    assert names >= {"iso", "sinumerik", "heidenhain"}
    bad = []
    for module, path in modules.items():
        if module == "ncfix.nc.dialects":
            continue
        for node in ast.walk(_tree(path)):
            if isinstance(node, ast.Compare):
                sides = [node.left, *node.comparators]
                sides += [e for s in sides if isinstance(s, (ast.Tuple, ast.List, ast.Set)) for e in s.elts]
                if any(isinstance(s, ast.Constant) and s.value in names for s in sides):
                    bad.append(f"{module} line {node.lineno}: {ast.unparse(node)}")
    assert not bad, "dialect names compared outside ncfix.nc.dialects:\n  " + "\n  ".join(bad)


def test_public_constructors_have_type_hints():
    """A public class's ``__init__`` says what each argument is: the constructor is where a
    newcomer meets a class."""
    bad = []
    for module, path in _modules().items():
        for cls in _tree(path).body:
            if not isinstance(cls, ast.ClassDef) or cls.name.startswith("_"):
                continue
            for init in (f for f in cls.body if isinstance(f, ast.FunctionDef) and f.name == "__init__"):
                args = init.args.posonlyargs + init.args.args[1:] + init.args.kwonlyargs
                missing = [a.arg for a in args if a.annotation is None]
                if missing:
                    bad.append(f"{module}.{cls.name}: {', '.join(missing)}")
    assert not bad, "constructors without type hints:\n  " + "\n  ".join(bad)
