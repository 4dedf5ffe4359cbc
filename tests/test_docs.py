"""The README and docs/: every relative link resolves (files and heading anchors), and the README's Python
examples run on the bundled data and give the examples' answers."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from pipeline.evaluate import centerline_errors

REPO = Path(__file__).resolve().parents[1]
DOCUMENTS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]

_FENCE = re.compile(r"^(```|~~~).*?^\1", re.MULTILINE | re.DOTALL)
_LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
_HEADING = re.compile(r"^#{1,6}\s+(.+?)\s*#*\s*$", re.MULTILINE)


def _prose(text: str) -> str:
    """``text`` without fenced code blocks and inline code (links there are not links)."""
    return re.sub(r"`[^`\n]*`", "", _FENCE.sub("", text))


def heading_anchors(text: str) -> set[str]:
    """The anchors GitHub gives the headings of a Markdown text: lower case, punctuation dropped, spaces to
    hyphens, ``-1``, ``-2`` ... appended to repeats."""
    anchors: set[str] = set()
    for heading in _HEADING.findall(_FENCE.sub("", text)):
        slug = re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")
        candidate, n = slug, 0
        while candidate in anchors:
            n += 1
            candidate = f"{slug}-{n}"
        anchors.add(candidate)
    return anchors


def broken_links(path: Path) -> list[str]:
    """The relative links of the Markdown file ``path`` whose file or ``#anchor`` does not exist."""
    broken = []
    for target in _LINK.findall(_prose(path.read_text(encoding="utf-8"))):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:
            continue
        file_part, _, anchor = target.partition("#")
        linked = (path.parent / file_part).resolve() if file_part else path
        if not linked.exists():
            broken.append(f"{target} (no file {linked})")
        elif anchor and linked.suffix == ".md" and anchor not in heading_anchors(linked.read_text(encoding="utf-8")):
            broken.append(f"{target} (no heading with anchor #{anchor} in {linked.name})")
    return broken


def test_anchors_follow_githubs_rule():
    text = ("# Speed (measured)\n## Model (`pipeline.robots.ContinuumRobot`)\n## Speed (measured)\n"
            "```\n# not a heading\n```")
    assert heading_anchors(text) == {"speed-measured", "model-pipelinerobotscontinuumrobot", "speed-measured-1"}


def test_the_link_checker_finds_a_missing_file_and_anchor(tmp_path):
    (tmp_path / "other.md").write_text("# Present heading\n")
    page = tmp_path / "page.md"
    page.write_text(
        "[ok](other.md#present-heading) [ok](#here) [web](https://example.com/x.md) `[code](nowhere.md)`\n"
        "## Here\n[gone](missing.md) [bad anchor](other.md#absent) ![img](pic.png)\n```\n[in code](nope.md)\n```\n"
    )
    assert [b.split(" ")[0] for b in broken_links(page)] == ["missing.md", "other.md#absent", "pic.png"]


@pytest.mark.parametrize("path", DOCUMENTS, ids=lambda p: p.name)
def test_every_relative_link_resolves(path):
    assert broken_links(path) == []


def readme_python_examples() -> list[str]:
    """The ```python blocks of the README, in order."""
    return re.findall(r"^```python\n(.*?)^```", (REPO / "README.md").read_text(encoding="utf-8"),
                      re.MULTILINE | re.DOTALL)


#: The one change made to the README's examples before they run: the default fit configs become the quick ones the
#: demo tests use (fewer iterations, a smaller working image), so that the test takes seconds, not a minute.
QUICK_CONFIGS = {
    "ShapeFitConfig()": "ShapeFitConfig(iterations=100)",
    "PoseFitConfig()": "PoseFitConfig(iterations=250, working_max_side=320)",
}


@pytest.mark.slow
def test_readme_python_examples_run_and_find_the_bundled_answers(monkeypatch, capsys):
    examples = readme_python_examples()
    assert len(examples) == 2, "the README has one Python example per robot kind"
    for default in QUICK_CONFIGS:
        assert sum(code.count(default) for code in examples) == 1, f"the README's examples use {default} once"
    monkeypatch.chdir(REPO)
    namespaces = []
    for code in examples:
        for default, quick in QUICK_CONFIGS.items():
            code = code.replace(default, quick)
        namespace: dict = {}
        exec(compile(code, "README.md", "exec"), namespace)  # noqa: S102 - the README's own examples
        namespaces.append(namespace)
    shape_ns = next(ns for ns in namespaces if "shape" in ns)
    pose_ns = next(ns for ns in namespaces if "pose" in ns)

    truth = json.loads((REPO / "data/soft_arm/quadratic/truth.json").read_text())
    K = np.asarray(json.loads((REPO / "data/soft_arm/quadratic/camera.json").read_text())["K"])
    errors = centerline_errors(np.asarray(shape_ns["shape"].centerline_cam_m), np.asarray(truth["centerline_cam_m"]), K)
    assert errors["mean_3d_mm"] < 5.0 and errors["mean_2d_px"] < 2.0, errors  # the demo's figures: 1.9 mm, 0.63 px

    truth = json.loads((REPO / "data/toy_arm/truth.json").read_text())
    T = np.asarray(pose_ns["pose"].T_cam_root)
    assert np.linalg.norm(T[:3, 3] - np.asarray(truth["T_cam_root"])[:3, 3]) < 0.02
    assert capsys.readouterr().out  # the examples print their answers
