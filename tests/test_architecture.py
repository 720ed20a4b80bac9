"""Architecture rules, checked on the source with :mod:`ast` (nothing is imported).

* no import cycle among ssp's modules, counting the imports inside functions (those under
  ``if TYPE_CHECKING:`` only when :data:`COUNT_TYPE_CHECKING_IMPORTS`);
* the file holding :class:`~ssp.parser.SceneParser` is at most 400 lines, and none of its
  methods is over 60 lines;
* no function of the scene-parsing core is over 80 lines;
* no module imports another ssp module's private name (``_name``), except from a private module
  (one with a ``_`` component in its dotted name, e.g. ``ssp.io._files``).

The scene-parsing core is every top-level module ``src/ssp/*.py`` and the packages
``ssp.physics`` and ``ssp.library``; the application packages (``ssp.cli``, ``ssp.pipeline``,
``ssp.eval``, ``ssp.sim``, ``ssp.viz``, ``ssp.io``, ``ssp.perception``) are not.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import networkx as nx

SRC = Path(__file__).resolve().parents[1] / "src"
PACKAGE = SRC / "ssp"
CORE_PACKAGES = ("physics", "library")

SCENE_PARSER_FILE_MAX_LINES = 400
SCENE_PARSER_METHOD_MAX_LINES = 60
CORE_FUNCTION_MAX_LINES = 80
#: ``if TYPE_CHECKING:`` imports are for annotations only and never run. The parser's stages
#: annotate their argument with :class:`ssp.frame_context.FrameContext`, whose fields are
#: annotated with the stages' own types (a Triage, a Verdict, ...): a cycle of annotations by
#: construction, while at run time ``ssp.frame_context`` imports no ssp module at all (tested
#: below). The run-time graph, function-level imports included, must have no cycle.
COUNT_TYPE_CHECKING_IMPORTS = False


@dataclass(frozen=True)
class Import:
    """One import statement's reference to an ssp module (``name``: an imported attribute of
    it, or ``None`` for the module itself)."""

    importer: str
    module: str
    name: str | None
    line: int
    #: "" (module level), "in a function" or "under TYPE_CHECKING"
    where: str = ""


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(SRC).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


@cache
def _modules() -> dict[str, Path]:
    """Every ssp module by dotted name (a package by its ``__init__.py``)."""
    return {_module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


@cache
def _tree(path: Path) -> ast.Module:
    return ast.parse(path.read_text(encoding="utf-8"), filename=str(path))


def _rel(path: Path) -> str:
    return str(path.relative_to(SRC.parent))


def _is_core(module: str) -> bool:
    parts = module.split(".")
    if parts[0] != "ssp":
        return False
    if len(parts) == 1:
        return True
    if _modules()[module].parent == PACKAGE:  # a top-level module (ssp/<name>.py)
        return True
    return parts[1] in CORE_PACKAGES


def _package_of(module: str) -> str:
    """The package a module's relative imports are relative to."""
    if _modules()[module].name == "__init__.py":
        return module
    return module.rpartition(".")[0]


def _imports(module: str) -> list[Import]:
    """The ssp imports of ``module`` at any depth (functions, classes, ``if`` blocks)."""
    return _imports_in(_tree(_modules()[module]), module, _package_of(module))


def _imports_in(tree: ast.AST, module: str, package: str) -> list[Import]:
    modules = _modules()
    out: list[Import] = []

    def visit(node: ast.AST, where: str) -> None:
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name == "ssp" or alias.name.startswith("ssp."):
                    out.append(Import(module, alias.name, None, node.lineno, where))
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            if source != "ssp" and not source.startswith("ssp."):
                return
            for alias in node.names:
                if f"{source}.{alias.name}" in modules:  # from ssp.x import submodule
                    out.append(Import(module, f"{source}.{alias.name}", None, node.lineno, where))
                else:
                    out.append(Import(module, source, alias.name, node.lineno, where))
        elif isinstance(node, ast.If) and _is_type_checking(node.test):
            for child in node.body:
                visit(child, where or "under TYPE_CHECKING")
            for child in node.orelse:
                visit(child, where)
        else:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                where = where or "in a function"
            for child in ast.iter_child_nodes(node):
                visit(child, where)

    visit(tree, "")
    return out


