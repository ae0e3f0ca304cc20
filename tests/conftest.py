"""Shared fixtures: the plugin registry, the data folders, synthetic sequences rendered once per test
run, and a small in-memory RGB-D sequence.

The in-memory sequences are rendered here, without the synthetic-data plugin, so the core tests do
not depend on it: flat panels facing the camera, densely sampled and z-buffered into a depth image,
with a known motion per frame (none, a translation, or one panel turning about a hinge).
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from artclass_core import Frame, Intrinsics, Sequence, load_registry

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # the app folder is not installed: it imports as app.*, from the project root
    sys.path.insert(0, str(ROOT))
SHARED_DATA = (Path(__file__).parents[1] / ".." / "shared" / "data").resolve()
SAMPLE_DATA = ROOT / "sample_data"

WIDTH, HEIGHT = 160, 120
INTRINSICS = Intrinsics(fx=160.0, fy=160.0, cx=79.5, cy=59.5, width=WIDTH, height=HEIGHT)
OBJECT_DEPTH_M = 0.6  # the panels' plane
BACKGROUND_DEPTH_M = 0.9  # a wall behind them, outside the mask
PANEL_SIZE_M = (0.10, 0.15)  # width (x), height (y) of one panel


@pytest.fixture(scope="session")
def registry():
    """The registry of every installed plugin (entry points of the group ``artclass``)."""
    return load_registry()


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data`` next to the repository; skips (with the reason) only when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(
            f"real data folder {SHARED_DATA} is absent (it sits next to the repository in the "
            f"development and CI set-up)"
        )
    return SHARED_DATA


@pytest.fixture(scope="session")
def sample_dir() -> Path:
    """The bundled ``sample_data/`` folder (committed to the repository)."""
    return SAMPLE_DATA


@pytest.fixture(scope="session")
def rendered(tmp_path_factory):
    """``rendered(object_name, motion, n_frames=..., seed=..., width=..., height=...)``: the folder of a
    synthetic sequence (low noise), rendered once per test run and shared; tests must not write into it."""
    from artclass_plugins.synth import generate_sequence

    root = tmp_path_factory.mktemp("rendered")
    done: dict[tuple, Path] = {}

    def render_once(
        object_name: str,
        motion: str,
        *,
        n_frames: int = 8,
        seed: int = 0,
        width: int = 320,
        height: int = 240,
    ) -> Path:
        key = (object_name, motion, n_frames, seed, width, height)
        if key not in done:
            folder = root / "_".join(map(str, key))
            generate_sequence(
                folder,
                object_name=object_name,
                motion=motion,
                noise="low",
                n_frames=n_frames,
                seed=seed,
                width=width,
                height=height,
            )
            done[key] = folder
        return done[key]

    return render_once


@pytest.fixture(scope="session")
def rendered_root(rendered):
    """``rendered_root(dest, {name: (object, motion)}, n_frames=..., width=..., height=...)``: a folder
    ``dest`` holding a copy of each rendered sequence (the n-th with seed n) under its name."""

    def make(dest: Path, sequences: dict[str, tuple[str, str]], **kwargs) -> Path:
        for n, (name, (obj, motion)) in enumerate(sequences.items()):
            shutil.copytree(rendered(obj, motion, seed=n, **kwargs), Path(dest) / name)
        return Path(dest)

    return make


def sample_sequences() -> list[Path]:
    """The sequence folders in ``sample_data/`` (for parametrising at collection time)."""
    if not SAMPLE_DATA.is_dir():
        return []
    return sorted(p for p in SAMPLE_DATA.iterdir() if (p / "meta.json").is_file())


# -- the in-memory sequence -------------------------------------------------------------------------


def panel_points(width_m: float, height_m: float, *, spacing_m: float = 0.0015) -> np.ndarray:
    """A regular sampling of a flat rectangle in the z = 0 plane, its left edge on x = 0, centred in y.

    Returns
    -------
    points : ndarray, shape (N, 3), metres
    """
    xs = np.arange(0.0, width_m + 1e-12, spacing_m)
    ys = np.arange(-height_m / 2, height_m / 2 + 1e-12, spacing_m)
    gx, gy = np.meshgrid(xs, ys)
    return np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])


def render(parts: list[tuple[np.ndarray, int]], intrinsics: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Z-buffer points in the camera frame into a depth image and an id image.

    Parameters
    ----------
    parts : list of (points (N, 3) metres in the camera frame, id >= 1)

    Returns
    -------
    depth_m : ndarray, shape (H, W), float32, 0 where nothing was hit
    ids : ndarray, shape (H, W), int, the id of the nearest part (0 = nothing)
    """
    pts = np.concatenate([p for p, _ in parts])
    ident = np.concatenate([np.full(len(p), i) for p, i in parts])
    z = pts[:, 2]
    u = np.round(intrinsics.fx * pts[:, 0] / z + intrinsics.cx).astype(int)
    v = np.round(intrinsics.fy * pts[:, 1] / z + intrinsics.cy).astype(int)
    ok = (z > 0) & (u >= 0) & (u < intrinsics.width) & (v >= 0) & (v < intrinsics.height)
    pix, z, ident = (v * intrinsics.width + u)[ok], z[ok], ident[ok]
    order = np.lexsort((z, pix))  # nearest first within each pixel
    first = np.unique(pix[order], return_index=True)[1]
    depth = np.zeros(intrinsics.height * intrinsics.width, np.float32)
    ids = np.zeros(intrinsics.height * intrinsics.width, int)
    depth[pix[order][first]] = z[order][first]
    ids[pix[order][first]] = ident[order][first]
    return depth.reshape(intrinsics.height, intrinsics.width), ids.reshape(
        intrinsics.height, intrinsics.width
    )


