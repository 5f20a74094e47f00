"""No import circle inside the package, and one direction between its layers: the graph of which `pi0_torch` module
imports which -- at module level and inside functions alike (an import moved into a function still runs; it only hides
a circle) -- has no cycle, but for the exceptions listed in `ALLOWED` (the registration ring inside `models/`), each
with its reason; and the engine's folders import only downward (`LAYERS`). `TYPE_CHECKING` imports never run and are
left out; a package is imported before its modules by Python itself, which is not an edge here either."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "pi0_torch"

# (importer, imported): the edges a cycle may use, and why.
ALLOWED: dict[tuple[str, str], str] = {
    (registry, model): "the AutoConfig / AutoModel registry: the configs call it when one is created, and it imports "
                       "the classes only then, so that `import pi0_torch` imports neither torch nor transformers "
                       "(transformers looks a model class up by config class)"
    for registry in ("pi0_torch.models.auto_registration",)
    for model in ("pi0_torch.models.configuration_pi0", "pi0_torch.models.configuration_pi0_fast",
                  "pi0_torch.models.modeling_pi0", "pi0_torch.models.modeling_pi0_fast")
}


# The engine's layers, top to bottom: a module of one may import its own folder and the folders after it, nothing else
# of the package (the models import the engine, the engine never the models: it is handed them).
LAYERS: tuple[tuple[str, ...], ...] = (
    ("pi0_torch.inference",),
    ("pi0_torch.kernels",),
    ("pi0_torch.utils", "pi0_torch.masks"),
)


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_graph() -> dict[str, dict[str, str]]:
    """importer -> {imported: "module" or "function"} over the modules of `pi0_torch`."""
    modules = {_module_name(path): path for path in PACKAGE.rglob("*.py")}
    graph: dict[str, dict[str, str]] = {}
    for name, path in modules.items():
        tree = ast.parse(path.read_text())
        skipped = {id(node) for guard in ast.walk(tree) if isinstance(guard, ast.If) and ast.unparse(guard.test) == "TYPE_CHECKING"
                   for node in ast.walk(guard)}
        in_function = {id(node) for function in ast.walk(tree) if isinstance(function, (ast.FunctionDef, ast.AsyncFunctionDef))
                       for node in ast.walk(function)}
        edges = graph.setdefault(name, {})
        for node in ast.walk(tree):
            if not isinstance(node, (ast.Import, ast.ImportFrom)) or id(node) in skipped:
                continue
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            else:
                base = node.module or ""
                if node.level:  # relative: from the package of this module
                    package = name.split(".")[: len(name.split(".")) - (node.level - (path.name == "__init__.py"))]
                    base = ".".join([*package, *([node.module] if node.module else [])])
                targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base for alias in node.names]
            for target in targets:
                while target and target not in modules:  # `import pi0_torch.a.b as x`, `from m import name`
                    target = target.rpartition(".")[0]
                if target and target != name and edges.get(target) != "module":
                    edges[target] = "function" if id(node) in in_function else "module"
    return graph


def find_cycle(graph: dict[str, dict[str, str]]) -> list[str] | None:
    """One cycle of `graph` as a path `[a, b, ..., a]`, or None."""
    state: dict[str, str] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = "open"
        stack.append(node)
        for nxt in sorted(graph.get(node, {})):
            if state.get(nxt) == "open":
                return [*stack[stack.index(nxt):], nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        state[node] = "done"
        stack.pop()
        return None

    for node in sorted(graph):
        if node not in state and (cycle := visit(node)):
            return cycle
    return None


def test_no_import_circle_but_the_listed_ones() -> None:
    graph = import_graph()
    pruned = {importer: {imported: kind for imported, kind in edges.items() if (importer, imported) not in ALLOWED}
              for importer, edges in graph.items()}
    cycle = find_cycle(pruned)
    assert cycle is None, "import circle: " + " -> ".join(
        f"{name} ({graph[name][nxt]}-level)" for name, nxt in zip(cycle, cycle[1:])) + f" -> {cycle[-1]}"


def test_each_allowed_edge_exists_and_runs_only_when_called() -> None:
    """The exceptions are real (a stale entry would hide a new circle) and stay inside functions."""
    graph = import_graph()
    assert {edge: graph[edge[0]].get(edge[1]) for edge in ALLOWED} == {edge: "function" for edge in ALLOWED}


def test_the_graph_sees_function_level_imports() -> None:
    graph = import_graph()
    assert graph["pi0_torch.runtime.rollout"]["pi0_torch.runtime.serving"] == "function"  # (websockets: an extra)
    assert graph["pi0_torch.runtime.policy"]["pi0_torch.runtime.policy_fast"] == "module"
    assert find_cycle({"a": {"b": "module"}, "b": {"c": "function"}, "c": {"a": "module"}}) == ["a", "b", "c", "a"]


def _layer_of(module: str) -> int | None:
    for index, prefixes in enumerate(LAYERS):
        if any(module == prefix or module.startswith(prefix + ".") for prefix in prefixes):
            return index
    return None


def _is_upward(module: str, layer: int) -> bool:
    """Whether an import of `module` from `layer` goes up: `module` lies outside that layer and the ones below it."""
    own = _layer_of(module)
    return own is None or own < layer


def test_the_engine_imports_only_downward() -> None:
    """`inference/` imports nothing of `models/` (or anything above it), `kernels/` nothing of `inference/`, `utils/`
    and `masks.py` nothing else of the package: at module level or deferred."""
    graph = import_graph()
    upward = sorted(
        f"{importer} -> {imported} ({kind}-level)"
        for importer, edges in graph.items() if (layer := _layer_of(importer)) is not None
        for imported, kind in edges.items() if imported != "pi0_torch" and _is_upward(imported, layer)
    )
    assert upward == []


def test_the_only_circle_is_the_registration_ring_inside_models() -> None:
    """Every module on a cycle of the whole graph (allowed edges included) lies in `models/`."""
    graph = import_graph()
    on_cycles = set()
    for start in graph:  # (small graph: a search from each module)
        stack, seen = [start], set()
        while stack:
            node = stack.pop()
            for nxt in graph.get(node, {}):
                if nxt == start:
                    on_cycles.add(start)
                elif nxt not in seen:
                    seen.add(nxt)
                    stack.append(nxt)
    assert on_cycles and all(name.startswith("pi0_torch.models.") for name in on_cycles), sorted(on_cycles)
