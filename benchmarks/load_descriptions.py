"""Load every robot description of the ``example-robot-data`` package, as a user with one of them would.

Each ``.urdf`` and ``.sdf`` file under the package's ``robots/`` folder (and, where robosuite's assets are
installed, each of its robots' and grippers' MJCF files) is loaded from its root link (the one no joint has as its
child; MJCF: ``world``) with ``--primitive auto`` (hulls of the visual meshes) and ``cad`` (the visual meshes,
decimated), and reported as loaded (links, joints, seconds) or refused (the error's first line). A refusal should name a
problem of the file itself (a closed kinematic loop, a mimic of a joint that does not exist, a mesh path of
another machine); anything else is a gap of the loader. Meshes are read from the files (no disk cache), so the
seconds are a first load's.

    python benchmarks/load_descriptions.py [NAME_PART ...]    # e.g. pr2 icub: only files whose path contains one

Needs ``pip install .[robots]`` (example-robot-data). Exit code 0 when every file was handled (loaded or refused
with an ``AssetError`` / ``ConfigError``), 1 when one raised anything else.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from acceptance_robots import ROBOSUITE, ROBOT_DATA

from pipeline.errors import AssetError, ConfigError
from pipeline.robots import load_robot
from pipeline.robots.description import read_description


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("only", nargs="*", help="only files whose path contains one of these")
    args = parser.parse_args()
    if not ROBOT_DATA.is_dir():
        print(f"error: {ROBOT_DATA} not found; pip install .[robots]", file=sys.stderr)
        return 2
    files = sorted(p for p in ROBOT_DATA.rglob("*") if p.suffix in (".urdf", ".sdf"))
    if ROBOSUITE.is_dir():  # robots/<name>/robot.xml and grippers/<name>.xml
        files += sorted(ROBOSUITE.glob("*/robot.xml")) + sorted((ROBOSUITE.parent / "grippers").glob("*.xml"))
    files = [f for f in files if not args.only or any(part in str(f) for part in args.only)]
    loaded = refused = crashed = 0
    for path in files:
        name = (path.relative_to(ROBOT_DATA) if path.is_relative_to(ROBOT_DATA)
                else Path("robosuite") / path.relative_to(ROBOSUITE.parent))
        t0 = time.perf_counter()
        try:
            description = read_description(path)
            root = next(link for link in description.links if link not in description.parent_joint)
            models = [load_robot(path, root, primitive=p, mesh_cache=None) for p in ("auto", "cad")]
        except (AssetError, ConfigError) as error:
            refused += 1
            print(f"refused  {name}: {type(error).__name__}: {str(error).splitlines()[0][:200]}", flush=True)
            continue
        except Exception as error:  # a loader gap: reported, and the exit code says so
            crashed += 1
            print(f"CRASHED  {name}: {type(error).__name__}: {str(error)[:200]}", flush=True)
            continue
        loaded += 1
        faces = ", ".join(f"{m.primitive} {len(m.faces)} faces" for m in models)
        print(f"loaded   {name}: root {root!r}, {len(models[0].link_names)} links, {len(models[0].joint_names)} "
              f"joints; {faces}; {time.perf_counter() - t0:.1f} s", flush=True)
    print(f"{len(files)} descriptions: {loaded} loaded, {refused} refused with a message, {crashed} crashed")
    return 1 if crashed else 0


if __name__ == "__main__":
    sys.exit(main())
