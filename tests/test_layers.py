"""The import layers of the packages, checked on every import statement (lazy ones too).

Rules (stated in the package docstrings): inside ``design`` a module imports only from
its own layer or lower (``design.LAYERS``); ``design`` and ``broker_free_net`` never import
each other nor ``agent``; inside ``agent`` only the command line (``agent.cli.main``,
``agent.cli``) imports the command line.
"""

import ast
from pathlib import Path

import pytest

import agent
import design

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("design", "agent", "broker_free_net")


def modules():
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            yield ".".join(parts), path


def imported(module: str, path: Path) -> list:
    """Absolute names of every module ``module`` imports (``from x import y`` gives x.y too)."""
    is_pkg = path.name == "__init__.py"
    package = module if is_pkg else module.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module
            out.append((name, node.lineno))
            out += [(f"{name}.{a.name}", node.lineno) for a in node.names]
    return out


def violations(module: str, target: str):
    top = module.split(".")[0]
    dest = target.split(".")[0]
    if dest not in PACKAGES:
        return None
    if top in ("design", "broker_free_net") and dest != top:
        return f"{top} must not import {dest}"
    if top == "design":
        src_layer = design.LAYERS.get(module.split(".")[1]) if "." in module else 5
        parts = target.split(".")
        if len(parts) > 1 and parts[1] in design.LAYERS:
            if design.LAYERS[parts[1]] > src_layer:
                return (f"layer {src_layer} module imports {parts[1]} of layer "
                        f"{design.LAYERS[parts[1]]}")
    if top == "agent":
        src, parts = module.split("."), target.split(".")
        if len(src) > 1 and len(parts) > 1 and parts[1] in agent.LAYERS:
            src_layer, dest_layer = agent.LAYERS[src[1]], agent.LAYERS[parts[1]]
            if dest_layer > src_layer:
                return (f"agent.{src[1]} (layer {src_layer}) imports agent.{parts[1]} "
                        f"(layer {dest_layer})")
    return None


ALL = list(modules())


def test_every_design_module_has_a_layer():
    names = {m.split(".")[1] for m, _ in ALL if m.startswith("design.")}
    assert names == set(design.LAYERS), names ^ set(design.LAYERS)


def test_every_agent_module_is_in_a_sub_package_with_a_layer():
    loose = [m for m, p in ALL if m.startswith("agent.") and p.parent == ROOT / "agent"]
    assert not loose, f"modules outside agent's sub-packages: {loose}"
    subs = {p.name for p in (ROOT / "agent").iterdir() if (p / "__init__.py").exists()}
    assert subs == set(agent.LAYERS), subs ^ set(agent.LAYERS)


@pytest.mark.parametrize("module, path", ALL, ids=[m for m, _ in ALL])
def test_no_upward_import(module, path):
    bad = [f"line {line}: {target}: {why}" for target, line in imported(module, path)
           if (why := violations(module, target))]
    assert not bad, "\n".join(bad)


def test_the_checker_sees_upward_imports():
    assert violations("design.graph", "design.analysis.analyze")
    assert violations("design.scenario", "design.observability")
    assert violations("design.simulate", "agent.node.core")
    assert violations("broker_free_net.peer", "design.scenario")
    assert violations("agent.node.core", "agent.cli._common")
    assert violations("agent.monitor.core", "agent.run.summary")
    assert violations("agent.protocol.wire", "agent.node.core")
    assert violations("agent.run.local", "agent.cli.up")
    assert not violations("agent.run.simulated", "agent.monitor.core")
    assert not violations("agent.cli.up", "agent.run.local")
    assert not violations("design.analysis", "design.graph")
    assert not violations("agent.cli.plan", "design.recovery")
    assert not violations("agent.node.core", "broker_free_net.impair")


def test_no_import_cycle_between_project_modules():
    names = {m for m, _ in ALL}
    graph = {m: sorted({t for t, _ in imported(m, p) if t in names and t != m}) for m, p in ALL}
    # a package's __init__ importing its own submodules is not a cycle of interest
    graph = {m: [t for t in ts if not m.startswith(t + ".") and not t.startswith(m + ".")]
             for m, ts in graph.items()}
    state = {}

    def visit(m, stack):
        state[m] = "open"
        for t in graph[m]:
            if state.get(t) == "open":
                raise AssertionError("import cycle: " + " -> ".join(stack + [m, t]))
            if t not in state:
                visit(t, stack + [m])
        state[m] = "done"

    for m in graph:
        if m not in state:
            visit(m, [])


@pytest.mark.parametrize("module", ["agent.node.core", "agent.monitor.core", "agent.protocol.timing",
                                    "agent.run.simulated",
                                    "broker_free_net.codec", "broker_free_net.impair"])
def test_the_pure_side_does_not_load_the_native_transport(module):
    """The state machines and the codec run without zenoh: only a session loads it."""
    import subprocess
    import sys

    code = f"import sys, {module}; print('zenoh' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, cwd=Path(__file__).resolve().parents[1])
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"
