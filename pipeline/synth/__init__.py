"""Synthetic data with known truth, for tests, benchmarks, demos and segmenter training (not the method itself).

- :mod:`pipeline.synth.soft_arm`: soft continuum arms (Bezier or constant-curvature centrelines) drawn as shaded
  tubes on random backgrounds.
- :mod:`pipeline.synth.manipulator`: random joint states, colours and photometric changes for rigid manipulators.
- :mod:`pipeline.synth.pose`: camera views of a manipulator, its rendered mask, and segmentation-like corruption.
"""
