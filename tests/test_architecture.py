"""The package graph (docs/design.md §2): uavloc ← estimator ← planner ← mission ← sitl_scenarios, no
import cycle, and estimator/planner free of I/O, sockets, asyncio and clocks.

Read from the source with `ast` (every import, at module level, inside functions and under
`if TYPE_CHECKING:` alike: a type-only import is a dependency too), so the test needs no import
side effects. What breaks the rules today is listed by name below (module granularity, so a
colleague's new import in a listed module does not break the build); anything else that breaks
them fails. Issue 12 phase 2 empties the lists.
"""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: a package may import only packages of its own or a lower layer
LAYERS = {"uavloc": 0, "estimator": 1, "planner": 2, "mission": 3, "sitl_scenarios": 4}

#: modules that import a higher layer (module → the higher package): none. Issue 12 phase 2 emptied
#: the list (mission file for `uavloc fly --mission`, sim runner and `sim` command in sitl_scenarios,
#: found through the `uavloc.commands` entry point).
KNOWN_UPWARD_IMPORTS: dict[str, str] = {}

#: pure packages (docs/design.md §2): no asyncio, sockets, files, clocks, processes or threads
PURE_PACKAGES = ("estimator", "planner")
IMPURE_MODULES = frozenset({
    "asyncio", "socket", "socketserver", "selectors", "select", "ssl", "signal", "time", "datetime", "os",
    "pathlib", "io", "shutil", "tempfile", "glob", "subprocess", "threading", "multiprocessing", "concurrent",
    "urllib", "http", "sqlite3", "pickle", "mavsdk", "pymavlink", "matplotlib", "shapely", "random",
})
IMPURE_BUILTINS = frozenset({"open", "print", "input", "exec", "eval", "breakpoint"})
#: (module, impure module) pairs allowed: none (the controller times `planner.plan(...)`).
KNOWN_IMPURE: frozenset[tuple[str, str]] = frozenset()


def project_modules() -> dict[str, Path]:
    """{dotted module name: file} of every module of the five packages."""
    out = {}
    for pkg in LAYERS:
        for f in sorted((ROOT / pkg).rglob("*.py")):
            parts = list(f.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = f
    return out


def imports_of(path: Path, modules: dict[str, Path]) -> tuple[set[str], set[str]]:
    """(project modules imported, top-level names of other imported modules) by one file."""
    ours, others = set(), set()
    pkg = path.parent.relative_to(ROOT).parts
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative import
                base = ".".join([*pkg[: len(pkg) - node.level + 1], *([base] if base else [])])
            # `from mission import geometry` imports the module mission.geometry
            names = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]
        for name in names:
            if name.split(".")[0] in LAYERS:
                while name and name not in modules:
                    name = name.rpartition(".")[0]
                if name:
                    ours.add(name)
            else:
                others.add(name.split(".")[0])
    return ours, others


def import_graph() -> tuple[dict[str, set[str]], dict[str, set[str]]]:
    """({module: project modules it imports}, {module: other top-level modules it imports})."""
    modules = project_modules()
    ours, others = {}, {}
    for name, path in modules.items():
        ours[name], others[name] = imports_of(path, modules)
    return ours, others


def upward_imports(graph: dict[str, set[str]]) -> dict[str, set[str]]:
    """{module: the modules of a higher layer it imports}."""
    out = defaultdict(set)
    for mod, targets in graph.items():
        for t in targets:
            if LAYERS[t.split(".")[0]] > LAYERS[mod.split(".")[0]]:
                out[mod].add(t)
    return dict(out)


