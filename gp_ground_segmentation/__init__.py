"""Gaussian-process ground segmentation for sloped terrain (Mehrabi & Taghirad, ICRoM 2021)."""

from .params import SegmenterParams, describe_params
from .segmenter import GroundSegmenter, Hyperparameters, SegmentationResult, valid_points_mask

__all__ = ['GroundSegmenter', 'Hyperparameters', 'SegmentationResult', 'SegmenterParams',
           'describe_params', 'valid_points_mask']
__version__ = '0.1.0'
