"""Steps 1 and 2 of the pipeline: one frame -> the object's mask -> its preprocessed cloud."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np

from .cache import StageCache
from .config import AUTO_SEGMENTER, Config, stage_dependencies
from .params import PipelineParams
from .plugins import Registry
from .scheduler import add_time, merge_timing
from .types import Cloud, FrameResult, Sequence, reading_seconds


@dataclass(frozen=True)
class _RawFrame:
    """What segmentation and preprocessing gave for one frame, before the pipeline's own checks."""

    index: int
    name: str
    cloud: Cloud | None
    mask_pixels: int


class FrameSteps:
    """Segment and preprocess frames, through a :class:`StageCache` when one is given. Used by
    :class:`~artclass_core.pipeline.Pipeline`, which sets the attributes below."""

    registry: Registry
    config: Config
    params: PipelineParams
    preprocessor: object
    _segmenters: dict[str, object]
    _lock: threading.Lock

    def segmenter_name(self, sequence: Sequence) -> str:
        name = self.config.segmenter
        if name == AUTO_SEGMENTER:
            name = "mask" if sequence.has_masks else "depth_threshold"
        return name

    def segmenter(self, sequence: Sequence):
        name = self.segmenter_name(sequence)
        with self._lock:
            if name not in self._segmenters:
                self._segmenters[name] = self.registry.create(
                    "segmenter", name, self.config.plugin_params(self.registry, "segmenter", name)
                )
            return self._segmenters[name]

    def frame(
        self,
        sequence: Sequence,
        i: int,
        *,
        timing: dict[str, float] | None = None,
        cache: StageCache | None = None,
    ) -> FrameResult:
        """Read, segment and preprocess frame ``i`` (taken from ``cache`` when it holds it). A frame with
        no object is returned as skipped."""
        return self._finish_frame(self._raw_frame(sequence, i, timing if timing is not None else {}, cache))

    def frame_key(self, sequence: Sequence, i: int, cache: StageCache) -> tuple:
        """The cache key of frame ``i``: the sequence, the frame and what the ``preprocess`` stage depends on."""
        return (cache.sequence_token(sequence), i, *self.depends(sequence, "preprocess"))

    def depends(self, sequence: Sequence, stage: str) -> tuple:
        """What the output of ``stage`` on ``sequence`` depends on (:func:`~artclass_core.config.stage_dependencies`)."""
        return stage_dependencies(self.config, self.registry, stage, segmenter=self.segmenter_name(sequence))

    def _raw_frame(
        self, sequence: Sequence, i: int, timing: dict[str, float], cache: StageCache | None
    ) -> _RawFrame:
        key = None if cache is None else self.frame_key(sequence, i, cache)
        if (hit := None if key is None else cache.get("frame", key)) is not None:
            return hit
        t0, read0 = time.perf_counter(), reading_seconds()
        frame = sequence[i]
        segmenter = self.segmenter(sequence)
        mask = segmenter.segment(frame, sequence=sequence)
        t2, read = time.perf_counter(), reading_seconds() - read0
        # A segmenter that compares the frame with later ones reads them ahead: reading, not segmenting.
        merge_timing(timing, {"read": read, "segment": t2 - t0 - read})
        n_mask = 0 if mask is None else int(np.count_nonzero(mask))
        raw = _RawFrame(i, frame.name, None, 0)
        if n_mask:
            cloud = self.preprocessor.process(frame, mask, intrinsics=sequence.intrinsics)
            add_time(timing, "preprocess", time.perf_counter() - t2)
            if cloud.view is not None and hasattr(segmenter, "covered"):
                cloud.view.covered = segmenter.covered(frame, sequence=sequence)
            raw = _RawFrame(i, frame.name, cloud, n_mask)
        if key is not None:
            cache.put("frame", key, raw)
        return raw

    def _finish_frame(self, raw: _RawFrame) -> FrameResult:
        if raw.cloud is None:
            return FrameResult(raw.index, raw.name, None, skipped="no object found")
        cloud = raw.cloud
        if len(cloud) < self.params.min_cell_points:
            read = cloud.info.get("n_raw")  # the mask's pixels the preprocessor found a depth reading on
            return FrameResult(
                raw.index,
                raw.name,
                None,
                skipped=f"only {len(cloud)} object points from a mask of {raw.mask_pixels} pixels"
                + ("" if read is None else f", {read} of them with a depth reading"),
                mask_pixels=raw.mask_pixels,
                info=dict(cloud.info),
            )
        return FrameResult(raw.index, raw.name, cloud, mask_pixels=raw.mask_pixels, info=dict(cloud.info))
