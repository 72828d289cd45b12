"""The package's import graph follows its layers (docs/architecture.md, "Layers").

Every import is read from the source with `ast`, the ones inside functions included (a
function-level import is still a dependency; it only hides a cycle from the interpreter
until the function runs). A module may import from its own layer or below, never above,
and no two modules may import each other through any chain. Private names (a leading
underscore) stay inside their module.
"""
import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "mdss_ros"

#: (layer, module name prefixes), lowest first. A module belongs to the first layer with a
#: prefix it starts with (a prefix matches the module or a package and what it holds).
LAYERS = [
    ("base", ["mdss_ros.errors", "mdss_ros.version", "mdss_ros.rotations", "mdss_ros.loads",
              "mdss_ros.linear_solver", "mdss_ros.threads", "mdss_ros.precompute", "mdss_ros.timeline",
              "mdss_ros.state_measure", "mdss_ros.step_options", "mdss_ros.model_api"]),
    ("mesh, fem, contact", ["mdss_ros.mesh", "mdss_ros.fem", "mdss_ros.contact", "mdss_ros.meshless"]),
    ("reduced", ["mdss_ros.reduced"]),
    ("model build", ["mdss_ros.body", "mdss_ros.scene", "mdss_ros.model_build"]),
    ("simulator", ["mdss_ros.simulator", "mdss_ros.guard", "mdss_ros.accuracy", "mdss_ros.budget"]),
    ("io", ["mdss_ros.ros", "mdss_ros.record"]),
    ("verify", ["mdss_ros.verify"]),
    ("programs", ["mdss_ros.node", "mdss_ros.cli", "mdss_ros.warmup", "mdss_ros.__init__"]),
]


def module_files():
    """{module name: path} of every module of the package ("mdss_ros.__init__" for the
    package's own file, which is the public facade and sits at the top)."""
    out = {}
    for p in sorted(PACKAGE.rglob("*.py")):
        parts = p.relative_to(PACKAGE.parent).with_suffix("").parts
        name = ".".join(parts)
        if parts[-1] == "__init__" and len(parts) > 2:
            name = ".".join(parts[:-1])
        out[name] = p
    return out


def layer_of(module):
    for i, (_, prefixes) in enumerate(LAYERS):
        if any(module == p or module.startswith(p + ".") for p in prefixes):
            return i
    raise AssertionError(f"{module} is in no layer: add it to test_layers.LAYERS and docs/architecture.md")


def imports(modules):
    """[(importer, imported module, line, names)] of every import of a package module."""
    out = []
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
        if name == "mdss_ros.__init__":
            package = "mdss_ros"
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                targets = [(a.name, []) for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = package.split(".")[:len(package.split(".")) - (node.level - 1)] if node.level else []
                target = ".".join(base + ([node.module] if node.module else []))
                targets = []
                for a in node.names:
                    full = f"{target}.{a.name}"
                    targets.append((full, []) if full in modules else (target, [a.name]))
            else:
                continue
            for target, names in targets:
                if target == "mdss_ros":
                    target = "mdss_ros.__init__"
                if target.startswith("mdss_ros") and target != name:
                    out.append((name, target, node.lineno, names))
    return out


def test_every_module_has_a_layer():
    for name in module_files():
        layer_of(name)


def test_no_module_imports_from_a_layer_above_it():
    modules = module_files()
    upward = [f"{src}:{line} imports {dst} ({LAYERS[layer_of(dst)][0]} is above {LAYERS[layer_of(src)][0]})"
              for src, dst, line, _ in imports(modules) if layer_of(dst) > layer_of(src)]
    assert not upward, "\n".join(upward)


def test_the_import_graph_has_no_cycle():
    modules = module_files()
    graph = {m: set() for m in modules}
    for src, dst, _, _ in imports(modules):
        if dst in graph:
            graph[src].add(dst)
    state, path = {}, []

    def visit(m):
        state[m] = "open"
        path.append(m)
        for n in sorted(graph[m]):
            if state.get(n) == "open":
                raise AssertionError("import cycle: " + " -> ".join(path[path.index(n):] + [n]))
            if n not in state:
                visit(n)
        path.pop()
        state[m] = "done"

    for m in sorted(graph):
        if m not in state:
            visit(m)


def test_no_private_name_crosses_a_module():
    crossing = [f"{src}:{line} imports {dst}.{n}" for src, dst, line, names in imports(module_files())
                for n in names if n.startswith("_") and not n.startswith("__")]
    assert not crossing, "\n".join(crossing)


@pytest.mark.parametrize("bad", ["mdss_ros.simulator", "mdss_ros.verify.tradeoff"])
def test_the_check_catches_an_upward_import(bad, tmp_path):
    """The rule is not vacuous: a fem module importing the simulator or a report is flagged."""
    modules = module_files()
    src = "mdss_ros.fem.elements"
    assert layer_of(bad) > layer_of(src)
    fake = tmp_path / "elements.py"
    fake.write_text(modules[src].read_text() + f"\n\ndef _late():\n    import {bad}\n")
    found = [(s, d) for s, d, _, _ in imports(dict(modules, **{src: fake})) if s == src and d == bad]
    assert found
