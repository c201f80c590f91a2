"""How good and how fast: recordings against ground truth, the accuracy table, the benchmark.

``evaluate`` (``pipeline evaluate``), ``accuracy_table`` (``python -m
pipeline.accuracy_table``), ``bench`` (``make bench``). Imports anything below.
"""
