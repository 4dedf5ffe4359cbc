"""Robot state from one camera image by differentiable rendering of primitive meshes.

Two estimators share one core (mesh from parameters -> soft silhouette -> losses -> Adam, best state kept):
the camera-to-base pose of a rigid manipulator, and the 3D shape of a soft continuum robot.
"""

__version__ = "0.1.0"
