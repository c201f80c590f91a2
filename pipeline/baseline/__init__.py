"""The original method, kept as a baseline to compare with.

``carving`` (its big-cube carving heuristic), ``curve`` (its sphere-fit/polyfit
centreline, also ``[centerline] method = "polyfit"``). Imports ``carve`` and below.
"""
