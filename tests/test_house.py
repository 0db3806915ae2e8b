"""The project speaks of itself alone: no development-process words in the tracked files' contents or names.

What is looked for: numbered work steps (the word for such a step followed by its number, in prose or in a file
name), issue numbers in prose, and remarks on which machines were lent for the work.  History lives in git; the
tree says what was measured, on what machine, with which command.
"""

import ast
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
# written in pieces, so that this file does not hold the phrases it looks for
PROCESS_WORDS = re.compile(
    "|".join(
        (
            r"\b" + "stop" + r"s? [0-9]+(-[0-9]+)?\b",
            "_" + "stop" + r"[0-9]+",
            r"\b" + "issue" + r"s? [0-9]+\b",
            r"\b" + "was" + r" lent\b",
            r"\b" + "same" + r" session\b",
        )
    ),
    re.IGNORECASE,
)


def _tracked() -> list[str]:
    try:
        out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True, timeout=60).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout: no list of tracked files")
    return [name for name in out.decode().split("\0") if name]


def test_no_tracked_file_speaks_of_the_development_process():
    found = []
    for name in _tracked():
        if PROCESS_WORDS.search(name):
            found.append(f"{name}: its name")
        path = ROOT / name
        if not path.is_file():
            continue
        data = path.read_bytes()
        if b"\0" in data[:8192]:  # binary (figures)
            continue
        for k, line in enumerate(data.decode("utf-8", errors="replace").splitlines(), 1):
            if PROCESS_WORDS.search(line):
                found.append(f"{name}:{k}: {line.strip()[:120]}")
    assert not found, "\n".join(found[:20])


# the layers, lowest first, by folder: each may import those below it, none above it
LAYERS = (("pusupu_jax",), ("tune", "experiments", "hw_bridge", "sim_robot"), ("pusupu_cli",), ("benchmarks",))
# the name each folder is installed under (pyproject.toml): one namespace, no generic top-level names
INSTALLED = {
    "tune": "pusupu_jax.tune",
    "experiments": "pusupu_jax.experiments",
    "hw_bridge": "pusupu_jax.hw_bridge",
    "sim_robot": "pusupu_jax.sim_robot",
    "pusupu_cli": "pusupu_jax.cli",
}


def _import_graph() -> dict:
    """``({module: modules of the project it imports}, {module: its folder})``, from every import statement in its
    source (those inside functions too), each named down to the project module it reaches."""
    modules, folder_of = {}, {}
    for layer in LAYERS:
        for folder in layer:
            for path in (ROOT / folder).rglob("*.py"):
                parts = list(path.relative_to(ROOT).with_suffix("").parts)
                parts[0] = INSTALLED.get(folder, folder)
                is_package = parts[-1] == "__init__"
                name = ".".join(parts[:-1] if is_package else parts)
                modules[name], folder_of[name] = (path, is_package), folder

    def project_module(name: str) -> str | None:
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name or None

    graph = {}
    for module, (path, is_package) in modules.items():
        here = module if is_package else module.rpartition(".")[0]
        found = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                found |= {project_module(a.name) for a in node.names}
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    package = here
                    for _ in range(node.level - 1):
                        package = package.rpartition(".")[0]
                    base = package + ("." + base if base else "")
                found |= {project_module(f"{base}.{a.name}") for a in node.names}
        graph[module] = found - {None, module}
    return graph, folder_of


def test_no_import_circle_and_no_layer_imports_one_above_it():
    """Core (``pusupu_jax``) -> applications (``tune``, ``experiments``, ``hw_bridge``) -> the CLI -> benchmarks: no
    module imports a higher layer's, and no modules import each other in a circle (imports inside functions count:
    a circle there is one module's concept split across two)."""
    graph, folder_of = _import_graph()
    layer = {m: k for m in graph for k, names in enumerate(LAYERS) if folder_of[m] in names}
    upward = [f"{m} imports {d}" for m, deps in graph.items() for d in deps if layer[d] > layer[m]]
    assert not upward, upward
    # Tarjan's strongly connected components: a component of more than one module is a circle
    index, low, stack, on_stack, circles = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while not component or component[-1] != v:
                component.append(stack.pop())
                on_stack.discard(component[-1])
            if len(component) > 1:
                circles.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    assert not circles, circles


def test_the_install_puts_no_generic_top_level_name(tmp_path):
    """Outside the checkout (a fresh interpreter in another folder, no PYTHONPATH), the applications import under
    ``pusupu_jax`` only: ``import tune`` finds nothing (a user's own ``tune`` stays theirs)."""
    names = [*INSTALLED, *INSTALLED.values()]
    code = (
        "import importlib.util, json; "
        f"print(json.dumps({{n: importlib.util.find_spec(n) is not None for n in {names!r}}}))"
    )
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120, check=True
    )
    found = json.loads(out.stdout)
    assert found == {n: n.startswith("pusupu_jax.") for n in names}, found
