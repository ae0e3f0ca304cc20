"""Segmenters: masks of the handled object."""

from artclass_core import hookimpl

from .depth_threshold import DepthThresholdSegmenter
from .mask import MaskSegmenter


@hookimpl
def register_segmenters(register):
    register(MaskSegmenter)
    register(DepthThresholdSegmenter)
