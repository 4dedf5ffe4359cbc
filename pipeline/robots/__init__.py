"""Robot descriptions: the soft continuum robot and rigid manipulators from URDF, MJCF or SDF.

- :mod:`pipeline.robots.continuum`: the soft arm (tapered tube around a Bezier centreline).
- :mod:`pipeline.robots.manipulator`: the rendered model of a rigid manipulator (meshes + FK), and its loader.
- :mod:`pipeline.robots.description`: parsing the description and its kinematics.
- :mod:`pipeline.robots.link_geometry`: each link's mesh from its geometry elements (primitives or CAD).
- :mod:`pipeline.robots.mesh_io`: mesh files (name resolution, reading).
"""

from pipeline.robots.continuum import ContinuumRobot
from pipeline.robots.manipulator import ManipulatorModel, load_robot, load_urdf_robot

__all__ = ["ContinuumRobot", "ManipulatorModel", "load_robot", "load_urdf_robot"]
