"""Forearms found by their shape: a cylinder that enters the picture, held above the table."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from artclass_core import Frame, Intrinsics, Sequence
from artclass_plugins.segmenters.depth_threshold import DepthThresholdSegmenter
from artclass_plugins.segmenters.limbs import limbs
from artclass_plugins.segmenters.selection import mask_iou
from artclass_plugins.segmenters.support import border_band

K = Intrinsics(fx=525.0, fy=525.0, cx=319.5, cy=239.5, width=640, height=480)
TABLE_Y = 0.3  # the table's plane, metres below the camera (y points down)


def _cylinder(start, end, radius: float) -> o3d.geometry.TriangleMesh:
    start, end = np.asarray(start, float), np.asarray(end, float)
    axis = end - start
    mesh = o3d.geometry.TriangleMesh.create_cylinder(
        radius=radius, height=np.linalg.norm(axis), resolution=40
    )
    z = axis / np.linalg.norm(axis)
    x = np.cross(z, [0.0, 0.0, 1.0] if abs(z[2]) < 0.9 else [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    rotation = np.column_stack([x, np.cross(z, x), z])
    return mesh.rotate(rotation, center=(0, 0, 0)).translate((start + end) / 2)


def _box(low, high) -> o3d.geometry.TriangleMesh:
    size = np.subtract(high, low)
    return o3d.geometry.TriangleMesh.create_box(*size).translate(low)


def _render(*meshes) -> tuple[np.ndarray, np.ndarray]:
    """Depth (H, W), metres, of the table and ``meshes``; and which mesh each pixel shows (-1: the
    table, or nothing)."""
    scene = o3d.t.geometry.RaycastingScene()
    ids = [scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(m)) for m in meshes]
    table = scene.add_triangles(
        o3d.t.geometry.TriangleMesh.from_legacy(_box((-2, TABLE_Y, 0.2), (2, TABLE_Y + 0.02, 3)))
    )
    rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(
        o3d.core.Tensor(np.array([[K.fx, 0, K.cx], [0, K.fy, K.cy], [0, 0, 1.0]])),
        o3d.core.Tensor(np.eye(4)),
        K.width,
        K.height,
    )
    hit = scene.cast_rays(rays)
    depth = (hit["t_hit"].numpy() * rays.numpy()[..., 5]).astype(np.float32)
    which = hit["geometry_ids"].numpy().astype(np.int64)
    depth[~np.isfinite(depth)] = 0
    shows = np.full(depth.shape, -1)
    for k, i in enumerate(ids):
        shows[which == i] = k
    shows[which == table] = -1
    return depth, shows


def _limbs(depth: np.ndarray, shows: np.ndarray) -> np.ndarray:
    foreground = shows >= 0
    v, u = np.nonzero(foreground)
    height = TABLE_Y - K.points(u, v, depth[v, u].astype(float))[:, 1]
    contact = np.zeros_like(foreground)
    contact[v, u] = height < 0.01
    return limbs(foreground, depth, K, contact=contact)


ARM = ((-0.75, -0.25, 0.7), (-0.02, 0.11, 0.8))  # from beyond the picture's left edge to the box's top
BOX = ((-0.05, 0.15, 0.75), (0.05, TABLE_Y, 0.85))  # standing on the table


def test_a_forearm_resting_its_hand_on_a_box_is_found_and_the_box_kept():
    depth, shows = _render(_cylinder(*ARM, radius=0.04), _box(*BOX))
    found = _limbs(depth, shows)
    arm, box = shows == 0, shows == 1
    assert (arm & (depth > 0)).any() and (arm[:, 0]).any()  # the arm enters at the left edge
    assert np.count_nonzero(found & arm) >= 0.9 * np.count_nonzero(arm)
    assert np.count_nonzero(found & box) <= 0.2 * np.count_nonzero(box)


def test_two_forearms_on_one_box_are_each_found_where_it_enters():
    """The box joins the two arms into one region, which enters the picture at two places."""
    other = ((0.75, -0.25, 0.7), (0.02, 0.11, 0.8))  # the mirror image, from beyond the right edge
    depth, shows = _render(_cylinder(*ARM, radius=0.04), _cylinder(*other, radius=0.04), _box(*BOX))
    found = _limbs(depth, shows)
    for arm in (shows == 0, shows == 1):
        assert np.count_nonzero(found & arm) >= 0.9 * np.count_nonzero(arm)
    assert np.count_nonzero(found & (shows == 2)) <= 0.3 * np.count_nonzero(shows == 2)


@pytest.mark.parametrize("noise_m", [0.004, 0.007, 0.01])
def test_a_slim_forearm_read_with_time_of_flight_noise_is_found(noise_m):
    """A slim forearm (5 cm across) read as a time-of-flight camera reads a dark sleeve: millimetres
    to a centimetre of noise, a fifth of the readings missing (off the picture's border, where it
    enters). Normals from single readings a centimetre apart would tilt by tens of degrees and hide
    the axis; from readings averaged over a centimetre they do not."""
    depth, shows = _render(_cylinder(*ARM, radius=0.026), _box(*BOX))
    arm = shows == 0
    for seed in range(10):
        rng = np.random.default_rng(seed)
        noisy = np.where(depth > 0, depth + rng.normal(0, noise_m, depth.shape), 0).astype(np.float32)
        noisy[(rng.random(depth.shape) < 0.2) & ~border_band(depth.shape)] = 0
        found = _limbs(noisy, np.where(noisy > 0, shows, -1))
        assert np.count_nonzero(found & arm) >= 0.9 * np.count_nonzero(arm & (noisy > 0)), seed


def _unread_sleeve(share: float, start=ARM[0]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The arm from ``start``, its first ``share`` a sleeve without readings (black under time of
    flight, or nearer than the sensor's range), resting its hand on the box: depth, which mesh each
    pixel shows (the sleeve: -1), and the forearm's pixels."""
    start, end = np.asarray(start), np.asarray(ARM[1])
    cuff = start + share * (end - start)
    wall = _box((-3, -3, 2.5), (3, 3, 2.6))  # every pixel has a reading but the sleeve's
    depth, shows = _render(
        _cylinder(start, cuff, radius=0.045), _cylinder(cuff, end, radius=0.04), _box(*BOX), wall
    )
    depth[shows == 0] = 0
    shows[(shows == 0) | (shows == 3)] = -1
    return depth, shows, shows == 1


