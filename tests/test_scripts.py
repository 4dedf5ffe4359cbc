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


def test_replay_choice_keeps_the_lower_loss_or_score_per_arm(tmp_path):
    """``benchmarks/replay_choice.py`` (the per-arm model choice of docs/soft-arms.md): B replaces A on an arm only
    where it ends lower, by loss or by the order penalty's score, and only above a gate; the means are checked
    against sums worked out by hand."""
    import json
    import subprocess
    import sys

    def write(name, rows):
        path = tmp_path / name
        path.write_text(json.dumps({"cases": [dict(zip(("seed", "loss", "order", "mean_2d_px", "mean_3d_mm"), r))
                                              for r in rows]}))
        return str(path)

    a = write("a.json", [(1, 0.030, 2, 1.0, 2.0), (2, 0.050, 2, 9.0, 30.0), (3, 0.040, 2, 3.0, 6.0)])
    b = write("b.json", [(1, 0.031, 2, 5.0, 5.0), (2, 0.045, 5, 1.0, 2.0), (3, 0.039, 2, 1.0, 2.0)])

    def run(*extra):
        out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "replay_choice.py"), a, b, *extra],
                             capture_output=True, text=True, check=True).stdout
        return [line for line in out.splitlines() if line.startswith(("the lower", "B tried"))]

    by_loss = run("--gates", "0.045")
    assert by_loss[0] == "the lower of A and B: 1.00 / 2.00 (1.00 / 2.00); B kept on 2"  # arms 2 and 3 from B
    assert by_loss[1] == "B tried where A's loss > 0.045 (1 arms): 1.67 / 3.33 (1.00 / 2.00)"  # arm 2 only
    # by score arm 2's B costs 0.045 + 3 * 0.002 = 0.051 > 0.050: A kept there
    assert run("--score")[0] == "the lower of A and B: 3.67 / 11.33 (1.00 / 2.00); B kept on 1"
