"""Imports point one way (DESIGN.md section 2): cli -> track -> estimators -> optimize -> losses/render ->
robots/shapes -> camera/geometry -> checks/errors. A module may import its own layer or lower ones, never higher."""

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "pipeline"

# Layer of each top-level module or subpackage of ``pipeline`` (higher imports lower).
LAYERS = {
    "errors": 0, "checks": 0,
    "camera": 1, "geometry": 1, "io": 1,
    "shapes": 2, "robots": 2, "preprocess": 2,
    "render": 3, "losses": 3, "viz": 3, "evaluate": 3, "segment": 3,
    "synth": 4,
    "optimize": 5,
    "shape_estimation": 6, "pose_estimation": 6,
    "track": 7, "demo": 7,
    "cli": 8, "batch": 8, "__main__": 8, "__init__": 8,
}


def _layer_of(module: str) -> int:
    name = module.split(".")[1] if module.count(".") else "__init__"
    if name not in LAYERS:
        raise AssertionError(f"pipeline.{name} has no layer in tests/test_layers.py: add it to LAYERS")
    return LAYERS[name]


def test_imports_point_down():
    wrong = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE.parent).with_suffix("")
        module = ".".join(rel.parts)
        own = _layer_of(module if module.count(".") else "pipeline.__init__")
        for node in ast.walk(ast.parse(path.read_text())):
            targets = []
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("pipeline."):
                targets = [node.module]
            elif isinstance(node, ast.Import):
                targets = [a.name for a in node.names if a.name.startswith("pipeline.")]
            for target in targets:
                if _layer_of(target) > own:
                    wrong.append(f"{module} (layer {own}) imports {target} (layer {_layer_of(target)})")
    assert not wrong, "imports that point up:\n" + "\n".join(wrong)
