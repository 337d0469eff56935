"""Code structure rules from STYLE.md, checked on the source with ``ast``.

* Imports point one way: estimation → mapping → sensors.
* Heavy dependencies stay at named edges: gtsam only in estimation; pyserial only in the LMS 200
  driver; open3d and matplotlib only inside functions, so ``coopmap --help`` stays fast.
* No import cycle between modules (every import counts: module level, inside functions, under
  ``TYPE_CHECKING``); the core of ``estimation`` never imports its application layer.
* No module over ``MAX_LINES`` lines; ``tests/`` mirrors the packages.
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
#: A module longer than this is split by concern.
MAX_LINES = 600


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


#: Where ROS interchange libraries may be imported at module level (the application's edge).
ROS_FOLDER = "estimation/app/ros/"


@pytest.mark.parametrize("heavy", ["rosbags", "mcap", "mcap_ros2", "foxglove"])
def test_ros_libraries_stay_in_the_ros_interchange(heavy: str) -> None:
    bad = [
        relative(p)
        for p in sources()
        if any(n == heavy and top for n, top in imports(p))
        and not relative(p).startswith(ROS_FOLDER)
    ]
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
        "from estimation.app.cli.main import app\n"
        "result = CliRunner().invoke(app, ['--help'])\n"
        "assert result.exit_code == 0, result.output\n"
        "print(sorted(m for m in ('open3d', 'gtsam', 'matplotlib', 'numba', 'serial', 'rosbags', "
        "'mcap', 'foxglove') if m in sys.modules))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, check=True
    )
    assert out.stdout.strip() == "[]"


def module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_graph(paths: list[Path]) -> dict[str, set[str]]:
    """Module → the project modules it imports (any import, anywhere in the file)."""
    modules = {module_name(p): p for p in paths}

    def resolve(name: str) -> str | None:
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, set[str]] = {m: set() for m in modules}
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join(up + ([base] if base else []))
                targets = [base] + [f"{base}.{alias.name}" for alias in node.names]
            else:
                continue
            for target in targets:
                found = resolve(target)
                # A package's __init__ is imported by its own modules' imports; not an edge back.
                if found and found != name and not name.startswith(found + "."):
                    graph[name].add(found)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def test_no_import_cycles() -> None:
    assert cycles(import_graph(sources())) == []


def test_the_cycle_checker_finds_cycles(tmp_path: Path) -> None:
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_the_import_graph_sees_imports_inside_functions_and_type_checking() -> None:
    graph = import_graph(sources())
    # results.py names the dataset's Sweep under TYPE_CHECKING only; the graph still sees it.
    assert "estimation.app.dataset" in graph["estimation.app.results"]
    assert "estimation.app.pipeline" in graph["estimation.app.cli.mission"]  # inside a command


def test_the_core_does_not_import_the_application() -> None:
    graph = import_graph(sources())
    core = [m for m in graph if m.startswith("estimation.") and not m.startswith("estimation.app")]
    assert [(m, d) for m in core for d in graph[m] if d.startswith("estimation.app")] == []


def test_no_module_is_too_long() -> None:
    long = {relative(p): n for p in sources() if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert long == {}


def test_tests_mirror_the_packages() -> None:
    """Every test module sits in the folder of the package it tests (tests/<package path>/)."""
    folders = {p.parent.relative_to(REPO).as_posix() for p in sources()}
    tests = [p for p in (REPO / "tests").rglob("test_*.py") if p.parent != REPO / "tests"]
    misplaced = [
        p.relative_to(REPO).as_posix()
        for p in tests
        if p.parent.relative_to(REPO / "tests").as_posix() not in folders
    ]
    assert misplaced == []


def test_no_module_imports_another_modules_private_names() -> None:
    """Helpers shared between modules are public; an underscore name stays in its module."""
    violations = []
    for path in sources():
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] in PACKAGES:
                private = [a.name for a in node.names if a.name.startswith("_")]
                private = [n for n in private if not n.startswith("__")]
                violations += [f"{relative(path)}: {node.module}.{n}" for n in private]
    assert violations == []
