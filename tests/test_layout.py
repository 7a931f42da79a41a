"""The architecture, checked from the source: the import graph (imports inside functions included) has no cycle and
no module imports one above its layer; the product does not speak of how it was built."""
import ast
import os
import re

import pytest

HERE = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))       # the repository
PACKAGES = ("diagnosis", "experiments", "motion", "robot")

# Lowest first: a module may import modules of its own layer or below, never above.
LAYERS = [
    {"checks", "qp", "dynamics"},
    {"nn_numpy", "vi", "error_model", "detector", "ds", "cpic", "sim", "motion", "rme_settings", "rme_levels",
     "rme_stream"},   # the method, the plant
    {"nn_train", "rme"},                                             # the pipeline and the trainer
    {"diagnosis"},                                                   # the diagnosis tool
    {"experiments", "franka", "robot"},                              # demos, benchmarks, the robot bridge
]


def modules():
    """{module name: path} of the project's own modules (tests excluded)."""
    out = {f[:-3]: os.path.join(HERE, f) for f in os.listdir(HERE) if f.endswith(".py") and not f.startswith("test_")}
    for pkg in PACKAGES:
        for f in os.listdir(os.path.join(HERE, pkg)):
            if f.endswith(".py") and not f.startswith("test_"):
                out[f"{pkg}.{f[:-3]}" if f != "__init__.py" else pkg] = os.path.join(HERE, pkg, f)
    return out


def _is_main_guard(node):
    """`if __name__ == "__main__":` - the script's entry: it runs as module __main__, not as the module others import."""
    t = node.test if isinstance(node, ast.If) else None
    return (isinstance(t, ast.Compare) and isinstance(t.left, ast.Name) and t.left.id == "__name__"
            and any(isinstance(c, ast.Constant) and c.value == "__main__" for c in t.comparators))


def imports_of(path, known):
    """The project modules imported anywhere in the file (functions included), except under a __main__ guard."""
    tree, found = ast.parse(open(path).read()), set()

    def visit(node):
        if _is_main_guard(node):
            return
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        else:
            names = []
        found.update(n for n in names if n in known)
        for child in ast.iter_child_nodes(node):
            visit(child)
    visit(tree)
    return found


def layer(name):
    top = name.split(".")[0]
    return next(i for i, group in enumerate(LAYERS) if top in group or name in group)


def graph():
    mods = modules()
    return {m: imports_of(p, set(mods)) - {m} for m, p in mods.items()}


def test_every_module_has_a_layer():
    for m in modules():
        layer(m)                                        # StopIteration names a module with no layer


def test_import_graph_has_no_cycle():
    g, state = graph(), {}

    def dfs(m, path):
        state[m] = "open"
        for d in sorted(g[m]):
            if d.split(".")[0] in PACKAGES and d not in g:
                continue
            if state.get(d) == "open":
                pytest.fail(f"import cycle: {' -> '.join(path + [m, d])}")
            if d not in state:
                dfs(d, path + [m])
        state[m] = "done"
    for m in sorted(g):
        if m not in state:
            dfs(m, [])


def test_no_module_imports_one_above_its_layer():
    bad = [f"{m} (layer {layer(m)}) imports {d} (layer {layer(d)})"
           for m, deps in graph().items() for d in deps if layer(d) > layer(m)]
    assert not bad, bad


def test_the_cycle_check_can_fail():
    """The checker sees a cycle made of imports inside functions, and ignores a __main__ guard."""
    known = {"a", "b"}
    src = {"a": "def f():\n    import b\n", "b": "def g():\n    from a import f\nif __name__ == '__main__':\n    import a\n"}
    trees = {k: ast.parse(v) for k, v in src.items()}
    found = {}
    for k, t in trees.items():
        path = os.path.join(HERE, ".layout_probe.py")
        try:
            with open(path, "w") as f:
                f.write(src[k])
            found[k] = imports_of(path, known)
        finally:
            os.remove(path)
    assert found == {"a": {"b"}, "b": {"a"}}
    only_main = "if __name__ == '__main__':\n    import a\n"
    path = os.path.join(HERE, ".layout_probe.py")
    try:
        with open(path, "w") as f:
            f.write(only_main)
        assert imports_of(path, known) == set()
    finally:
        os.remove(path)


def test_no_history_or_process_words_in_the_product():
    """Code, comments and output speak of the product, not of how it was built."""
    words = re.compile(r"\b(issue \d+|issue's|item \d+|the lead\b|the old\b|previously)", re.IGNORECASE)
    files = list(modules().values()) + [os.path.join(HERE, f) for f in os.listdir(HERE) if f.startswith("test_")]
    files += [os.path.join(HERE, pkg, f) for pkg in PACKAGES for f in os.listdir(os.path.join(HERE, pkg))
              if f.startswith("test_")]
    hits = [f"{os.path.relpath(p, HERE)}:{i}: {line.strip()}" for p in files if not p.endswith("test_layout.py")
            for i, line in enumerate(open(p), 1) if words.search(line)]
    assert not hits, "\n".join(hits)