def rot_y(angle_rad: float) -> np.ndarray:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


class ArraySequence(Sequence):
    """A sequence whose frames are held in memory (tests only)."""

    def __init__(
        self,
        frames: list[Frame],
        *,
        name: str,
        intrinsics: Intrinsics = INTRINSICS,
        label: str | None = None,
        path: str | Path | None = None,
    ):
        super().__init__(
            name=name,
            path=path or f"/in-memory/{name}",
            intrinsics=intrinsics,
            n_frames=len(frames),
            label=label,
            has_masks=frames[0].mask is not None,
        )
        self._frames = frames

    def load(self, i: int) -> Frame:
        return self._frames[i]


def make_sequence(
    motion: str = "static",
    *,
    n_frames: int = 6,
    step: float | None = None,
    empty_frames: tuple[int, ...] = (),
    masks: bool = True,
    background: bool = True,
    noise_m: float = 0.0,
    seed: int = 0,
) -> ArraySequence:
    """Render a small sequence of two 10 x 15 cm panels side by side, 0.6 m in front of the camera.

    Parameters
    ----------
    motion : ``"static"`` (nothing moves), ``"rigid"`` (both panels move away from the camera by
        ``step`` metres per frame, default 0.01) or ``"hinge"`` (the right panel turns about the
        vertical edge it shares with the left one by ``step`` radians per frame, default 5 degrees;
        the left panel stays still)
    empty_frames : frames rendered without the object (empty mask, background only)
    masks : store the object masks with the frames (the ``mask`` segmenter then works)
    background : a wall 0.9 m away behind the panels, outside the mask
    noise_m : standard deviation of Gaussian depth noise (seeded by ``seed``)
    """
    rng = np.random.default_rng(seed)
    left = panel_points(*PANEL_SIZE_M) - [PANEL_SIZE_M[0], 0.0, 0.0]  # left edge at x = -0.1
    right = panel_points(*PANEL_SIZE_M)  # hinge at x = 0
    hinge = np.array([0.0, 0.0, OBJECT_DEPTH_M])
    frames = []
    for i in range(n_frames):
        if motion == "static":
            parts = [(left + hinge, 1), (right + hinge, 2)]
        elif motion == "rigid":
            shift = np.array([0.0, 0.0, (0.01 if step is None else step) * i])
            parts = [(left + hinge + shift, 1), (right + hinge + shift, 2)]
        elif motion == "hinge":
            angle = (np.radians(5.0) if step is None else step) * i
            parts = [(left + hinge, 1), (right @ rot_y(angle).T + hinge, 2)]
        else:
            raise ValueError(f"unknown motion {motion!r}")
        if i in empty_frames:
            parts = []
        if background:
            wall = panel_points(1.2, 0.9, spacing_m=0.004) - [0.6, 0.0, -BACKGROUND_DEPTH_M]
            parts.append((wall, 9))
        depth, ids = (
            render(parts, INTRINSICS)
            if parts
            else (np.zeros((HEIGHT, WIDTH), np.float32), np.zeros((HEIGHT, WIDTH), int))
        )
        if noise_m:
            depth = np.where(depth > 0, depth + rng.normal(0.0, noise_m, depth.shape), 0).astype(np.float32)
        rgb = np.full((HEIGHT, WIDTH, 3), 90, np.uint8)
        rgb[ids == 1] = (200, 40, 40)
        rgb[ids == 2] = (40, 40, 200)
        mask = ((ids == 1) | (ids == 2)) if masks else None
        frames.append(Frame(i, f"{i:06d}", rgb, depth, mask, time_s=i / 30.0))
    return ArraySequence(
        frames,
        name=f"memory_{motion}",
        label={"static": "static", "rigid": "rigid", "hinge": "articulated"}[motion],
    )


@pytest.fixture(scope="session")
def sequence_factory():
    """:func:`make_sequence`: ``sequence_factory("hinge", n_frames=5)`` renders a small sequence."""
    return make_sequence


# -- the app --------------------------------------------------------------------------------------------
@pytest.fixture(scope="session")
def data_root(tmp_path_factory, rendered_root) -> Path:
    """A data root holding a few small synthetic sequences (what the app opens in its tests)."""
    from app_helpers import N_FRAMES, SEQUENCES

    return rendered_root(tmp_path_factory.mktemp("app_data"), SEQUENCES, n_frames=N_FRAMES)


@pytest.fixture
def app(data_root, tmp_path, monkeypatch):
    """The app, with ``data_root`` as its bundled samples and its only data root."""
    from streamlit.testing.v1 import AppTest

    from app_helpers import APP, TIMEOUT

    monkeypatch.setenv("ARTCLASS_SAMPLE_DATA", str(data_root))
    monkeypatch.delenv("ARTCLASS_DATA_ROOTS", raising=False)
    monkeypatch.setenv("ARTCLASS_UPLOAD_DIR", str(tmp_path / "uploads"))
    return AppTest.from_file(APP, default_timeout=TIMEOUT)


@pytest.fixture(scope="session")
def laptop(registry, data_root):
    """The app's articulated laptop sequence."""
    from artclass_core import open_sequences

    return open_sequences(registry, data_root / "laptop_articulate")[0]


@pytest.fixture(scope="session")
def laptop_run(registry, laptop):
    """The default pipeline's run of :func:`laptop`, with its clouds."""
    from artclass_core import Config, Pipeline

    return Pipeline(registry, Config()).run(laptop, keep_clouds=True)
