"""Writer for artclass's native sequence folder.

Layout (read by the rest of artclass)::

    SEQ/meta.json          intrinsics, depth_scale, label, object, motion, noise, seed, ...
    SEQ/truth.json         joint_type, joint_positions, object_poses (camera_from_object); parts,
                           joints (per frame state and axis in the first camera frame), part_poses,
                           part_valid_px, part_points_m (visible points per part and frame), sensor,
                           holders; for articulated objects also part_visibility
                           (docs/data-formats.md describes every key)
    SEQ/rgb/000000.png     8-bit colour (stored BGR by OpenCV, i.e. a normal colour PNG)
    SEQ/depth/000000.png   uint16 depth, depth_scale units per metre, 0 = no reading
    SEQ/mask/000000.png    uint8, 255 = object, 0 = anything else (a hand is not the object)
    SEQ/hand/000000.png    uint8, 255 = hand or gripper, 0 = anything else
    SEQ/parts/000000.png   uint8, 0 = not the object, 1 + part index = that part
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np

__all__ = [
    "DEPTH_SCALE",
    "depth_to_uint16",
    "prepare_sequence_dir",
    "write_frame",
    "write_json",
]

#: Depth units per metre in the depth PNGs (1000: millimetres).
DEPTH_SCALE = 1000
#: Entries a sequence folder consists of; ``overwrite=True`` removes only these.
SEQUENCE_ENTRIES = ("rgb", "depth", "mask", "hand", "parts", "meta.json", "truth.json")
#: Image folders of a sequence.
IMAGE_FOLDERS = ("rgb", "depth", "mask", "hand", "parts")
# zlib level 1: about 4x faster to write than level 6 for noisy 640x480 images, files about 5 % larger.
_PNG_PARAMS = [cv2.IMWRITE_PNG_COMPRESSION, 1]


def prepare_sequence_dir(out_dir: str | Path, *, overwrite: bool = False) -> Path:
    """Create ``out_dir`` with empty image folders (``rgb/``, ``depth/``, ``mask/``, ``hand/``,
    ``parts/``).

    Parameters
    ----------
    out_dir : str or Path
    overwrite : bool
        If False, a non-empty ``out_dir`` is refused. If True, the sequence
        entries (the image folders, ``meta.json``, ``truth.json``) are removed
        first; other files are left alone.

    Returns
    -------
    Path

    Raises
    ------
    FileExistsError
        ``out_dir`` is a non-empty folder and ``overwrite`` is False, or it is a file.
    """
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"{out} exists and is not a folder")
    if out.is_dir() and any(out.iterdir()):
        if not overwrite:
            raise FileExistsError(
                f"{out} is not empty; refusing to overwrite it (pass overwrite=True "
                "or --overwrite to replace the sequence in it)"
            )
        for name in SEQUENCE_ENTRIES:
            p = out / name
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p)
            elif p.exists() or p.is_symlink():
                p.unlink()
    for sub in IMAGE_FOLDERS:
        (out / sub).mkdir(parents=True, exist_ok=True)
    return out


def depth_to_uint16(depth_m: np.ndarray, *, depth_scale: int = DEPTH_SCALE) -> np.ndarray:
    """Metres to uint16 depth units (rounded); invalid, negative or out-of-range -> 0."""
    d = np.asarray(depth_m, dtype=np.float64) * depth_scale
    d = np.where(np.isfinite(d) & (d > 0), np.rint(d), 0.0)
    d = np.where(d > 65535, 0.0, d)
    return d.astype(np.uint16)


def _imwrite(path: Path, image: np.ndarray) -> None:
    if not cv2.imwrite(str(path), image, _PNG_PARAMS):
        raise OSError(f"could not write {path}")


def write_rgbd(
    seq_dir: str | Path, index: int, *, rgb: np.ndarray, depth_m: np.ndarray, depth_scale: int
) -> None:
    """Write frame ``index``'s colour (RGB order) and depth (metres) into ``rgb/`` and ``depth/``."""
    name = f"{index:06d}.png"
    _imwrite(Path(seq_dir) / "rgb" / name, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    _imwrite(Path(seq_dir) / "depth" / name, depth_to_uint16(depth_m, depth_scale=depth_scale))


def write_frame(
    seq_dir: str | Path,
    index: int,
    *,
    rgb: np.ndarray,
    depth_m: np.ndarray,
    mask: np.ndarray,
    hand: np.ndarray | None = None,
    parts: np.ndarray | None = None,
    depth_scale: int = DEPTH_SCALE,
) -> None:
    """Write frame ``index`` of a sequence.

    Parameters
    ----------
    seq_dir : str or Path
        A folder made by ``prepare_sequence_dir``.
    index : int
        Frame number; files are named ``%06d.png``.
    rgb : ndarray, shape (H, W, 3), uint8, RGB order
    depth_m : ndarray, shape (H, W), metres, 0 = no reading
    mask : ndarray, shape (H, W), bool
    hand : ndarray, shape (H, W), bool, optional
        Hand or gripper pixels (``hand/``); all zero when omitted.
    parts : ndarray, shape (H, W), uint8, optional
        0 = not the object, 1 + part index (``parts/``); the mask as part 0 when omitted.
    """
    seq = Path(seq_dir)
    name = f"{index:06d}.png"
    rgb = np.asarray(rgb)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"rgb must be uint8 of shape (H, W, 3), got {rgb.dtype} {rgb.shape}")
    if depth_m.shape != rgb.shape[:2] or mask.shape != rgb.shape[:2]:
        raise ValueError(f"depth {depth_m.shape} and mask {mask.shape} must match rgb {rgb.shape[:2]}")
    write_rgbd(seq, index, rgb=rgb, depth_m=depth_m, depth_scale=depth_scale)
    mask = np.asarray(mask, dtype=bool)
    _imwrite(seq / "mask" / name, np.where(mask, 255, 0).astype(np.uint8))
    hand = np.zeros_like(mask) if hand is None else np.asarray(hand, dtype=bool)
    if (hand & mask).any():
        raise ValueError("a hand pixel is also an object pixel: the hand is never the object")
    _imwrite(seq / "hand" / name, np.where(hand, 255, 0).astype(np.uint8))
    parts = mask.astype(np.uint8) if parts is None else np.asarray(parts, dtype=np.uint8)
    if parts.shape != mask.shape or ((parts > 0) != mask).any():
        raise ValueError("the part map must be non-zero exactly on the mask")
    _imwrite(seq / "parts" / name, parts)


def write_json(path: str | Path, obj) -> None:
    """Write ``obj`` as indented JSON with a trailing newline."""
    Path(path).write_text(json.dumps(obj, indent=1) + "\n")
