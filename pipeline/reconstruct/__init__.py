"""One frame to its centreline: the tube model fitted to the silhouettes, tracked over time.

``model`` (what every frame shares: cameras, hull grid, settings), ``frame`` (a frame's
silhouettes, hull and curve), ``ordering`` (the hull's base-to-tip march, the
initialiser), ``tube_fit`` (the tube fitted to the views' sub-pixel edges), ``tube_tip``
(its end against the grey levels), ``centerline`` (the fit's steps), ``profiles`` (the
radius along it), ``tracking`` (each frame started from the last), ``quality`` (the
per-frame metrics and the suspect flag), ``tip_shape`` (the session's end, flat or
round), ``frame_result`` and ``frame_task`` (a range of frames from the videos).
Imports ``baseline``, ``carve``, ``session`` and below.
"""
