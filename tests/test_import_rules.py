"""The one rule between the packages (DESIGN.md): reglib never imports testbed, studies,
pybullet, pyrender or matplotlib; testbed uses nothing of reglib but reglib.geometry.

Checked two ways: statically on every import statement, and dynamically by importing all of
reglib in a fresh interpreter and looking at ``sys.modules``.
"""

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FORBIDDEN_IN_REGLIB = {"testbed", "studies", "pybullet", "pyrender", "matplotlib"}


def _imports(path: Path):
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield node.lineno, a.name
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            yield node.lineno, node.module
            for a in node.names:
                yield node.lineno, f"{node.module}.{a.name}"


def test_reglib_imports_no_simulator_and_no_plotting():
    bad = []
    for f in sorted((ROOT / "reglib").rglob("*.py")):
        for line, name in _imports(f):
            if name.split(".")[0] in FORBIDDEN_IN_REGLIB:
                bad.append(f"{f.relative_to(ROOT)}:{line} imports {name}")
    assert not bad, "\n".join(bad)


def test_testbed_uses_only_reglib_geometry():
    bad = []
    for f in sorted((ROOT / "testbed").rglob("*.py")):
        for line, name in _imports(f):
            parts = name.split(".")
            if parts[0] != "reglib":
                continue
            if name == "reglib" or parts[1] == "geometry":
                continue
            bad.append(f"{f.relative_to(ROOT)}:{line} imports {name}")
    assert not bad, "\n".join(bad)


def test_importing_reglib_loads_no_forbidden_module():
    mods = sorted(p.stem for p in (ROOT / "reglib").glob("*.py") if p.stem != "__init__")
    code = (
        "import sys\n"
        + "".join(f"import reglib.{m}\n" for m in mods)
        + f"bad = sorted(m for m in sys.modules if m.split('.')[0] in {FORBIDDEN_IN_REGLIB!r})\n"
        + "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=ROOT, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "", f"importing reglib loaded: {out.stdout.strip()}"


def _project_modules() -> dict[str, Path]:
    mods = {}
    for pkg in ("reglib", "testbed", "studies"):
        for f in (ROOT / pkg).rglob("*.py"):
            name = ".".join(f.relative_to(ROOT).with_suffix("").parts)
            mods[name.removesuffix(".__init__")] = f
    return mods


def test_testbed_never_imports_studies():
    """The world never reaches up into the judge (any import, also inside functions)."""
    bad = []
    for f in sorted((ROOT / "testbed").rglob("*.py")):
        for line, name in _imports(f):
            if name.split(".")[0] == "studies":
                bad.append(f"{f.relative_to(ROOT)}:{line} imports {name}")
    assert not bad, "\n".join(bad)


def _import_graph() -> dict[str, set[str]]:
    """Module -> project modules it imports (any import statement, also inside functions;
    a package's imports of its own submodules left out)."""
    mods = _project_modules()
    graph = {m: set() for m in mods}
    for m, f in mods.items():
        for _, name in _imports(f):
            while name and name not in mods:
                name = name.rpartition(".")[0]
            if name and name != m and not name.startswith(m + "."):
                graph[m].add(name)
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index, low, on, stack, out, counter = {}, {}, set(), [], [], [0]
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter[0]
        counter[0] += 1
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            for w in it:
                if w not in index:
                    index[w] = low[w] = counter[0]
                    counter[0] += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                    break
                if w in on:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
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
    return out


def test_cycle_finder_finds_a_planted_cycle():
    g = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert _cycles(g) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycles_between_project_modules():
    cycles = _cycles(_import_graph())
    assert not cycles, "import cycles: " + "; ".join(" <-> ".join(c) for c in cycles)


def test_importing_testbed_loads_only_reglib_geometry():
    code = ("import sys, testbed.simulate, testbed.scene, testbed.dataset\n"
            "print(','.join(sorted(m for m in sys.modules if m.startswith('reglib'))))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=ROOT, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().split(",") == ["reglib", "reglib.geometry"]
