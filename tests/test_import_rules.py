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
