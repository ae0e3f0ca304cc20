"""Classifying frames as they arrive: the running decision after every pair.

:func:`classify_live` runs the same pipeline steps as :meth:`Pipeline.run` (segment and preprocess
each frame, register and decide each pair (i, i + k), again over slow_factor k frames when it shows
no motion, filter and label), one frame at a time in arrival order, and yields a
:class:`LiveUpdate` after each pair. A source that knows its length (a file) gives exactly the
pairs ``artclass classify`` gives on it; a camera's last few frames, whose later neighbours never
come, are not classified.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from artclass_core import Config, Frame, InputError, Pipeline, Sequence
from artclass_core.plugins import Registry
from artclass_core.types import FrameResult, PairResult, RunResult

from ..synth.write import DEPTH_SCALE, write_json, write_rgbd
from .sources import FrameSource

#: The length of a sequence whose end is not known (a camera): segmenters that compare a frame with a
#: later one then always find one after it.
UNBOUNDED = 10**9


class StreamEnded(InputError):
    """A frame was asked for after the source's last one."""


class LiveSequence(Sequence):
    """The frames of a source as a sequence: frame i waits until the source has sent it.

    A thread pulls frames from the source into a window of the last ``keep`` frames, and waits while
    it is ``keep // 2`` frames ahead of the frames asked for (a camera's SDK then drops frames, as it
    does for any slow consumer). Frames older than the window are forgotten.
    """

    def __init__(self, source: FrameSource, *, keep: int = 64, record: Path | None = None):
        super().__init__(
            name=source.name,
            path=source.path,
            intrinsics=source.intrinsics,
            n_frames=source.n_frames or UNBOUNDED,
            meta=dict(live=True),
        )
        self.source, self.keep, self.record = source, keep, record
        self.received = 0  # frames sent by the source so far
        self._frames: dict[int, Frame] = {}
        self._asked = 0
        self._done = False
        self._error: BaseException | None = None
        self._changed = threading.Condition()
        self._stop = threading.Event()
        if record is not None:
            _start_recording(record, source)
        self._thread = threading.Thread(target=self._pull, name="artclass-live-source", daemon=True)
        self._thread.start()

    def _pull(self) -> None:
        try:
            for frame in self.source.frames():
                if self.record is not None:
                    _record_frame(self.record, frame)
                with self._changed:
                    self._frames[frame.index] = frame
                    self.received = frame.index + 1
                    for old in [i for i in self._frames if i < self.received - self.keep]:
                        del self._frames[old]
                    self._changed.notify_all()
                    self._changed.wait_for(
                        lambda: self._stop.is_set() or self.received <= self._asked + self.keep // 2
                    )
                if self._stop.is_set():
                    break
        except BaseException as exc:  # handed to the frame that waits for it
            self._error = exc
        finally:
            with self._changed:
                self._done = True
                self._changed.notify_all()

    def load(self, i: int) -> Frame:
        with self._changed:
            self._asked = max(self._asked, i)
            self._changed.notify_all()
            self._changed.wait_for(lambda: i in self._frames or self._done or i < self.received - self.keep)
            if i in self._frames:
                return self._frames[i]
        if self._error is not None:
            raise self._error
        if i < self.received - self.keep:
            raise InputError(f"frame {i} is no longer kept (only the last {self.keep} are)", path=self.path)
        raise StreamEnded(f"the source ended after {self.received} frames", path=self.path)

    def stop(self) -> None:
        """Stop pulling frames and close the source."""
        self._stop.set()
        with self._changed:
            self._changed.notify_all()
        self._thread.join(timeout=10)
        self.source.close()


@dataclass
class LiveUpdate:
    """The state after one more pair: that pair, and the run so far (label, filtered decisions, all
    pairs). The pair's evidence and its two frames' clouds are kept until the next update, for a 3D
    view of the latest pair."""

    pair: PairResult
    result: RunResult
    source: FrameResult
    target: FrameResult
    n_frames: int  # frames classified so far


def classify_live(
    registry: Registry,
    source: FrameSource,
    config: Config | None = None,
    *,
    record: Path | None = None,
    max_frames: int | None = None,
) -> Iterator[LiveUpdate]:
    """Classify the frames of ``source`` as they arrive; one :class:`LiveUpdate` after each pair.

    Parameters
    ----------
    source : a :class:`~artclass_plugins.live.sources.FrameSource`
    config : the pipeline (default: the mask-free ``depth_threshold`` segmenter)
    record : a folder to write the frames into, in the native folder layout, as they arrive
    max_frames : stop after this many frames (None: when the source ends)

    Closing the iterator (or leaving a ``for`` loop over it) stops the source.
    """
    config = config or Config(segmenter="depth_threshold")
    pipeline = Pipeline(registry, config)
    k, far = pipeline.params.k, pipeline.params.k * pipeline.params.slow_factor
    sequence = LiveSequence(source, record=record)
    n = min(max_frames or UNBOUNDED, source.n_frames or UNBOUNDED)
    frames: list[FrameResult] = []  # frames[i] is frame i
    pairs: list[PairResult] = []
    pending: deque[FrameResult] = deque()  # the frames whose pair is not decided yet
    timing: dict[str, float] = {}

    def decide(*, at_end: bool) -> Iterator[LiveUpdate]:
        # Pair i is decided once frame i + far is in (the longer pair's), or at the end with i + k.
        while len(pending) > far or (at_end and len(pending) > k):
            first = pending.popleft()
            pair = pipeline.pair_for(sequence, first, tuple(pending), timing)
            if pairs:  # the previous pair's evidence and first cloud served its 3D view
                pairs[-1].release()
                frames[pairs[-1].i].cloud = None
            pairs.append(pair)
            result = pipeline.summarise(sequence, frames, pairs, timing)
            yield LiveUpdate(pair, result, first, frames[pair.j], len(frames))

    try:
        for j in range(n):
            try:
                frames.append(pipeline.frame(sequence, j, timing=timing))
            except StreamEnded:
                break
            pending.append(frames[-1])
            yield from decide(at_end=j == n - 1)
        yield from decide(at_end=True)
    finally:
        sequence.stop()
    if not frames:
        raise InputError("the source sent no frame", path=source.path)


# -- recording --------------------------------------------------------------------------------------


def _start_recording(folder: Path, source: FrameSource) -> None:
    """An empty folder for a recording in the native layout (an existing non-empty one is refused,
    so no user data is overwritten)."""
    folder = Path(folder)
    if folder.exists() and (not folder.is_dir() or any(folder.iterdir())):
        raise InputError("exists and is not an empty folder; record into a new one", path=folder)
    for sub in ("rgb", "depth"):
        (folder / sub).mkdir(parents=True, exist_ok=True)
    k = source.intrinsics
    meta = dict(fx=k.fx, fy=k.fy, cx=k.cx, cy=k.cy, depth_scale=DEPTH_SCALE, object=source.name)
    write_json(folder / "meta.json", dict(meta, recorded_from=str(source.path)))


def _record_frame(folder: Path, frame: Frame) -> None:
    try:
        write_rgbd(folder, frame.index, rgb=frame.rgb, depth_m=frame.depth_m, depth_scale=DEPTH_SCALE)
    except OSError as exc:
        raise InputError(f"could not write frame {frame.index}: {exc}", path=folder) from None
