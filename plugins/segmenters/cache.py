"""Compact in-memory masks and the optional on-disk mask cache of the instance segmenters."""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from artclass_core import InputError
from artclass_core.params import Params, as_dict

__all__ = ["PackedMask", "DiskMaskCache", "params_hash"]


@dataclass(frozen=True)
class PackedMask:
    """A boolean mask stored as the bits of its bounding box (a few kB instead of W*H bytes)."""

    shape: tuple[int, int]
    box: tuple[int, int, int, int]  # y0, x0, y1, x1 (exclusive ends); empty mask: all 0
    bits: bytes

    @classmethod
    def pack(cls, mask: np.ndarray) -> PackedMask:
        mask = np.ascontiguousarray(mask, dtype=bool)
        x0, y0, w, h = cv2.boundingRect(mask.view(np.uint8))
        if not w:
            return cls(mask.shape, (0, 0, 0, 0), b"")
        y1, x1 = y0 + h, x0 + w
        return cls(mask.shape, (y0, x0, y1, x1), np.packbits(mask[y0:y1, x0:x1]).tobytes())

    @property
    def empty(self) -> bool:
        return not self.bits

    def crop(self) -> np.ndarray:
        """The mask inside its bounding box, shape (y1 - y0, x1 - x0)."""
        y0, x0, y1, x1 = self.box
        n = (y1 - y0) * (x1 - x0)
        return (
            np.unpackbits(np.frombuffer(self.bits, np.uint8), count=n).reshape(y1 - y0, x1 - x0).astype(bool)
        )

    def unpack(self) -> np.ndarray:
        """The full mask, ndarray of bool, shape ``self.shape``."""
        out = np.zeros(self.shape, dtype=bool)
        if not self.empty:
            y0, x0, y1, x1 = self.box
            out[y0:y1, x0:x1] = self.crop()
        return out


def params_hash(params: Params, *, exclude: tuple[str, ...] = ("cache_dir",)) -> str:
    """A short stable hash of a parameter dataclass (fields in ``exclude`` left out)."""
    values = {k: v for k, v in as_dict(params).items() if k not in exclude}
    text = json.dumps(dict(cls=type(params).__qualname__, values=values), sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


class DiskMaskCache:
    """Masks as PNG files under ``root/<segmenter>-<params hash>/<sequence key>/<frame name>.png``.

    The sequence key is the sequence name plus a hash of its resolved path, so two sequences of the
    same name in different folders do not collide. An empty mask is stored as an all-zero PNG.
    Writing into the sequence's own folder is refused.
    """

    def __init__(self, root: str | Path, *, segmenter: str, params: Params):
        self.root = Path(root).expanduser()
        self.folder = self.root / f"{segmenter}-{params_hash(params)}"

    def check_outside(self, sequence_path: Path) -> None:
        """Raise :class:`InputError` if the cache folder is the sequence folder or inside it."""
        seq = Path(sequence_path).expanduser().resolve()
        root = self.root.resolve()
        if root == seq or seq in root.parents:
            raise InputError(
                f"cache_dir {self.root} is inside the sequence folder; choose a folder outside "
                "the input data (artclass never writes into an input folder)",
                path=sequence_path,
            )

    def _file(self, sequence_path: Path, sequence_name: str, frame_name: str) -> Path:
        key = hashlib.sha256(str(Path(sequence_path).expanduser().resolve()).encode()).hexdigest()[:12]
        safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in sequence_name)
        return self.folder / f"{safe}-{key}" / f"{frame_name}.png"

    def load(self, sequence_path: Path, sequence_name: str, frame_name: str) -> np.ndarray | None:
        """The cached mask (bool (H, W)), or None when not cached or unreadable."""
        path = self._file(sequence_path, sequence_name, frame_name)
        if not path.is_file():
            return None
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        return None if image is None else image > 0

    def store(self, sequence_path: Path, sequence_name: str, frame_name: str, mask: np.ndarray) -> None:
        path = self._file(sequence_path, sequence_name, frame_name)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.png")
        if not cv2.imwrite(str(tmp), np.asarray(mask, dtype=np.uint8) * 255):
            raise InputError("could not write the mask cache file", path=tmp)
        tmp.replace(path)
