"""A session on disk: its settings, calibration and videos, validated on load.

``settings`` (session.toml into one validated object), ``toml_file``, ``calibration_io``
(calibration.toml), ``video`` (decoding and checks), ``grey_levels`` (images of any depth
as the videos' 8-bit levels), ``folder`` (a session directory: :func:`pipeline.load_session`).
Imports ``geometry`` and ``errors``.
"""
