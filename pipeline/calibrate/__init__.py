"""Cameras calibrated from board images, and refined from a session's silhouettes.

``boards``, ``views``, ``solve``, ``result`` and ``report`` (``pipeline calibrate``);
``adjust`` and ``refine`` (the cameras and a few frames' tubes adjusted together,
``[calibration] refine``). Imports ``reconstruct`` and below.
"""