def _is_type_checking(test: ast.expr) -> bool:
    """``TYPE_CHECKING`` or ``typing.TYPE_CHECKING``."""
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _import_graph(type_checking: bool = COUNT_TYPE_CHECKING_IMPORTS) -> nx.DiGraph:
    """Module -> module edges of every ssp import (``type_checking``: also those under ``if
    TYPE_CHECKING:``); each edge keeps its import lines ("12", "40 in a function", ...)."""
    modules = _modules()
    graph = nx.DiGraph()
    graph.add_nodes_from(modules)
    for module in modules:
        for imp in _imports(module):
            if imp.module not in modules or imp.module == module:
                continue  # a module that does not exist fails where it is imported
            if imp.where == "under TYPE_CHECKING" and not type_checking:
                continue
            if not graph.has_edge(module, imp.module):
                graph.add_edge(module, imp.module, lines=[])
            line = f"{imp.line} {imp.where}".strip()
            if line not in graph.edges[module, imp.module]["lines"]:
                graph.edges[module, imp.module]["lines"].append(line)
    return graph


def _functions(tree: ast.AST) -> list[ast.FunctionDef | ast.AsyncFunctionDef]:
    return [n for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]


def _span(node: ast.AST) -> int:
    end = node.end_lineno
    assert end is not None
    return end - node.lineno + 1


def _qualified_functions(
    tree: ast.Module,
) -> list[tuple[str, ast.FunctionDef | ast.AsyncFunctionDef]]:
    """Every function and method with its dotted path in the module (nested ones included)."""
    out: list[tuple[str, ast.FunctionDef | ast.AsyncFunctionDef]] = []

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                out.append((prefix + child.name, child))
                visit(child, f"{prefix}{child.name}.")
            elif isinstance(child, ast.ClassDef):
                visit(child, f"{prefix}{child.name}.")
            else:
                visit(child, prefix)

    visit(tree, "")
    return out


# --------------------------------------------------------------------------------------------
# the rules


def test_no_import_cycle() -> None:
    graph = _import_graph()
    problems = []
    for component in nx.strongly_connected_components(graph):
        if len(component) < 2:
            continue
        cycle = nx.find_cycle(graph.subgraph(component))
        steps = [
            f"    {a} -> {b}  ({_rel(_modules()[a])}:" + ", ".join(graph.edges[a, b]["lines"]) + ")"
            for a, b in cycle
        ]
        problems.append(
            f"  {len(component)} modules import each other: {', '.join(sorted(component))}\n"
            "  for example:\n" + "\n".join(steps)
        )
    if problems and COUNT_TYPE_CHECKING_IMPORTS:
        runtime = _import_graph(type_checking=False)
        if all(len(c) < 2 for c in nx.strongly_connected_components(runtime)):
            problems.append("  (without the TYPE_CHECKING imports there would be no cycle)")
    assert not problems, "import cycles among ssp's modules (function-level imports count):\n" + (
        "\n".join(problems)
    )


def test_the_frame_context_imports_no_ssp_module_at_run_time() -> None:
    """The stages' shared context depends on the stages' types for annotations only (the
    reason :data:`COUNT_TYPE_CHECKING_IMPORTS` is off): at run time it imports nothing of ssp,
    so no run-time cycle can pass through it."""
    runtime = [i for i in _imports("ssp.frame_context") if i.where != "under TYPE_CHECKING"]
    assert runtime == [], [f"{i.module} (line {i.line})" for i in runtime]
    assert any(i.where == "under TYPE_CHECKING" for i in _imports("ssp.frame_context"))


