"""Robot descriptions: the soft continuum robot and rigid manipulators from URDF."""

from pipeline.robots.continuum import ContinuumRobot
from pipeline.robots.urdf import ManipulatorModel
from pipeline.robots.urdf import load_urdf_robot

__all__ = ["ContinuumRobot", "ManipulatorModel", "load_urdf_robot"]
