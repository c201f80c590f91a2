"""Silhouettes and the visual hull: each view thresholded, the views' cones intersected.

``silhouette`` (grey image to mask), ``hull`` (exact voxel carving through per-camera
lookup tables). Imports ``session``, ``geometry`` and ``errors``.
"""
