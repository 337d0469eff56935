"""Code structure rules from STYLE.md, checked on the source with ``ast``.

* Imports point one way: estimation → mapping → sensors.
* Heavy dependencies stay at named edges: gtsam only in estimation; pyserial only in the LMS 200
  driver; open3d and matplotlib only inside functions, so ``coopmap --help`` stays fast.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("estimation", "sensors", "mapping")
#: What each package may import of the others.
ALLOWED = {"estimation": {"mapping", "sensors"}, "mapping": {"sensors"}, "sensors": set()}
#: The modules allowed to import pyserial (the driver owns the serial port).
SERIAL_MODULES = {"sensors/lms200/driver.py"}


def sources() -> list[Path]:
    files = [p for pkg in PACKAGES for p in (REPO / pkg).rglob("*.py")]
    assert len(files) >= 10, "the packages were not found"
    return sorted(files)


def imports(path: Path) -> list[tuple[str, bool]]:
    """(top-level module name, imported at module level?) for every import in the file."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    found: list[tuple[str, bool]] = []
    module_level: set[int] = set()
    for node in tree.body:
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            continue  # seen by type checkers only, never imported at run time
        if isinstance(node, ast.If | ast.Try):
            module_level |= {id(child) for child in ast.walk(node)}
        else:
            module_level.add(id(node))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module]
        else:
            continue
        found += [(name.split(".")[0], id(node) in module_level) for name in names]
    return found


def relative(path: Path) -> str:
    return path.relative_to(REPO).as_posix()


def test_imports_point_from_estimation_to_mapping_to_sensors() -> None:
    violations = []
    for path in sources():
        package = relative(path).split("/")[0]
        for name, _ in imports(path):
            if name in PACKAGES and name != package and name not in ALLOWED[package]:
                violations.append(f"{relative(path)} imports {name}")
    assert violations == []


def test_gtsam_only_in_estimation() -> None:
    bad = [relative(p) for p in sources() if any(n == "gtsam" for n, _ in imports(p))]
    assert [p for p in bad if not p.startswith("estimation/")] == []


def test_pyserial_only_in_the_driver() -> None:
    bad = [relative(p) for p in sources() if any(n == "serial" for n, _ in imports(p))]
    assert [p for p in bad if p not in SERIAL_MODULES] == []


@pytest.mark.parametrize("heavy", ["open3d", "matplotlib"])
def test_heavy_modules_are_imported_inside_functions(heavy: str) -> None:
    bad = [relative(p) for p in sources() if any(n == heavy and top for n, top in imports(p))]
    assert bad == []


def test_the_checker_sees_module_level_imports(tmp_path: Path) -> None:
    sample = tmp_path / "sample.py"
    sample.write_text(
        "import open3d\nfrom typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import gtsam\n"
        "def f():\n    import matplotlib\n",
        encoding="utf-8",
    )
    found = dict(imports(sample))
    assert found["open3d"] is True
    assert found["gtsam"] is False
    assert found["matplotlib"] is False


def test_help_does_not_load_heavy_modules() -> None:
    code = (
        "import sys\n"
        "from typer.testing import CliRunner\n"
        "from estimation.cli import app\n"
        "result = CliRunner().invoke(app, ['--help'])\n"
        "assert result.exit_code == 0, result.output\n"
        "print(sorted(m for m in ('open3d', 'gtsam', 'matplotlib', 'numba', 'serial') "
        "if m in sys.modules))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, check=True
    )
    assert out.stdout.strip() == "[]"