def test_the_core_imports_no_application_package() -> None:
    """The scene-parsing core is free of I/O, datasets, perception and presentation: it
    imports none of the application packages, not even inside a function."""
    outside = ("cli", "pipeline", "eval", "sim", "viz", "io", "perception")
    found = [
        f"{i.importer}:{i.line} imports {i.module}"
        for module in _modules()
        if _is_core(module)
        for i in _imports(module)
        if i.module.split(".")[1:2] and i.module.split(".")[1] in outside
    ]
    assert found == [], "\n".join(found)


def test_the_import_checker_sees_nested_and_relative_imports() -> None:
    """The checker itself: imports inside functions and classes count, ``from ssp.x import m``
    of a submodule ``m`` is an import of ``ssp.x.m``, relative imports are resolved."""
    code = (
        "import numpy\n"
        "def f():\n"
        "    from ssp.scene import Frame\n"
        "    class C:\n"
        "        import ssp.parser as p\n"
        "from ssp import physics\n"
        "from ssp.physics import world\n"
        "from .geometry import validate_pose\n"
        "if TYPE_CHECKING:\n"
        "    from ssp.estimate import SceneEstimate\n"
    )
    found = {(i.module, i.name, i.where) for i in _imports_in(ast.parse(code), "ssp.forces", "ssp")}
    assert found == {
        ("ssp.scene", "Frame", "in a function"),
        ("ssp.parser", None, "in a function"),
        ("ssp.physics", None, ""),
        ("ssp.physics.world", None, ""),
        ("ssp.geometry", "validate_pose", ""),
        ("ssp.estimate", "SceneEstimate", "under TYPE_CHECKING"),
    }
    graph = _import_graph()
    assert graph.has_edge("ssp", "ssp.config")  # ssp/__init__.py's top-level import


def test_scene_parser_file_and_methods_are_short() -> None:
    holders = [
        (path, node)
        for path in _modules().values()
        for node in ast.walk(_tree(path))
        if isinstance(node, ast.ClassDef) and node.name == "SceneParser"
    ]
    assert len(holders) == 1, f"class SceneParser defined {len(holders)} times"
    path, cls = holders[0]
    problems = []
    n_lines = len(path.read_text(encoding="utf-8").splitlines())
    if n_lines > SCENE_PARSER_FILE_MAX_LINES:
        problems.append(
            f"  {_rel(path)} has {n_lines} lines (at most {SCENE_PARSER_FILE_MAX_LINES})"
        )
    for node in cls.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            if _span(node) > SCENE_PARSER_METHOD_MAX_LINES:
                problems.append(
                    f"  SceneParser.{node.name} ({_rel(path)}:{node.lineno}) has "
                    f"{_span(node)} lines (at most {SCENE_PARSER_METHOD_MAX_LINES})"
                )
    assert not problems, "SceneParser is too long:\n" + "\n".join(problems)


def test_core_functions_are_short() -> None:
    problems = []
    for module, path in _modules().items():
        if not _is_core(module):
            continue
        for name, node in _qualified_functions(_tree(path)):
            if _span(node) > CORE_FUNCTION_MAX_LINES:
                problems.append(f"  {_rel(path)}:{node.lineno} {name}: {_span(node)} lines")
    assert not problems, (
        f"functions of the scene-parsing core over {CORE_FUNCTION_MAX_LINES} lines:\n"
        + "\n".join(problems)
    )


def test_core_is_what_the_docs_say() -> None:
    assert _is_core("ssp") and _is_core("ssp.parser") and _is_core("ssp.physics.world")
    assert _is_core("ssp.library.mesh")
    for app in ("cli", "pipeline", "eval", "sim", "viz", "io", "perception"):
        for module in _modules():
            if module == f"ssp.{app}" or module.startswith(f"ssp.{app}."):
                assert not _is_core(module), module


def _is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def _private_module(module: str) -> bool:
    return any(_is_private(part) for part in module.split("."))


