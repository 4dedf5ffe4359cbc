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


def test_same_hour_runs_both_trees_in_turn_and_removes_its_worktree():
    """``benchmarks/same_hour.py``: the command runs in this checkout and in a worktree of the earlier commit, in turn
    (each from its own tree: the script prints its working directory), the figure's medians and ratio are printed,
    and no worktree is left behind; a commit git does not know is one line, not a traceback."""
    import subprocess
    import sys

    script = str(ROOT / "benchmarks" / "same_hour.py")
    command = ["-c", "import os, sys; print('cwd', os.getcwd()); print('figure', 2.0 if 'against' in os.getcwd() "
               "else 1.0)"]
    out = subprocess.run([sys.executable, script, "--against", "HEAD", "--figure", r"figure ([0-9.]+)", "--show",
                          "cwd|figure", "--", *command], capture_output=True, text=True, check=True, cwd=ROOT).stdout
    lines = out.splitlines()
    assert [line.split(": ")[0].strip() for line in lines if "cwd" in line] == [
        "this checkout (round 1)", "HEAD (round 1)", "this checkout (round 2)", "HEAD (round 2)"]
    assert lines[-1] == "median figure: this checkout 1, HEAD 2; ratio HEAD / this checkout 2.00"
    listed = subprocess.run(["git", "-C", str(ROOT), "worktree", "list"], capture_output=True, text=True).stdout
    assert "against" not in listed
    bad = subprocess.run([sys.executable, script, "--against", "no-such-commit", "--figure", "x ([0-9]+)", "--",
                          "-c", "pass"], capture_output=True, text=True, cwd=ROOT)
    assert bad.returncode == 1 and bad.stderr.strip().startswith("--against no-such-commit: git could not check it")
