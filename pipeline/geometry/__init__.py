"""Geometry without a session: pinhole cameras and polylines in mm.

``camera`` (projection, rays, the OpenCV model), ``polyline`` (arc length, resampling).
Imports nothing of the package but ``errors``.
"""
