"""Generate one synthetic RGB-D sequence with ground truth."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path

import numpy as np

from .hands import HOLDER_KINDS, Holder, colour_box, grasp_pose, holder_pieces, wave_path
from .motion import MOTIONS, Trajectory, make_trajectory
from .objects import OBJECTS, ObjectSpec, part_poses
from .render import (
    HAND,
    NOISE_LEVELS,
    CleanFrame,
    Intrinsics,
    SceneMesh,
    add_sensor_noise,
    object_meshes,
    place_pieces,
    render_clean,
    room_meshes,
)
from .sensors import StructuredLight, add_tof_noise, sensor_header, shift_colour
from .wild import SCENE_STREAM, SceneDraw, check_wild_arguments, draw_scene, plan_wild
from .write import DEPTH_SCALE, prepare_sequence_dir, write_frame, write_json

__all__ = [
    "GENERATOR_VERSION",
    "HANDS",
    "TEXTURES",
    "SynthFrame",
    "SynthSequence",
    "generate_sequence",
    "plan_sequence",
]

GENERATOR_VERSION = "0.4.1"

#: Surface variants: ``textured`` pieces carry their printed pattern, ``plain`` ones are uniform
#: colours with shading only.
TEXTURES = ("textured", "plain")
#: Who handles the object: nobody, a human hand or a two-finger robot gripper.
HANDS = ("none",) + HOLDER_KINDS
#: Largest number of visible points per part and frame written to truth.json.
MAX_PART_POINTS = 256


@dataclass
class SynthFrame:
    """One rendered frame.

    Attributes
    ----------
    index : int
    rgb : ndarray, shape (H, W, 3), uint8, RGB order
    depth_m : ndarray, shape (H, W), float32, metres, 0 = no reading
    mask : ndarray, shape (H, W), bool
        Object pixels (all parts) from the renderer, independent of depth dropouts; a hand
        in front of the object is not in it.
    clean : CleanFrame
        Noise-free rendering (depth, colour, part ids, hand).
    """

    index: int
    rgb: np.ndarray
    depth_m: np.ndarray
    mask: np.ndarray
    clean: CleanFrame

    @property
    def hand(self) -> np.ndarray:
        """Hand or gripper pixels, bool, shape (H, W)."""
        return self.clean.hand

    @property
    def parts(self) -> np.ndarray:
        """Part map, uint8, shape (H, W): 0 = not the object, 1 + part index elsewhere."""
        return np.where(self.clean.part_ids >= 0, self.clean.part_ids + 1, 0).astype(np.uint8)


@dataclass
class SynthSequence:
    """A planned sequence: metadata, ground truth and a frame renderer.

    Attributes
    ----------
    meta : dict
        Contents of ``meta.json``.
    truth : dict
        Contents of ``truth.json`` that do not depend on rendering (the visible points per part
        and frame are added by ``generate_sequence``).
    trajectory : Trajectory
    intrinsics : Intrinsics
        The rendered camera (a randomised sequence's ``meta.json`` states other intrinsics).
    object_name, noise, texture : str
    seed : int
    holders : list of Holder
    scene : SceneDraw or None
        A randomised sequence's draw (sensor, camera, lighting, ...); None for the fixed presets.
    props : list of SceneMesh
        Things in the scene that are not the object (a stand it is lifted from), world frame.
    """

    meta: dict
    truth: dict
    trajectory: Trajectory
    intrinsics: Intrinsics
    object_name: str
    noise: str
    seed: int
    texture: str = "textured"
    holders: list = field(default_factory=list)
    scene: SceneDraw | None = None
    props: list = field(default_factory=list)

    @property
    def n_frames(self) -> int:
        return len(self.trajectory.T_world_from_object)

    @property
    def spec(self) -> ObjectSpec:
        return OBJECTS[self.object_name]

    def joint_positions(self, index: int) -> np.ndarray | None:
        """Positions of every joint in frame ``index``, shape (J,), or None (rigid object)."""
        q = self.trajectory.joint_positions
        return None if q is None else q[index]

    def T_camera_from_parts(self, index: int) -> list[np.ndarray]:
        """``camera_from_part`` of every part in frame ``index``, each shape (4, 4)."""
        T_co = self.trajectory.T_camera_from_object[index]
        return [T_co @ T for T in part_poses(self.spec, self.joint_positions(index))]

    def meshes(self, index: int) -> list[SceneMesh]:
        """Room, object and holders of frame ``index``, in the world frame."""
        traj = self.trajectory
        meshes = object_meshes(self.spec, self.joint_positions(index), traj.T_world_from_object[index])
        if self.texture == "plain":
            for m in meshes:
                m.piece = replace(m.piece, pattern="plain")
        if self.scene is not None and self.scene.albedo_scale != 1.0:
            k = self.scene.albedo_scale
            for m in meshes:
                m.piece = replace(
                    m.piece,
                    colour=tuple(k * c for c in m.piece.colour),
                    colour2=tuple(k * c for c in m.piece.colour2),
                )
        for h in self.holders:
            meshes += place_pieces(h.pieces, h.T_world_from_holder[index], HAND)
            if h.arm_pieces:
                meshes += place_pieces(
                    h.arm_pieces, h.T_world_from_holder[index] @ h.T_holder_from_arm[index], HAND
                )
        return room_meshes() + meshes + self.props

    @cached_property
    def _disparity_bias_px(self) -> np.ndarray | None:
        sensor = None if self.scene is None else self.scene.sensor
        return sensor.disparity_bias_px(self.intrinsics) if isinstance(sensor, StructuredLight) else None

    def render(self, index: int) -> SynthFrame:
        """Render frame ``index`` (noise drawn from a generator seeded by (seed, 1, index))."""
        rng = np.random.default_rng([self.seed, 1, index])
        T_cw = self.trajectory.T_camera_from_world[index]
        if self.scene is None:
            clean = render_clean(self.meshes(index), T_camera_from_world=T_cw, intrinsics=self.intrinsics)
            depth_m, rgb = add_sensor_noise(clean, noise=NOISE_LEVELS[self.noise], rng=rng)
            return SynthFrame(index, rgb, depth_m, clean.mask, clean)
        sc = self.scene
        structured = isinstance(sc.sensor, StructuredLight)
        clean = render_clean(
            self.meshes(index),
            T_camera_from_world=T_cw,
            intrinsics=self.intrinsics,
            projector_baseline_m=sc.sensor.level.baseline_m if structured else 0.0,
            ambient=sc.ambient,
            light_dir_camera=sc.light_dir_camera,
        )
        seen = replace(clean, rgb=shift_colour(clean.rgb, sc.camera.colour_offset_px))
        if structured:
            depth_m, rgb = add_sensor_noise(
                seen, noise=sc.sensor.level, rng=rng, disparity_bias_px=self._disparity_bias_px
            )
        else:
            depth_m, rgb = add_tof_noise(seen, sensor=sc.sensor, fx_px=self.intrinsics.fx_px, rng=rng)
        return SynthFrame(index, rgb, depth_m, clean.mask, clean)

    def part_visibility(self, frame: SynthFrame) -> dict:
        """How much of the moving part the camera sees in ``frame``: its share of the object's pixels,
        and how far from the joint axis (m) its visible points reach (90th percentile; 0 when unseen).
        A revolute part turned by dq moves its visible points by up to 2 r sin(dq / 2)."""
        part = frame.clean.part_ids == 1
        seen = int(np.count_nonzero(frame.clean.mask))
        joint = self.spec.joint
        reach = 0.0
        if part.any() and joint is not None:
            v, u = np.nonzero(part)
            z = frame.clean.depth_m[v, u].astype(float)
            K = self.intrinsics
            cam = np.stack([(u - K.cx_px) * z / K.fx_px, (v - K.cy_px) * z / K.fy_px, z, np.ones_like(z)])
            obj = (np.linalg.inv(self.trajectory.T_camera_from_object[frame.index]) @ cam)[:3].T
            off = obj - np.asarray(joint.origin_m)
            axis = np.asarray(joint.axis, float)
            reach = float(np.percentile(np.linalg.norm(off - np.outer(off @ axis, axis), axis=1), 90))
        return {"share": round(int(part.sum()) / max(seen, 1), 4), "axis_distance_m": round(reach, 4)}

    def part_samples(self, frame: SynthFrame) -> tuple[list[int], list[list]]:
        """What the sensor sees of each part in ``frame``.

        Returns
        -------
        valid_px : list of int
            Per part, its pixels with a depth reading.
        points_m : list of list of [x, y, z]
            Per part, at most ``MAX_PART_POINTS`` of those pixels, evenly spread over them in
            row-major order, as exact surface points in the part's own frame (metres, rounded to
            0.1 mm).
        """
        K = self.intrinsics
        valid = frame.depth_m > 0
        counts, samples = [], []
        for k, T_cp in enumerate(self.T_camera_from_parts(frame.index)):
            v, u = np.nonzero((frame.clean.part_ids == k) & valid)
            counts.append(int(len(v)))
            if len(v) > MAX_PART_POINTS:
                pick = np.rint(np.linspace(0, len(v) - 1, MAX_PART_POINTS)).astype(int)
                v, u = v[pick], u[pick]
            z = frame.clean.depth_m[v, u].astype(float)
            cam = np.column_stack([(u - K.cx_px) * z / K.fx_px, (v - K.cy_px) * z / K.fy_px, z])
            T_pc = np.linalg.inv(T_cp)
            local = cam @ T_pc[:3, :3].T + T_pc[:3, 3]
            samples.append([[round(float(x), 4) for x in p] for p in local])
        return counts, samples

    def frames(self) -> Iterator[SynthFrame]:
        """Render all frames in order."""
        for i in range(self.n_frames):
            yield self.render(i)


def _nested(T: np.ndarray) -> list:
    return [[round(float(x), 10) for x in row] for row in T]


def _floats(v, digits: int = 10) -> list[float]:
    return [round(float(x), digits) for x in np.asarray(v).ravel()]


def _joint_truth(spec: ObjectSpec, traj: Trajectory) -> list[dict]:
    """Per joint: its type, parts, limits and, per frame, its state and its axis in the camera frame
    of frame 0."""
    T_c0w = traj.T_camera_from_world[0]
    out = []
    for k, joint in enumerate(spec.joints):
        origins, directions = [], []
        for f in range(len(traj.T_world_from_object)):
            T = T_c0w @ traj.T_world_from_object[f] @ part_poses(spec, traj.joint_positions[f])[joint.parent]
            origins.append(_floats(T[:3, :3] @ np.asarray(joint.origin_m) + T[:3, 3]))
            directions.append(_floats(T[:3, :3] @ np.asarray(joint.axis, float)))
        out.append(
            {
                "type": joint.joint_type,
                "parent": joint.parent,
                "child": k + 1,
                "limits": _floats(joint.limits),
                "origin_object_m": _floats(joint.origin_m),
                "axis_object": _floats(joint.axis),
                "state": _floats(traj.joint_positions[:, k]),
                "origin_camera0_m": origins,
                "axis_camera0": directions,
            }
        )
    return out


def _plan_holders(
    spec: ObjectSpec, motion: str, hand: str, traj: Trajectory, rng: np.random.Generator
) -> list[Holder]:
    """Holders of a sequence: on the moving part when a joint moves, on the base when the object
    is carried, in front of the object (not touching it) when it is static."""
    if hand == "none":
        return []
    m = MOTIONS[motion]
    # A joint is moved by its free end: the last part of the chain (a lid, a lamp's head).
    holds = ([len(spec.parts) - 1] if m.moves_joint else []) + ([0] if m.moves_object else [])
    n = len(traj.T_world_from_object)
    q = traj.joint_positions
    out = []
    for part in holds:
        T_ph = grasp_pose(spec, part, None if q is None else q[0], rng)
        poses = np.stack(
            [
                traj.T_world_from_object[f] @ part_poses(spec, None if q is None else q[f])[part] @ T_ph
                for f in range(n)
            ]
        )
        out.append(Holder(hand, holder_pieces(hand, rng), poses, part))
    if not holds:
        T_wc = np.linalg.inv(traj.T_camera_from_world[0])
        pts = np.concatenate([p.vertices_m for part in spec.parts for p in part.pieces])
        centre_obj = 0.5 * (pts.min(0) + pts.max(0))
        centre = traj.T_world_from_object[0][:3, :3] @ centre_obj + traj.T_world_from_object[0][:3, 3]
        radius = 0.5 * float(np.linalg.norm(pts.max(0) - pts.min(0)))
        poses = wave_path(centre, T_wc[:3, 3], T_wc[:3, 0], n, rng, clearance_m=radius + 0.12)
        out.append(Holder(hand, holder_pieces(hand, rng), poses, None))
    return out


def plan_sequence(
    *,
    object_name: str,
    motion: str,
    noise: str,
    n_frames: int,
    seed: int,
    width: int = 640,
    height: int = 480,
    texture: str = "textured",
    hand: str = "none",
    wild: bool = False,
) -> SynthSequence:
    """Draw the trajectory and ground truth of a sequence without rendering it.

    Parameters are those of ``generate_sequence``.

    Returns
    -------
    SynthSequence
        Call ``.frames()`` or ``.render(i)`` to render.
    """
    if object_name not in OBJECTS:
        raise ValueError(f"object_name={object_name!r} is not one of {sorted(OBJECTS)}")
    if motion not in MOTIONS:
        raise ValueError(f"motion={motion!r} is not one of {sorted(MOTIONS)}")
    if wild:
        check_wild_arguments(noise=noise, hand=hand, texture=texture, hands=HANDS, textures=TEXTURES)
    else:
        if noise not in NOISE_LEVELS:
            raise ValueError(f"noise={noise!r} is not one of {sorted(NOISE_LEVELS)}")
        if texture not in TEXTURES:
            raise ValueError(f"texture={texture!r} is not one of {TEXTURES}")
        if hand not in HANDS:
            raise ValueError(f"hand={hand!r} is not one of {HANDS}")
    if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0:
        raise ValueError(f"seed={seed!r} must be a non-negative integer")
    if not isinstance(n_frames, (int, np.integer)) or n_frames < 2:
        raise ValueError(f"n_frames={n_frames!r} must be an integer >= 2")
    spec = OBJECTS[object_name]
    m = MOTIONS[motion]
    if m.needs_joint and spec.joint is None:
        raise ValueError(
            f"motion={motion!r} needs an articulated object; {object_name!r} is rigid "
            f"(articulated: {sorted(k for k, v in OBJECTS.items() if v.joint is not None)})"
        )
    if m.needs_tag and m.needs_tag not in spec.tags:
        raise ValueError(
            f"motion={motion!r} needs a {m.needs_tag} object; {object_name!r} is not one "
            f"({sorted(k for k, v in OBJECTS.items() if m.needs_tag in v.tags)} are)"
        )
    seed, n = int(seed), int(n_frames)
    scene = None
    props: list = []
    if wild:
        scene = draw_scene(
            spec=spec,
            motion=motion,
            n_frames=n,
            width=int(width),
            height=int(height),
            rng=np.random.default_rng([seed, SCENE_STREAM]),
            noise=noise,
            hand=hand,
            texture=texture,
        )
        drawn = plan_wild(spec, motion, n, seed, scene)
        intr, stated = scene.camera.rendered, scene.camera.stated
        traj, holders, props = drawn.trajectory, drawn.holders, drawn.props
        noise, texture, hand = scene.sensor.kind, scene.texture, scene.holder_kind
        boxes = drawn.gripper_hsv
        sensor = scene.sensor.record(intr)
    else:
        intr = stated = Intrinsics.for_resolution(int(width), int(height))
        traj = make_trajectory(spec, motion, n_frames=n, rng=np.random.default_rng([seed, 0]))
        holders = _plan_holders(spec, motion, hand, traj, np.random.default_rng([seed, 3]))
        level = NOISE_LEVELS[noise]
        # the rig knows its grippers' colours, as a robot's owner would measure them once: a box a colour
        boxes = [colour_box(h.pieces, rgb_sigma=level.rgb_sigma) for h in holders if h.kind == "gripper"]
        sensor = sensor_header(
            fx_px=intr.fx_px,
            axial_a_m=level.axial_a_m,
            axial_b_per_m=level.axial_b_per_m,
            depth_step_m=1.0 / DEPTH_SCALE,
        )

    T_co = traj.T_camera_from_object
    meta = {
        "fx": stated.fx_px,
        "fy": stated.fy_px,
        "cx": stated.cx_px,
        "cy": stated.cy_px,
        "depth_scale": DEPTH_SCALE,
        "label": m.label,
        "object": object_name,
        "motion": motion,
        "noise": noise,
        "seed": seed,
        "generator": f"artclass synth {GENERATOR_VERSION}",
        "joint_type": spec.joint_type,
        "texture": texture,
        "hand": hand,
    }
    if boxes:
        meta["gripper_hsv"] = "; ".join(dict.fromkeys(boxes))
    q = traj.joint_positions
    truth = {
        "joint_type": spec.joint_type,
        "joint_positions": [None] * n if q is None else _floats(q[:, 0]),
        "object_poses": [_nested(T) for T in T_co],
        # Extras beyond the native format: enough to score axis estimates and part motion.
        "joint_axis_object": None
        if spec.joint is None
        else {
            "origin_m": [float(x) for x in spec.joint.origin_m],
            "direction": [float(x) for x in spec.joint.axis],
        },
        "moving_part_poses": None
        if q is None
        else [_nested(T_co[i] @ part_poses(spec, q[i])[1]) for i in range(n)],
        "part_names": [p.name for p in spec.parts],
        "parts": [
            {
                "name": p.name,
                "parent": -1 if k == 0 else spec.joints[k - 1].parent,
                "joint": None if k == 0 else k - 1,
            }
            for k, p in enumerate(spec.parts)
        ],
        "joints": _joint_truth(spec, traj),
        "part_poses": [
            [_nested(T) for T in [T_co[i] @ P for P in part_poses(spec, None if q is None else q[i])]]
            for i in range(n)
        ],
        "sensor": sensor,
        "holders": [
            {"kind": h.kind, "holds": None if h.holds is None else spec.parts[h.holds].name} for h in holders
        ],
    }
    if scene is not None:
        for entry, h in zip(truth["holders"], holders):
            entry.update(role=h.role, style=h.style)
        truth.update(
            camera=scene.camera.record(),
            scene=scene.record(),
            motion_style=scene.motion_style,
            stand=None
            if scene.stand is None
            else dict(
                scene.stand, camera0_from_stand=_nested(traj.T_camera_from_world[0] @ _stand_pose(props))
            ),
        )
    return SynthSequence(meta, truth, traj, intr, object_name, noise, seed, texture, holders, scene, props)


def _stand_pose(props: list) -> np.ndarray:
    """``T_world_from_stand`` of the props placed by ``plan_wild`` (their texture frame)."""
    return np.linalg.inv(props[0].T_local_from_world)


def generate_sequence(
    out_dir: str | Path,
    *,
    object_name: str,
    motion: str,
    noise: str,
    n_frames: int,
    seed: int,
    width: int = 640,
    height: int = 480,
    texture: str = "textured",
    hand: str = "none",
    wild: bool = False,
    overwrite: bool = False,
) -> Path:
    """Render a synthetic RGB-D sequence and write it in the native folder format.

    Parameters
    ----------
    out_dir : str or Path
        Sequence folder to create; a non-empty folder is refused unless ``overwrite``.
    object_name : str
        A key of ``OBJECTS``.
    motion : {"articulate", "carry_articulate", "carry", "static", "spin", "slide", "lift"}
        The first two need an articulated object, ``spin`` a body of revolution, ``slide`` a flat
        object; ``lift`` starts the object on a stand that stays.
    noise : {"none", "low", "high"}
        Sensor noise level (see ``NOISE_LEVELS``); see ``wild`` for randomised sensors.
    n_frames : int
        Number of frames, >= 2.
    seed : int
        Non-negative; the same seed gives byte-identical files.
    width, height : int
        Image size in pixels; 4:3 sizes are a Kinect-like camera (640x480: fx = fy = 570),
        848x480 a RealSense-like one (fx = fy = 615); see ``Intrinsics.for_resolution``.
    texture : {"textured", "plain"}
        ``plain`` object surfaces are uniform colours, with shading only.
    hand : {"none", "hand", "gripper"}
        Who handles the object: a hand or gripper holds the moving part while a joint moves
        and the base while the object is carried, and moves in front of a static object
        without touching it. It hides the object and is never in its mask.
    wild : bool
        Randomise everything else from the seed (see ``artclass_plugins.synth.wild``): the sensor
        (``noise`` is then ``"drawn"``, ``"structured_light"`` or ``"time_of_flight"``), the camera
        and the intrinsics stated for it, the colour-depth offset, the lighting, the speeds, and the
        holders (``hand`` and ``texture`` may then be ``"drawn"`` too): one or two hands with any
        sleeve, glove or skin, or grippers of any colour, grasping, resting or passing.
    overwrite : bool
        Replace the sequence files in an existing non-empty ``out_dir``.

    Returns
    -------
    Path
        The sequence folder.

    Raises
    ------
    FileExistsError
        ``out_dir`` is not empty and ``overwrite`` is False.
    ValueError
        Unknown object, motion or noise level, or a motion that needs a joint on a rigid object.
    """
    seq = plan_sequence(
        object_name=object_name,
        motion=motion,
        noise=noise,
        n_frames=n_frames,
        seed=seed,
        width=width,
        height=height,
        texture=texture,
        hand=hand,
        wild=wild,
    )
    out = prepare_sequence_dir(out_dir, overwrite=overwrite)
    visibility, valid_px, points = [], [], []
    for frame in seq.frames():
        write_frame(
            out,
            frame.index,
            rgb=frame.rgb,
            depth_m=frame.depth_m,
            mask=frame.mask,
            hand=frame.hand,
            parts=frame.parts,
        )
        visibility.append(seq.part_visibility(frame))
        counts, samples = seq.part_samples(frame)
        valid_px.append(counts)
        points.append(samples)
    truth = dict(seq.truth)
    if seq.truth["joint_positions"][0] is not None:
        truth["part_visibility"] = visibility
    truth["part_valid_px"] = valid_px
    truth["part_points_m"] = points
    write_json(out / "truth.json", truth)
    write_json(out / "meta.json", seq.meta)
    return out