def test_a_forearm_comes_into_view_where_the_readings_of_its_sleeve_start():
    depth, shows, arm = _unread_sleeve(0.6)
    assert not arm[:, :20].any()  # the readings start well inside the picture
    found = _limbs(depth, shows)
    assert np.count_nonzero(found & arm) >= 0.9 * np.count_nonzero(arm)
    assert np.count_nonzero(found & (shows == 2)) <= 0.2 * np.count_nonzero(shows == 2)


def test_a_gap_in_the_readings_that_does_not_reach_the_border_is_no_way_in():
    depth, shows, arm = _unread_sleeve(0.3, start=(-0.35, -0.1, 0.7))
    assert not (depth[:, :20] == 0).any() and (depth == 0).sum() > 2000
    assert not _limbs(depth, shows).any()


def test_a_slim_forearm_coming_from_far_away_is_as_wide_as_it_is_where_it_enters():
    """A slim forearm (3.4 cm across) enters the picture half again as far as the box it reaches:
    its width where it enters is measured at its own depth, not at the region's (there it would
    seem too slim for a forearm)."""
    depth, shows = _render(_cylinder((-1.6, 0.0, 1.7), ARM[1], radius=0.017), _box(*BOX))
    arm = shows == 0
    assert arm[:, 0].any() and np.median(depth[:, :3][arm[:, :3]]) > 1.5 * np.median(depth[shows >= 0])
    found = _limbs(depth, shows)
    assert np.count_nonzero(found & arm) >= 0.9 * np.count_nonzero(arm)


def test_a_box_that_enters_the_picture_is_no_forearm():
    depth, shows = _render(_box((-1.0, -0.1, 0.7), (-0.1, 0.2, 1.0)))
    assert (shows == 0)[:, 0].any()
    assert not _limbs(depth, shows).any()


def test_a_cylinder_lying_on_the_table_is_no_forearm():
    lying = _cylinder((-0.9, TABLE_Y - 0.04, 0.9), (0.0, TABLE_Y - 0.04, 0.9), radius=0.04)
    depth, shows = _render(lying)
    assert (shows == 0)[:, 0].any()
    assert not _limbs(depth, shows).any()


def test_a_cylinder_too_thick_for_a_forearm_is_none():
    depth, shows = _render(_cylinder(*ARM, radius=0.09))
    assert (shows == 0)[:, 0].any()
    assert not _limbs(depth, shows).any()


class _Frames(Sequence):
    def __init__(self, frames: list[Frame]):
        super().__init__(name="gloved", path="/in-memory/limbs", intrinsics=K, n_frames=len(frames))
        self._frames = frames

    def load(self, i: int) -> Frame:
        return self._frames[i]


def test_a_gloved_forearm_resting_on_a_still_box_is_no_part_of_it():
    """A forearm in a green glove and sleeve (no skin colour anywhere) rests its end on a still box
    and sways 2 cm from frame to frame: the segmenter's hand mask holds the arm, and the box is
    chosen without it, in every frame."""
    rng = np.random.default_rng(0)
    frames, arms, boxes = [], [], []
    for i in range(5):
        start, end = np.array(ARM[0]), np.array(ARM[1])
        depth, shows = _render(_cylinder(start + [0, 0.02 * (i % 2), 0], end, radius=0.04), _box(*BOX))
        depth = np.where(depth > 0, np.round(depth + rng.normal(0, 0.001, depth.shape), 3), 0)
        rgb = np.empty(depth.shape + (3,))
        rgb[:] = (150, 120, 90)  # a wooden table
        rgb[shows == 0], rgb[shows == 1] = (40, 120, 60), (50, 70, 150)
        rgb = np.clip(rgb + rng.normal(0, 4, rgb.shape), 0, 255).astype(np.uint8)
        frames.append(Frame(i, f"{i:06d}", rgb, depth.astype(np.float32)))
        arms.append(shows == 0)
        boxes.append(shows == 1)
    scene, seg = _Frames(frames), DepthThresholdSegmenter()
    for i in range(len(scene)):
        hand = seg.hand_mask(scene[i], sequence=scene)
        assert np.count_nonzero(hand & arms[i]) >= 0.9 * np.count_nonzero(arms[i]), i
        mask = seg.segment(scene[i], sequence=scene)
        assert np.count_nonzero(mask & arms[i]) <= 0.02 * np.count_nonzero(mask), i
        assert mask_iou(mask, boxes[i]) >= 0.8, i
