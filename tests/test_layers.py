"""The package's layers: imports point downward only, there is no import cycle,
and the command line lists the book without loading JAX."""

import ast
import subprocess
import sys

from qdnb.book import registry
from qdnb.core import paths

# core -> envs, nets -> rl -> qd -> models -> chapters -> plotting -> book (a module may import
# its own layer and those below it, never one above)
LAYERS = {
    "core": 0,
    "envs": 1,
    "nets": 1,
    "rl": 2,
    "qd": 3,
    "models": 4,
    "chapters": 5,
    "plotting": 6,
    "book": 7,
    "__main__": 7,
}
PACKAGE = paths.ROOT / "qdnb"


def module_name(path) -> str:
    parts = path.relative_to(paths.ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def layer(module: str) -> int:
    parts = module.split(".")
    return LAYERS[parts[1]] if len(parts) > 1 else 0


def imports(path, runtime: bool = False) -> set[str]:
    """Every ``qdnb`` module ``path`` imports, at module level or inside a function; with
    ``runtime``, but those under ``if TYPE_CHECKING:`` (read by type checkers, never run)."""
    found = set()
    tree = ast.parse(path.read_text())
    typing_only = {
        id(n)
        for block in ast.walk(tree)
        if isinstance(block, ast.If) and ast.unparse(block.test) == "TYPE_CHECKING"
        for n in ast.walk(block)
    }
    for node in ast.walk(tree):
        if runtime and id(node) in typing_only:
            continue
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name.split(".")[0] == "qdnb"}
        elif (
            isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "qdnb"
        ):
            for a in node.names:  # `from qdnb.core import paths` imports the module qdnb.core.paths
                sub = f"{node.module}.{a.name}"
                is_module = (PACKAGE.parent / (sub.replace(".", "/") + ".py")).exists() or (
                    PACKAGE.parent / sub.replace(".", "/")
                ).is_dir()
                found.add(sub if is_module else node.module)
    return found


def graph(runtime: bool = False) -> dict[str, set[str]]:
    return {module_name(p): imports(p, runtime) for p in PACKAGE.rglob("*.py")}


def test_every_module_belongs_to_a_layer():
    for module in graph():
        parts = module.split(".")
        assert len(parts) == 1 or parts[1] in LAYERS, f"{module} is in no layer of {sorted(LAYERS)}"


def test_imports_point_down_the_layers():
    upward = [
        f"{m} (layer {layer(m)}) imports {t} (layer {layer(t)})"
        for m, targets in graph().items()
        for t in targets
        if layer(t) > layer(m)
    ]
    assert not upward, "\n".join(upward)


def find_cycle(edges: dict[str, set[str]]) -> list[str] | None:
    state, stack = {}, []

    def visit(node):
        state[node] = "open"
        stack.append(node)
        for nxt in sorted(edges.get(node, ())):
            if state.get(nxt) == "open":
                return stack[stack.index(nxt) :] + [nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        stack.pop()
        state[node] = "done"
        return None

    for node in sorted(edges):
        if node not in state and (cycle := visit(node)):
            return cycle
    return None


def test_there_is_no_import_cycle():
    edges = graph(runtime=True)  # a type checker's imports run nothing: no cycle there
    # a module's import of its own package (``qdnb.qd`` from ``qdnb.qd.x``) runs the package's
    # __init__, which imports nothing here, or, for a chapter's package, its files (which
    # never import the package itself): only module-to-module edges count
    cycle = find_cycle({m: {t for t in ts if t in edges and t != m} for m, ts in edges.items()})
    assert cycle is None, " -> ".join(cycle)


def test_cycle_finder_finds_a_hand_made_cycle():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set(), "c": {"b"}}) is None


def test_listing_the_book_loads_no_jax():
    code = (
        "import sys; from qdnb.__main__ import main; main(['list']); "
        "heavy = sorted(m for m in ('jax', 'flax', 'optax', 'brax', 'matplotlib') if m in "
        "sys.modules); "
        "print('HEAVY', heavy)"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=paths.ROOT, capture_output=True, text=True, check=True
    )
    assert "HEAVY []" in out.stdout, out.stdout
    assert all(name in out.stdout for name in registry.names())


def test_the_registry_is_the_table_of_contents_and_every_chapter_has_its_parts():
    assert (paths.BOOK / "_toc.yml").read_text() == registry.toc()
    for chapter in registry.CHAPTERS:
        assert chapter.notebook.exists()
        module = chapter.module
        assert set(module.SCALES) == {"tiny", "small", "paper"}
        assert all(isinstance(cfg, chapter.config_class) for cfg in module.SCALES.values())
        assert len(module.METHODS) > 0
