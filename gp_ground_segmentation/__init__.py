"""Gaussian-process ground segmentation for sloped terrain (Mehrabi & Taghirad, ICRoM 2021).

Layout: ``core`` (numpy/scipy/numba only, no ROS), ``labels`` (the labelled rows of a frame:
every valid point plus ground and height_above_ground; numpy only), ``ros`` (PointCloud2
conversion, the node, diagnostics, parameter loading; needs rclpy), ``tools`` (bag replay,
evaluation, plots, CLI). The public API below is the core's.
"""

from .core.params import SegmenterParams, describe_params
from .core.segmenter import GroundSegmenter, Hyperparameters, SegmentationResult, valid_points_mask

__all__ = ['GroundSegmenter', 'Hyperparameters', 'SegmentationResult', 'SegmenterParams',
           'describe_params', 'valid_points_mask']
__version__ = '0.1.0'
