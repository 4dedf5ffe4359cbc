"""Robot descriptions: the soft continuum robot (and, later, URDF manipulators)."""

from pipeline.robots.continuum import ContinuumRobot

__all__ = ["ContinuumRobot"]
