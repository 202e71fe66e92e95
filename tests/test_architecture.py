"""The import structure of midas_cli, read from the source with ``ast`` (nothing is imported).

Three rules:

1. No private name crosses a package boundary: ``from midas_cli.X import _y`` is refused where X's top
   package (``session``, ``devices``, ``analysis``, ... or a top-level module such as ``geometry``)
   differs from the importer's.
2. No import cycle between modules, counting module-level imports only. An import inside a function
   body runs when the function is called, after every module has loaded, so it cannot break module
   loading; such lazy imports are allowed (they are how torch and pandas stay out of start-up) and are
   not edges of this graph. Imports under ``if TYPE_CHECKING:`` never run and are skipped everywhere.
   Separately, and stricter: today no loop closes even through lazy imports either (the calibration
   <-> residual_mlp pair did, issue 18 item 5), and ``test_no_cycle_even_through_lazy_imports`` keeps
   it so, with its own allow-list.
3. Layering: a module imports only from its own layer or below (``LAYERS``). This applies to every
   import, lazy ones included: a lazy import still makes the lower layer depend on the upper one.
   Arrows that still point up are listed by name in ``UPWARD_ALLOWED``; the test fails when one of them
   disappears too, so the list only ever shrinks to what is left.
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE_DIR = Path(__file__).resolve().parents[1] / "midas_cli"

# Lowest first. A "unit" is the first component under midas_cli: a subpackage (session, devices, ...) or
# a top-level module (errors, rig, ...); "" is the package itself (midas_cli/__init__.py: __version__).
#   foundations  errors, clock, geometry, early_stop: no midas imports beyond each other
#   jobs         batch runs of units (a session, a fold) here or as SLURM job arrays: options, run folders,
#                markers, executors; it names each task's units module as a string (jobs/tasks.py) and
#                imports it only when a unit runs, never through an import statement
#   session      the session folder format (reading, writing, schema, derived files)
#   devices/synthetic  drivers and emulators, producing session streams (rig files are parsed here,
#                devices/rigconfig.py, because devices/fps/rigfile.py edits them), and the synthetic
#                world the emulators and simulated devices play back (surgeon, hands, feet, console
#                video, stereo camera), which speaks the devices' units (pedal volts, camera calibration):
#                one layer, the cycle rule keeps its modules from looping
#   rig/labels/models  the built-in simulated rig; gesture labels; learned models (gesture networks,
#                the calibration's residual MLP)
#   analysis     alignment, calibration fitting, evaluation
#   record/importers/interop/simulate  producing whole sessions: live recording, imports, exports
#                (interop: MCAP, Parquet, XDF), simulated datasets
#   console/diagnostics  terminal rendering and machine checks
#   commands     the typer CLI
#   __main__     entry point
LAYERS: list[set[str]] = [
    {"", "errors", "clock", "geometry", "config", "processes", "early_stop"},
    {"jobs"},
    {"session"},
    {"devices", "synthetic"},
    {"rig", "labels", "models"},
    {"analysis"},
    {"record", "importers", "interop", "simulate"},
    {"console", "diagnostics"},
    {"commands"},
    {"__main__"},
]

# (importer module, imported module) arrows that point up today, each with why it is still there.
# Remove an entry when its arrow is gone (the test says so).
UPWARD_ALLOWED: dict[tuple[str, str], str] = {
}

# Module-level import cycles still present (each a sorted tuple of the modules in one cycle).
CYCLES_ALLOWED: set[tuple[str, ...]] = set()

# Cycles closed only through lazy (function-level) imports, still present.
LAZY_CYCLES_ALLOWED: set[tuple[str, ...]] = set()

# (importer module, imported module, private name) crossing a package boundary today, with why.
PRIVATE_ALLOWED: dict[tuple[str, str, str], str] = {}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE_DIR.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


MODULES: dict[str, Path] = {module_name(p): p for p in sorted(PACKAGE_DIR.rglob("*.py"))}


def unit(module: str) -> str:
    """``midas_cli.session.reader`` -> ``session``; ``midas_cli`` -> ``""``."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def layer(module: str) -> int:
    found = [i for i, units in enumerate(LAYERS) if unit(module) in units]
    assert found, f"{module}: its unit {unit(module)!r} is in no layer of LAYERS: add it there"
    return found[0]


def resolve(importer: str, node: ast.ImportFrom | ast.Import) -> list[tuple[str, list[str]]]:
    """(imported midas_cli module, names taken from it) for one import statement; other packages skipped.
    ``from midas_cli.a import b`` where ``midas_cli.a.b`` is a module counts as importing that module."""
    if isinstance(node, ast.Import):
        return [(a.name, []) for a in node.names if a.name.split(".")[0] == "midas_cli" and a.name in MODULES]
    if node.level:  # relative import
        package = importer if MODULES[importer].name == "__init__.py" else importer.rpartition(".")[0]
        base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
        target = ".".join(base + ([node.module] if node.module else []))
    else:
        target = node.module or ""
    if target.split(".")[0] != "midas_cli":
        return []
    found: list[tuple[str, list[str]]] = []
    names = []
    for alias in node.names:
        if f"{target}.{alias.name}" in MODULES:
            found.append((f"{target}.{alias.name}", []))
        else:
            names.append(alias.name)
    if names or not found:
        assert target in MODULES, f"{importer}: imports {target}, which is not a module of midas_cli"
        found.append((target, names))
    return found


