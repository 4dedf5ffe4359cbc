"""The scripts beside the package (data/, benchmarks/, models/) import only names the package has.

They are not imported by the suite (they run for minutes), so a moved module broke them silently once
(``data/make_toy_arm_example.py`` after the layout move); this reads their imports with ``ast`` and resolves each.
"""
from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = sorted(p for folder in ("data", "benchmarks", "models") for p in (ROOT / folder).rglob("*.py"))


def _package_imports(path: Path) -> list[tuple[str, str | None]]:
    """(module, name) for every ``from pipeline... import name`` and (module, None) for ``import pipeline...``."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").split(".")[0] == "pipeline":
            found += [(node.module, alias.name) for alias in node.names]
        elif isinstance(node, ast.Import):
            found += [(alias.name, None) for alias in node.names if alias.name.split(".")[0] == "pipeline"]
    return found


def test_scripts_are_found():
    names = {p.relative_to(ROOT).as_posix() for p in SCRIPTS}
    assert {"data/make_toy_arm_example.py", "data/make_examples.py", "benchmarks/acceptance_pose.py"} <= names


@pytest.mark.parametrize("path", SCRIPTS, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_script_imports_resolve(path):
    for module_name, name in _package_imports(path):
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as error:
            pytest.fail(f"{path.relative_to(ROOT)} imports missing module {module_name}: {error}")
        if name is not None and not hasattr(module, name):
            try:  # a submodule imported by name: from pipeline.synth import pose
                importlib.import_module(f"{module_name}.{name}")
            except ModuleNotFoundError:
                pytest.fail(f"{path.relative_to(ROOT)}: {module_name} has no {name}")
