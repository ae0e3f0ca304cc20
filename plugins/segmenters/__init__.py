"""Segmenters: masks of the handled object, and the ``artclass models`` command for their weights."""

from artclass_core import hookimpl

from .commands import add_models_command
from .depth_threshold import DepthThresholdSegmenter
from .mask import MaskSegmenter
from .maskrcnn import MaskrcnnSegmenter
from .u2net import U2netSegmenter


@hookimpl
def register_segmenters(register):
    register(MaskSegmenter)
    register(DepthThresholdSegmenter)
    register(U2netSegmenter)
    register(MaskrcnnSegmenter)


@hookimpl
def register_commands(subparsers):
    add_models_command(subparsers)
