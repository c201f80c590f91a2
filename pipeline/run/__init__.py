"""A session processed: frame ranges over workers, smoothing, the outputs written.

``runner`` (:func:`pipeline.process_session`), ``workers`` (joblib and Dask), ``outputs``
(the recordings' writers and the run's summary), ``smoothing``, ``interrupts`` (Ctrl-C
and SIGTERM). Imports ``record``, ``calibrate`` and below.
"""