def mission_imports_of_sitl_scenarios(graph: dict[str, set[str]]) -> dict[str, set[str]]:
    """{mission module: the sitl_scenarios modules it imports} (empty once phase 2 is done)."""
    return {m: {t for t in ts if t.split(".")[0] == "sitl_scenarios"}
            for m, ts in graph.items() if m.split(".")[0] == "mission"
            and any(t.split(".")[0] == "sitl_scenarios" for t in ts)}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one node (Tarjan), each sorted."""
    index, low, on, stack, out = {}, {}, set(), [], []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def package_graph(graph: dict[str, set[str]], drop_known: bool) -> dict[str, set[str]]:
    """{package: packages it imports} (self-imports left out), optionally without the known upward ones."""
    out: dict[str, set[str]] = {p: set() for p in LAYERS}
    for mod, targets in graph.items():
        src = mod.split(".")[0]
        for t in targets:
            dst = t.split(".")[0]
            if dst != src and not (drop_known and KNOWN_UPWARD_IMPORTS.get(mod) == dst):
                out[src].add(dst)
    return out


# ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def graph():
    return import_graph()


def test_the_reader_sees_the_imports_it_must():
    """The analysis itself: known imports of known modules are found (a reader that found nothing
    would pass every test below)."""
    ours, others = import_graph()
    assert "estimator.geodesy" in ours["mission.config"] and "uavloc.errors" in ours["mission.config"]
    assert "mission.geometry" in ours["mission.safety"]       # `from mission import geometry`
    assert "mission.report.inputs" in ours["mission.report.exports"]
    assert "planner.types" in ours["sitl_scenarios.scenario"]
    assert "mission.schema" in ours["sitl_scenarios.scenario"]  # `from mission import schema`
    assert {"numpy", "pymap3d"} <= others["estimator.geodesy"]
    assert "asyncio" in others["mission.control.flight"]


def test_every_import_goes_down_the_layers(graph):
    ours, _ = graph
    new = {m: ts for m, ts in upward_imports(ours).items()
           if not all(t.split(".")[0] == KNOWN_UPWARD_IMPORTS.get(m) for t in ts)}
    assert not new, f"imports of a higher layer (docs/design.md §2: {' ← '.join(LAYERS)}): {new}"


def test_mission_imports_sitl_scenarios_only_where_known(graph):
    """Phase 2 switch: with KNOWN_UPWARD_IMPORTS = {} this says mission never imports sitl_scenarios."""
    ours, _ = graph
    known = {m for m, p in KNOWN_UPWARD_IMPORTS.items() if p == "sitl_scenarios" and m.startswith("mission")}
    offenders = set(mission_imports_of_sitl_scenarios(ours))
    assert offenders <= known, f"mission modules importing sitl_scenarios: {sorted(offenders - known)}"


def test_no_cycle_between_packages_besides_the_known_upward_imports(graph):
    ours, _ = graph
    assert cycles(package_graph(ours, drop_known=True)) == []
    # and the layers are what docs/design.md §2 draws: every remaining package edge points down
    for src, dsts in package_graph(ours, drop_known=True).items():
        assert all(LAYERS[d] < LAYERS[src] for d in dsts), (src, dsts)


def without_known_upward(graph: dict[str, set[str]]) -> dict[str, set[str]]:
    """The module graph without the listed upward imports (they close cycles until phase 2)."""
    return {m: {t for t in ts if t.split(".")[0] != KNOWN_UPWARD_IMPORTS.get(m)} for m, ts in graph.items()}


def test_no_import_cycle_between_any_two_modules(graph):
    """Function-level and type-only imports included: a cycle is a cycle (besides those the listed
    upward imports close: planner.types → sitl_scenarios.scenario → mission.config → planner.types)."""
    ours, _ = graph
    assert cycles(without_known_upward(ours)) == []


def test_no_import_cycle_between_modules_of_estimator_and_planner(graph):
    ours, _ = graph
    pure = {m: {t for t in ts if t.split(".")[0] in ("uavloc", *PURE_PACKAGES)}
            for m, ts in ours.items() if m.split(".")[0] in PURE_PACKAGES}
    assert cycles(pure) == []


def test_no_import_cycle_in_the_report_package(graph):
    ours, _ = graph
    report = {m: {t for t in ts if t.startswith("mission.report.")}
              for m, ts in ours.items() if m.startswith("mission.report.")}
    assert len(report) >= 6 and cycles(report) == []


def test_estimator_and_planner_do_no_io_and_read_no_clock(graph):
    _, others = graph
    found = {(m, o) for m, os_ in others.items() if m.split(".")[0] in PURE_PACKAGES
             for o in os_ if o in IMPURE_MODULES}
    assert found <= KNOWN_IMPURE, f"I/O, clocks or concurrency in a pure package: {sorted(found - KNOWN_IMPURE)}"
    calls = []
    for name, path in project_modules().items():
        if name.split(".")[0] not in PURE_PACKAGES:
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in IMPURE_BUILTINS:
                calls.append(f"{name}:{node.lineno} {node.func.id}()")
            if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                    and node.func.attr in {"load", "save", "savez", "loadtxt", "savetxt", "fromfile", "tofile"}
                    and isinstance(node.func.value, ast.Name) and node.func.value.id in {"np", "numpy"}):
                calls.append(f"{name}:{node.lineno} np.{node.func.attr}()")
    assert calls == [], calls


#: parameter names that say "a simulation scenario" (its dataclass, sitl_scenarios.scenario.Scenario)
SCENARIO_PARAMETERS = frozenset({"scenario", "sc"})


def scenario_uses(tree: ast.AST) -> list[str]:
    """Where a module takes a simulation scenario: a `from_scenario` adapter, a parameter named
    like a scenario or annotated with `Scenario`, a call of the scenario's `mission_config()`."""
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            if node.name.endswith("from_scenario"):
                out.append(f"{node.lineno} def {node.name}")
            a = node.args
            for arg in [*a.posonlyargs, *a.args, *a.kwonlyargs, a.vararg, a.kwarg]:
                if arg is None:
                    continue
                if arg.arg in SCENARIO_PARAMETERS:
                    out.append(f"{node.lineno} {node.name}({arg.arg})")
                if arg.annotation is not None and "Scenario" in ast.unparse(arg.annotation):
                    out.append(f"{node.lineno} {node.name}({arg.arg}: {ast.unparse(arg.annotation)})")
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "mission_config":
            out.append(f"{node.lineno} .mission_config()")
    return out


def test_scenario_uses_are_seen():
    """The reader itself: each kind of use is found (a reader finding nothing would pass below)."""
    src = ("class C:\n    @classmethod\n    def from_scenario(cls, x): pass\n"
           "def f(scenario): pass\ndef g(x: Scenario): pass\ndef h(y): return y.mission_config()\n")
    assert len(scenario_uses(ast.parse(src))) == 4


def test_mission_and_planner_take_no_scenario():
    """A simulation scenario is sitl_scenarios' business: mission/ and planner/ are configured by a
    mission file's objects (mission.config) and the planner's own types, never by a scenario."""
    found = {}
    for name, path in project_modules().items():
        if name.split(".")[0] in ("mission", "planner"):
            uses = scenario_uses(ast.parse(path.read_text(encoding="utf-8")))
            if uses:
                found[name] = uses
    assert found == {}, f"a scenario taken in mission/ or planner/: {found}"
