"""Recordings: the MCAP and Rerun files written, and the MCAP read back.

``mcap_log`` (Foxglove schemas), ``rerun_log`` (the .rrd and its layout), ``load``
(:func:`pipeline.load_recording`), ``commit_marker`` (a pair of files renamed into place
together). Imports ``reconstruct`` and below.
"""