def is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def imports(module: str) -> list[tuple[str, list[str], bool, int]]:
    """Every midas_cli import of ``module``: (imported module, names, module-level?, line)."""
    tree = ast.parse(MODULES[module].read_text(encoding="utf-8"), str(MODULES[module]))
    found = []

    def visit(node: ast.AST, top: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and is_type_checking(child):
                continue
            if isinstance(child, (ast.Import, ast.ImportFrom)):
                found.extend((target, names, top, child.lineno) for target, names in resolve(module, child))
            inner = top and not isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            visit(child, inner)

    visit(tree, True)
    return found


IMPORTS = {module: imports(module) for module in MODULES}


def test_every_module_is_parsed_and_placed_in_a_layer() -> None:
    assert "midas_cli.analysis.sync" in MODULES and len(MODULES) > 50
    for module in MODULES:
        layer(module)


def is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))  # __version__ is public


def test_no_private_name_is_imported_from_another_package() -> None:
    crossing = {(module, target, name): line
                for module, found in IMPORTS.items() for target, names, _, line in found
                for name in names if is_private(name) and unit(target) != unit(module)}
    new = sorted(f"{m}:{line} imports {name} from {t}" for (m, t, name), line in crossing.items()
                 if (m, t, name) not in PRIVATE_ALLOWED)
    assert not new, "private names used across packages (make them public or move them):\n" + "\n".join(new)
    gone = sorted(set(PRIVATE_ALLOWED) - set(crossing))
    assert not gone, f"these imports are gone: remove them from PRIVATE_ALLOWED: {gone}"


def import_graph(lazy: bool = False) -> dict[str, set[str]]:
    """module -> modules it imports at module level (and in function bodies too when ``lazy``)."""
    graph: dict[str, set[str]] = {module: set() for module in MODULES}
    for module, found in IMPORTS.items():
        for target, _, top, _ in found:
            if (top or lazy) and target != module:
                graph[module].add(target)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[tuple[str, ...]]:
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(tuple(sorted(component)))
    return found


def test_cycle_finder_finds_a_cycle() -> None:
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [("a", "b", "c")]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_no_module_level_import_cycle() -> None:
    found = set(cycles(import_graph()))
    assert not found - CYCLES_ALLOWED, f"module-level import cycles: {sorted(found - CYCLES_ALLOWED)}"
    assert not CYCLES_ALLOWED - found, f"gone, remove from CYCLES_ALLOWED: {sorted(CYCLES_ALLOWED - found)}"


def test_no_cycle_even_through_lazy_imports() -> None:
    """Stricter than the rule above (see the module docstring): a lazy import may defer a heavy
    dependency, but should not be the way two modules that need each other get around rule 2."""
    found = set(cycles(import_graph(lazy=True))) - set(cycles(import_graph()))
    assert not found - LAZY_CYCLES_ALLOWED, f"cycles through lazy imports: {sorted(found - LAZY_CYCLES_ALLOWED)}"
    assert not LAZY_CYCLES_ALLOWED - found, f"gone, remove from LAZY_CYCLES_ALLOWED: {sorted(LAZY_CYCLES_ALLOWED - found)}"


def upward_arrows() -> dict[tuple[str, str], list[str]]:
    arrows: dict[tuple[str, str], list[str]] = {}
    for module, found in IMPORTS.items():
        for target, _, top, line in found:
            if layer(target) > layer(module):
                arrows.setdefault((module, target), []).append(f"line {line}{'' if top else ' (lazy)'}")
    return arrows


def test_imports_point_down_the_layers() -> None:
    arrows = upward_arrows()
    new = {k: v for k, v in arrows.items() if k not in UPWARD_ALLOWED}
    assert not new, "imports pointing up the layers (LAYERS):\n" + "\n".join(
        f"{a} -> {b} ({', '.join(where)})" for (a, b), where in sorted(new.items()))
    gone = sorted(set(UPWARD_ALLOWED) - set(arrows))
    assert not gone, f"these arrows are gone: remove them from UPWARD_ALLOWED: {gone}"


SIZE_LIMIT = 400


def test_modules_are_short_or_say_why() -> None:
    """issue 18: no module over ~400 lines without a stated reason at its top (a module docstring saying
    "over 400 lines" and why)."""
    long = []
    for module, path in MODULES.items():
        text = path.read_text(encoding="utf-8")
        lines = text.count("\n")
        if lines > SIZE_LIMIT and "over 400 lines" not in (ast.get_docstring(ast.parse(text)) or "").lower():
            long.append(f"{module}: {lines} lines")
    assert not long, "split these along a real seam, or say why not at the top:\n" + "\n".join(long)