def _private_uses(module: str) -> list[str]:
    path = _modules()[module]
    return _private_uses_in(_tree(path), module, _rel(path))


def _private_uses_in(tree: ast.Module, module: str, where: str) -> list[str]:
    """``from ssp.x import _y`` and ``<ssp.x>._y`` (through ``import ssp.x [as m]`` or
    ``from ssp import x``) in ``module``, of a module ``ssp.x`` that is not itself private."""
    modules = _modules()
    out: list[tuple[int, str]] = []
    aliases: dict[str, str] = {}  # local name -> the ssp module it is bound to
    for imp in _imports_in(tree, module, _package_of(module)):
        if imp.module == module or imp.module not in modules or _private_module(imp.module):
            continue
        if imp.name is not None and _is_private(imp.name):
            out.append((imp.line, f"  {where}:{imp.line} from {imp.module} import {imp.name}"))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name in modules:
                    aliases[alias.asname or alias.name.split(".")[0]] = (
                        alias.name if alias.asname else alias.name.split(".")[0]
                    )
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            for alias in node.names:
                if f"{node.module}.{alias.name}" in modules:
                    aliases[alias.asname or alias.name] = f"{node.module}.{alias.name}"
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Attribute) and _is_private(node.attr)):
            continue
        target = _dotted(node.value, aliases)
        if (
            target in modules
            and target != module
            and not _private_module(target)
            and f"{target}.{node.attr}" not in modules
        ):
            out.append((node.lineno, f"  {where}:{node.lineno} {target}.{node.attr}"))
    return [text for _, text in sorted(out)]


def _dotted(node: ast.expr, aliases: dict[str, str]) -> str | None:
    """The ssp module an expression such as ``ssp.x`` or ``m`` (bound to one) names."""
    if isinstance(node, ast.Name):
        return aliases.get(node.id)
    if isinstance(node, ast.Attribute):
        base = _dotted(node.value, aliases)
        return None if base is None else f"{base}.{node.attr}"
    return None


def test_the_private_name_checker() -> None:
    code = (
        "import ssp.scene\n"
        "import ssp.physics.world as w\n"
        "from ssp import geometry\n"
        "from ssp.io._files import write_json\n"
        "from ssp.library import _coacd_worker\n"
        "from ssp.registration import _exact_icp, grid_icp\n"
        "def f():\n"
        "    ssp.scene._clean_points(1)\n"
        "    w._install_warning_handler()\n"
        "    geometry._x\n"
        "    _coacd_worker._main\n"
        "    ssp.scene.__name__\n"
        "    ssp.io._files.write_json\n"
    )
    found = _private_uses_in(ast.parse(code), "ssp.forces", "f.py")
    assert found == [
        "  f.py:6 from ssp.registration import _exact_icp",
        "  f.py:8 ssp.scene._clean_points",
        "  f.py:9 ssp.physics.world._install_warning_handler",
        "  f.py:10 ssp.geometry._x",
    ], found


def test_no_private_names_across_modules() -> None:
    problems = [line for module in _modules() for line in _private_uses(module)]
    assert not problems, (
        "private names used from another ssp module (make them public, or move them to a "
        "private module such as ssp.io._files):\n" + "\n".join(problems)
    )


def test_the_kernel_cache_is_keyed_by_every_module_that_defines_kernels() -> None:
    # ssp.jit.kernel_cache_dir digests KERNEL_MODULES: a module with kernels left out would
    # let a caller keep a stale copy of its kernels (numba keys a cache by one file)
    from ssp.jit import KERNEL_MODULES

    pkg = SRC / "ssp"
    users = set()
    for path in pkg.rglob("*.py"):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module == "ssp.jit":
                if any(a.name == "njit" for a in node.names):
                    users.add(path.relative_to(pkg).as_posix())
    assert users | {"jit.py"} == set(KERNEL_MODULES)
