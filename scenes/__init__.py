"""Synthetic LiDAR scenes with exact ground truth, flat-ground baselines, and where the real
labelled scans are (real_data).

Not runtime code: the tests and benchmarks use it (it is not installed with the package).
"""
