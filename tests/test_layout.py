"""The architecture, checked from the source: the import graph (imports inside functions included) has no cycle and
no module imports one above its layer; tests live in tests/ and only tests import them (a test imports no other test
file, only tests/helpers.py); the product does not speak of how it was built."""
import ast
import os
import re

import pytest

from tests.helpers import ROOT

PACKAGES = ("diagnosis", "experiments", "motion", "robot")
TESTS = "tests"                        # the tests and their helpers; the design card's test_rme.py stays at the root

# Lowest first: a module may import modules of its own layer or below, never above.
LAYERS = [
    {"checks", "qp", "dynamics"},
    {"nn_numpy", "vi", "error_model", "detector", "changes", "ds", "cpic", "sim", "motion", "rme_settings"},
    # the method, the plant
    {"nn_train", "window", "rme"},                                   # the pipeline and the trainer
    {"diagnosis"},                                                   # the diagnosis tool
    {"experiments", "franka", "robot"},                              # demos, benchmarks, the robot bridge
]


def modules():
    """{module name: path} of the project's own modules (tests excluded)."""
    out = {f[:-3]: os.path.join(ROOT, f) for f in os.listdir(ROOT) if f.endswith(".py") and not f.startswith("test_")}
    for pkg in PACKAGES:
        for f in os.listdir(os.path.join(ROOT, pkg)):
            if f.endswith(".py") and not f.startswith("test_"):
                out[f"{pkg}.{f[:-3]}" if f != "__init__.py" else pkg] = os.path.join(ROOT, pkg, f)
    return out


def suite_files():
    """Paths of the test files and their helpers: tests/*.py and the root's test_rme.py."""
    folder = os.path.join(ROOT, TESTS)
    return [os.path.join(folder, f) for f in sorted(os.listdir(folder)) if f.endswith(".py")] + [
        os.path.join(ROOT, "test_rme.py")]


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


def test_the_robot_package_never_imports_the_franka_script():
    """franka.py is the bridge's command line on top of robot/ (its loop, backends, workers), never below it."""
    bad = [m for m, deps in graph().items() if m.split(".")[0] == "robot" and "franka" in deps]
    assert not bad, bad


def test_the_cycle_check_can_fail(tmp_path):
    """The checker sees a cycle made of imports inside functions, and ignores a __main__ guard."""
    known = {"a", "b"}
    src = {"a": "def f():\n    import b\n", "b": "def g():\n    from a import f\nif __name__ == '__main__':\n    import a\n"}
    found = {}
    for k, code in src.items():
        path = tmp_path / f"{k}.py"
        path.write_text(code)
        found[k] = imports_of(path, known)
    assert found == {"a": {"b"}, "b": {"a"}}
    only_main = tmp_path / "only_main.py"
    only_main.write_text("if __name__ == '__main__':\n    import a\n")
    assert imports_of(only_main, known) == set()


def imported_names(path):
    """Every name the file imports (inside functions and a __main__ guard too), dotted: `from a import b` gives a and
    a.b; a relative import is named without its dots."""
    names = set()
    for node in ast.walk(ast.parse(open(path).read())):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            names.update([base] * bool(base) + [f"{base}.{a.name}".lstrip(".") for a in node.names])
    return names


def names_a_test(name):
    """The name of tests/ or anything in it, of a test module (test_*, in any package) or of a conftest."""
    parts = name.split(".")
    return parts[0] == TESTS or any(p.startswith("test_") or p == "conftest" for p in parts)


def outside_files():
    """The .py files outside tests/ but the root's test_rme.py (hidden folders, caches, data/ and virtual
    environments left out)."""
    out = []
    for folder, dirs, files in os.walk(ROOT):
        dirs[:] = [d for d in dirs if not d.startswith((".", "__")) and d not in (TESTS, "data")
                   and not os.path.exists(os.path.join(folder, d, "pyvenv.cfg"))]
        out += [os.path.join(folder, f) for f in files if f.endswith(".py")]
    return [p for p in out if p != os.path.join(ROOT, "test_rme.py")]


def test_every_package_is_scanned():
    """Each folder with an __init__.py is a product package (PACKAGES: layered, scanned) or tests/."""
    found = {d for d in os.listdir(ROOT) if os.path.isfile(os.path.join(ROOT, d, "__init__.py"))}
    assert found == set(PACKAGES) | {TESTS}, found


def test_tests_live_in_tests():
    """No test file or conftest outside tests/ but the design card's test_rme.py at the root (pytest.ini collects
    tests/ and test_rme.py only)."""
    stray = [os.path.relpath(p, ROOT) for p in outside_files()
             if os.path.basename(p).startswith("test_") or os.path.basename(p) == "conftest.py"]
    assert not stray, stray


def test_only_tests_import_tests_and_a_test_imports_no_other_test_file():
    """No file outside tests/ (test_rme.py aside) imports a test module, tests/helpers.py or a conftest; a test file
    imports no other test file (what several share is in tests/helpers.py)."""
    bad = [f"{os.path.relpath(p, ROOT)} imports {n}" for p in outside_files() for n in imported_names(p)
           if names_a_test(n)]
    bad += [f"{os.path.relpath(p, ROOT)} imports {n}" for p in suite_files() for n in imported_names(p)
            if names_a_test(n.removeprefix(TESTS + ".")) and n not in (TESTS, TESTS + ".helpers")
            and not n.startswith(TESTS + ".helpers.")]
    assert not bad, "\n".join(bad)


def test_the_test_import_check_can_fail(tmp_path):
    """The check sees a test module, tests/helpers.py and a conftest imported inside a function or relatively."""
    probe = tmp_path / "probe.py"
    probe.write_text("def f():\n    from test_streaming import SYNC\nimport tests.helpers\nfrom tests import conftest\n"
                     "from . import test_x\nfrom diagnosis import logs\nimport pytest\n")
    names = imported_names(probe)
    assert {n for n in names if names_a_test(n)} == {"test_streaming", "test_streaming.SYNC", "tests.helpers",
                                                     "tests", "tests.conftest", "test_x"}, names


def test_no_history_or_process_words_in_the_product():
    """Code, comments and output speak of the product, not of how it was built."""
    words = re.compile(r"\b(issue \d+|issue's|item \d+|the lead\b|the old\b|previously)", re.IGNORECASE)
    files = list(modules().values()) + suite_files()
    hits = [f"{os.path.relpath(p, ROOT)}:{i}: {line.strip()}" for p in files if not p.endswith("test_layout.py")
            for i, line in enumerate(open(p), 1) if words.search(line)]
    assert not hits, "\n".join(hits)
