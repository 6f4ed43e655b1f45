"""Synthetic LiDAR scenes with exact ground truth, and flat-ground baselines.

Not runtime code: the tests and benchmarks use it (it is not installed with the package).
"""
