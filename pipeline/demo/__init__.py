"""The bundled examples run end to end (``python -m pipeline demo``): :mod:`pipeline.demo.shape` (soft arm) and
:mod:`pipeline.demo.pose` (manipulator)."""
