"""Geometry of robot parts: primitive meshes, Bezier curves, frames along curves, tube meshes, polylines."""
