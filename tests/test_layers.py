"""Imports point one way (DESIGN.md section 2): cli -> track -> estimators -> optimize -> losses/render ->
robots/shapes -> camera/geometry -> checks/errors. A module may import its own layer or lower ones, never higher."""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "pipeline"

# Layer of each top-level module or subpackage of ``pipeline`` (higher imports lower).
LAYERS = {
    "errors": 0, "checks": 0,
    "camera": 1, "geometry": 1, "io": 1,
    "shapes": 2, "robots": 2, "preprocess": 2,
    "render": 3, "losses": 3, "_losses_numba": 3, "_path_numba": 3, "_radii_numba": 3, "_tube_loss_numba": 3, "viz": 3, "evaluate": 3,
    "segment": 3,
    "synth": 4,
    "optimize": 5,
    "shape_estimation": 6, "pose_estimation": 6,
    "track": 7, "demo": 7,
    "cli": 8, "batch": 8, "__main__": 8, "__init__": 8,
}


def _layer_of(module: str) -> int:
    """Layer of a dotted module name: that of its top-level module or subpackage (``pipeline`` itself: its
    ``__init__``)."""
    name = module.split(".")[1] if module.count(".") else "__init__"
    if name not in LAYERS:
        raise AssertionError(f"pipeline.{name} has no layer in tests/test_layers.py: add it to LAYERS")
    return LAYERS[name]


def _imported_modules(source: str, module: str) -> list[str]:
    """Dotted names of the ``pipeline`` modules that ``source`` imports, written as ``import pipeline.x [as y]``,
    ``from pipeline.x import y``, ``from pipeline import x`` (``pipeline.x`` when ``x`` is a top-level module or
    subpackage, else a name of ``pipeline/__init__.py``) or relatively (``from . import x``, ``from .x import y``,
    ``from ..x import y``, resolved against the package of ``module``).

    Args:
        source: Python source of the importing file.
        module: its dotted name, ``__init__`` included for a package's own file (``pipeline.render.__init__``).
    """
    package = module.split(".")[:-1]  # where a relative import starts: the file's package
    targets = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            targets += [a.name for a in node.names if a.name == "pipeline" or a.name.startswith("pipeline.")]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                if node.level > len(package):
                    raise AssertionError(f"{module}: relative import beyond the top-level package")
                base = package[: len(package) - node.level + 1] + ([node.module] if node.module else [])
                source_module = ".".join(base)
            else:
                source_module = node.module or ""
            if source_module == "pipeline":
                targets += [f"pipeline.{a.name}" if a.name in LAYERS else "pipeline" for a in node.names]
            elif source_module.startswith("pipeline."):
                targets.append(source_module)
    return targets


def _upward_imports(source: str, module: str) -> list[str]:
    own = _layer_of(module)
    return [f"{module} (layer {own}) imports {target} (layer {_layer_of(target)})"
            for target in _imported_modules(source, module) if _layer_of(target) > own]  # fmt: skip


def test_imports_point_down():
    wrong = []
    for path in sorted(PACKAGE.rglob("*.py")):
        module = ".".join(path.relative_to(PACKAGE.parent).with_suffix("").parts)  # pipeline.render.__init__
        wrong += _upward_imports(path.read_text(), module)
    assert not wrong, "imports that point up:\n" + "\n".join(wrong)


@pytest.mark.parametrize("module, source, target", [
    ("pipeline.geometry", "import pipeline.optimize", "pipeline.optimize"),
    ("pipeline.geometry", "import pipeline.optimize as opt", "pipeline.optimize"),
    ("pipeline.geometry", "from pipeline.optimize import fit", "pipeline.optimize"),
    ("pipeline.geometry", "from pipeline import optimize", "pipeline.optimize"),
    ("pipeline.geometry", "from pipeline import estimate_pose", "pipeline"),  # a name of pipeline/__init__.py
    ("pipeline.geometry", "from . import optimize", "pipeline.optimize"),
    ("pipeline.geometry", "from .optimize import fit", "pipeline.optimize"),
    ("pipeline.render.rasterize", "from ..optimize import fit", "pipeline.optimize"),
    ("pipeline.render.rasterize", "from .. import synth", "pipeline.synth"),
    ("pipeline.shapes.__init__", "from .. import render", "pipeline.render"),
    ("pipeline.shapes.__init__", "from ..render.rasterize import render_hard", "pipeline.render.rasterize"),
    ("pipeline.render.settings", "def f():\n    from pipeline import viz, cli\n", "pipeline.cli"),  # in a function
])  # fmt: skip
def test_every_import_form_pointing_up_is_reported(module, source, target):
    assert _imported_modules(source, module)[-1] == target
    assert _upward_imports(source, module) == [
        f"{module} (layer {_layer_of(module)}) imports {target} (layer {_layer_of(target)})"
    ]


@pytest.mark.parametrize("module, source", [
    ("pipeline.render.rasterize", "from . import settings\nfrom .settings import X\nfrom ..errors import E"),
    ("pipeline.render.rasterize", "from pipeline import errors, camera\nimport pipeline.shapes.bezier as b"),
    ("pipeline.shapes.__init__", "from .bezier import bezier_points\nfrom . import frames"),
    ("pipeline.cli.pose", "from pipeline import __version__\nfrom ..pose_estimation import estimate_pose"),
    ("pipeline.geometry", "import numpy\nfrom numpy import linalg\nfrom pipelines import x"),  # not ours
])  # fmt: skip
def test_imports_of_the_same_or_a_lower_layer_pass(module, source):
    assert _upward_imports(source, module) == []
