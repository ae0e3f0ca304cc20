"""Ray-casting renderer (Open3D ``RaycastingScene``) and a structured-light sensor model.

Conventions
-----------
* World frame: metres, z up, the table top is the plane z = 0, the wall behind
  the object is the plane y = ``WALL_Y_M``.
* Camera frame: OpenCV (x right, y down, z forward). ``T_camera_from_world``
  maps world points into the camera frame (Open3D's "extrinsic").
* Depth images hold z-depth in metres (not ray length); 0 means no reading.
* Pixel (u, v) looks through ``x = (u - cx) / fx``, ``y = (v - cy) / fy``:
  integer pixel coordinates are pixel centres, as in Open3D and OpenCV.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
from scipy import ndimage

from .objects import ObjectSpec, Piece, part_poses
from .objects import box as _box

__all__ = [
    "PROP",
    "CleanFrame",
    "Intrinsics",
    "NOISE_LEVELS",
    "NoiseLevel",
    "SceneMesh",
    "add_sensor_noise",
    "object_meshes",
    "render_clean",
    "room_meshes",
]

#: Reference resolution of the simulated sensor.
REFERENCE_WIDTH_PX = 640
REFERENCE_HEIGHT_PX = 480
#: Focal length at the reference resolution (between Kinect v1's 525 and a RealSense's 615).
REFERENCE_FOCAL_PX = 570.0
#: A RealSense D400's colour camera at 848x480 (its 16:9 mode): focal length, pixels.
REALSENSE_SIZE_PX = (848, 480)
REALSENSE_FOCAL_PX = 615.0
#: Distance between the IR camera and the pattern projector, along camera +x (Kinect v1: 7.5 cm).
PROJECTOR_BASELINE_M = 0.075
#: The wall behind the object.
WALL_Y_M = 0.62
#: ``SceneMesh.part`` of the room, of a hand or gripper, and of a prop that is not the object (a stand
#: the object is lifted from); object parts are 0, 1, ...
ROOM = -1
HAND = -2
PROP = -3
#: Ambient share of the lighting (the rest is a directional light near the camera).
AMBIENT = 0.35
#: Direction the light travels, camera frame (from above left of the camera, into the scene).
LIGHT_DIR_CAMERA = (-0.35, -0.55, -1.0)


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics.

    Attributes
    ----------
    width_px, height_px : int
    fx_px, fy_px, cx_px, cy_px : float
        Focal lengths and principal point, pixels.
    """

    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float

    def __post_init__(self):
        if self.width_px < 8 or self.height_px < 8:
            raise ValueError(f"image size {self.width_px}x{self.height_px} px is too small (need >= 8x8)")

    @classmethod
    def for_resolution(cls, width_px: int = 640, height_px: int = 480) -> Intrinsics:
        """The simulated camera for a ``width_px`` x ``height_px`` image.

        4:3 images are a Kinect-like sensor: 640x480 gives fx = fy = 570, cx = 319.5,
        cy = 239.5, and 320x240 halves the focal length (same field of view). The 848:480
        aspect ratio is a RealSense-like sensor: 848x480 gives fx = fy = 615, cx = 423.5,
        cy = 239.5 (a wider view: 69 x 43 degrees against 58 x 45). Other sizes scale the
        Kinect-like sensor's focal length with the width and the height.
        """
        w, h = int(width_px), int(height_px)
        if w * REALSENSE_SIZE_PX[1] == h * REALSENSE_SIZE_PX[0]:
            fx = fy = REALSENSE_FOCAL_PX * h / REALSENSE_SIZE_PX[1]
        else:
            fx = REFERENCE_FOCAL_PX * w / REFERENCE_WIDTH_PX
            fy = REFERENCE_FOCAL_PX * h / REFERENCE_HEIGHT_PX
        return cls(w, h, fx, fy, (w - 1) / 2.0, (h - 1) / 2.0)

    @property
    def matrix(self) -> np.ndarray:
        """The 3x3 intrinsic matrix K."""
        return np.array([[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class NoiseLevel:
    """Parameters of the simulated structured-light depth sensor and colour camera.

    Axial noise follows Nguyen, Izadi & Lovell (3DIMPVT 2012):
    ``sigma_z(z) = axial_a_m + axial_b_per_m * (z - 0.4 m)**2``.
    """

    name: str
    axial_a_m: float = field(metadata={"help": "axial noise at 0.4 m, metres"})
    axial_b_per_m: float = field(metadata={"help": "growth of axial noise, 1/m"})
    disparity_subpixel: float = field(
        metadata={"help": "disparity quantisation step, pixels of the 570 px reference focal"}
    )
    grazing_start_deg: float = field(metadata={"help": "incidence angle where dropouts begin"})
    grazing_end_deg: float = field(metadata={"help": "incidence angle of full dropout rate"})
    grazing_drop_prob: float = field(metadata={"help": "dropout probability at grazing_end_deg"})
    edge_drop_prob: float = field(metadata={"help": "dropout probability next to depth jumps"})
    lateral_fraction: float = field(metadata={"help": "fraction of edge pixels taking a neighbour's depth"})
    random_drop_fraction: float = field(metadata={"help": "fraction of pixels lost at random"})
    speckle_fraction: float = field(metadata={"help": "fraction of outlier (flying) pixels"})
    projector_shadow: bool = field(metadata={"help": "drop pixels the projector cannot see"})
    rgb_sigma: float = field(metadata={"help": "colour noise std, 8-bit levels"})
    min_range_m: float = 0.3
    max_range_m: float = 4.5
    flying_fraction: float = field(
        default=0.0,
        metadata={
            "help": "fraction of pixels at a depth discontinuity that read a depth between the "
            "foreground and the background (flying pixels)"
        },
    )
    depth_step_m: float = field(
        default=0.0, metadata={"help": "depth quantisation of the delivered depth, metres (0: none)"}
    )
    baseline_m: float = field(
        default=PROJECTOR_BASELINE_M,
        metadata={"help": "projector-camera baseline b of the disparity, metres"},
    )
    focal_px: float = field(
        default=REFERENCE_FOCAL_PX, metadata={"help": "focal length f of the disparity, pixels"}
    )

    def __post_init__(self):
        for name in (
            "grazing_drop_prob",
            "edge_drop_prob",
            "lateral_fraction",
            "random_drop_fraction",
            "speckle_fraction",
            "flying_fraction",
        ):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"NoiseLevel {self.name!r}: {name}={value} is not in [0, 1]")
        for name in ("axial_a_m", "axial_b_per_m", "disparity_subpixel", "rgb_sigma", "depth_step_m"):
            if getattr(self, name) < 0:
                raise ValueError(f"NoiseLevel {self.name!r}: {name}={getattr(self, name)} < 0")
        if not 0 <= self.grazing_start_deg <= self.grazing_end_deg <= 90:
            raise ValueError(
                f"NoiseLevel {self.name!r}: need 0 <= grazing_start_deg "
                f"({self.grazing_start_deg}) <= grazing_end_deg "
                f"({self.grazing_end_deg}) <= 90"
            )
        if self.baseline_m <= 0 or self.focal_px <= 0:
            raise ValueError(
                f"NoiseLevel {self.name!r}: baseline_m={self.baseline_m} and focal_px={self.focal_px} must be > 0"
            )

    def axial_sigma_m(self, depth_m: np.ndarray) -> np.ndarray:
        """Axial noise standard deviation at z-depth ``depth_m``, metres."""
        return self.axial_a_m + self.axial_b_per_m * (np.asarray(depth_m) - 0.4) ** 2


#: Depth unit of the delivered depth (Kinect and RealSense deliver millimetres).
DEPTH_STEP_M = 0.001

#: Sensor noise levels. ``none`` is an ideal sensor (used by tests and ground truth);
#: ``low`` is a good structured-light sensor; ``high`` about 2.5x worse everywhere.
NOISE_LEVELS: dict[str, NoiseLevel] = {
    "none": NoiseLevel(
        "none",
        0.0,
        0.0,
        0.0,
        90.0,
        90.0,
        0.0,
        0.0,
        0.0,
        0.0,
        0.0,
        False,
        0.0,
        min_range_m=0.0,
        max_range_m=math.inf,
    ),
    "low": NoiseLevel(
        "low",
        0.0012,
        0.0019,
        1 / 8,
        72.0,
        82.0,
        0.9,
        0.25,
        0.25,
        0.002,
        2e-4,
        True,
        0.4,
        flying_fraction=0.25,
        depth_step_m=DEPTH_STEP_M,
    ),
    "high": NoiseLevel(
        "high",
        0.003,
        0.0048,
        1 / 4,
        65.0,
        78.0,
        0.95,
        0.55,
        0.5,
        0.01,
        1e-3,
        True,
        2.5,
        flying_fraction=0.5,
        depth_step_m=DEPTH_STEP_M,
    ),
}


@dataclass
class SceneMesh:
    """A triangle mesh placed in the world, with what is needed to colour it.

    Attributes
    ----------
    vertices_m : ndarray, shape (V, 3), metres, world frame
    triangles : ndarray, shape (F, 3), uint32
    part : int
        Object part index (0 base, 1, 2, ... the parts hanging on joints), ``ROOM`` (-1) for the
        room or ``HAND`` (-2) for a hand or gripper.
    piece : Piece
        Colours and texture pattern.
    T_local_from_world : ndarray, shape (4, 4)
        Maps world points into the frame in which the texture is defined.
    """

    vertices_m: np.ndarray
    triangles: np.ndarray
    part: int
    piece: Piece
    T_local_from_world: np.ndarray


def _transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``T`` applied to ``points`` (N, 3); written out (no BLAS call, which is slow for 3x3)."""
    p = np.asarray(points)
    out = np.empty(p.shape, dtype=np.result_type(p.dtype, np.float32))
    for r in range(3):
        out[:, r] = p[:, 0] * T[r, 0] + p[:, 1] * T[r, 1] + p[:, 2] * T[r, 2] + T[r, 3]
    return out


def _dot3(a: np.ndarray, v) -> np.ndarray:
    """Dot product of the last axis of ``a`` (..., 3) with the 3-vector ``v``."""
    return a[..., 0] * v[0] + a[..., 1] * v[1] + a[..., 2] * v[2]


def _invert(T: np.ndarray) -> np.ndarray:
    Ti = np.eye(4)
    Ti[:3, :3] = T[:3, :3].T
    Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return Ti


def place_pieces(pieces, T_world_from_local: np.ndarray, part: int) -> list[SceneMesh]:
    """``pieces`` (defined in a local frame) placed in the world by ``T_world_from_local``."""
    T_local_world = _invert(T_world_from_local)
    return [
        SceneMesh(_transform(T_world_from_local, p.vertices_m), p.triangles, part, p, T_local_world)
        for p in pieces
    ]


def object_meshes(spec: ObjectSpec, q, T_world_from_object: np.ndarray) -> list[SceneMesh]:
    """The pieces of ``spec`` at joint positions ``q`` (see ``part_poses``) placed by
    ``T_world_from_object``."""
    out = []
    for part_index, (T_obj_part, part) in enumerate(zip(part_poses(spec, q), spec.parts)):
        out += place_pieces(part.pieces, T_world_from_object @ T_obj_part, part_index)
    return out


def room_meshes() -> list[SceneMesh]:
    """Table (top at z = 0), back wall and floor, world frame."""
    pieces = [
        _box(
            (1.8, 1.45, 0.04),
            (0.0, WALL_Y_M - 0.725, -0.02),
            (0.58, 0.42, 0.26),
            pattern="stripes",
            cell_m=0.025,
            contrast=0.12,
        ),
        _box(
            (6.0, 0.02, 3.0),
            (0.0, WALL_Y_M + 0.01, 0.75),
            (0.80, 0.80, 0.76),
            pattern="blobs",
            cell_m=0.12,
            contrast=0.10,
        ),
        _box(
            (6.0, 6.0, 0.02),
            (0.0, 0.0, -0.76),
            (0.45, 0.45, 0.50),
            pattern="checker",
            cell_m=0.3,
            contrast=0.2,
        ),
    ]
    return [SceneMesh(p.vertices_m, p.triangles, ROOM, p, np.eye(4)) for p in pieces]


def _pattern(points_local: np.ndarray, pattern: str, cell_m: float) -> np.ndarray:
    """Texture weight in [0, 1] of the second colour, shape (N,)."""
    if pattern == "plain" or len(points_local) == 0:
        return np.zeros(len(points_local))
    p = points_local / cell_m
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    if pattern == "checker":
        k = np.floor(x + 0.137) + np.floor(y + 0.311) + np.floor(z + 0.529)
        return np.mod(k, 2.0)
    if pattern == "stripes":
        return np.mod(np.floor(x + 0.6 * y + 0.35 * z + 0.137), 2.0)
    if pattern == "blobs":
        v = np.sin(2.1 * x + 0.3) * np.sin(1.7 * y + 1.1) * np.sin(2.9 * z + 0.7)
        v = v + 0.5 * np.sin(1.3 * (x + y - z) + 0.2)
        return (v > 0.1).astype(float)
    raise ValueError(f"unknown pattern {pattern!r}")


@dataclass
class CleanFrame:
    """A noise-free rendering.

    Attributes
    ----------
    depth_m : ndarray, shape (H, W), float32, metres
        z-depth; 0 where the ray hit nothing.
    rgb : ndarray, shape (H, W, 3), float32 in [0, 1]
        Lambertian-shaded, textured colour, RGB order.
    part_ids : ndarray, shape (H, W), int8
        Object part seen in each pixel (0 base, 1, 2, ... the other parts), ``ROOM`` (-1) where
        the room or nothing is seen, ``HAND`` (-2) where a hand or gripper is.
    cos_incidence : ndarray, shape (H, W), float32
        |cos| of the angle between the viewing ray and the surface normal.
    shadowed : ndarray, shape (H, W), bool
        Surface points the pattern projector cannot see.
    albedo : ndarray, shape (H, W), float32 in [0, 1], or None
        Luminance of the unshaded surface colour (its reflectance; 0 where nothing is hit).
    """

    depth_m: np.ndarray
    rgb: np.ndarray
    part_ids: np.ndarray
    cos_incidence: np.ndarray
    shadowed: np.ndarray
    albedo: np.ndarray | None = None

    @property
    def mask(self) -> np.ndarray:
        """Object pixels (all parts), bool, shape (H, W); a hand in front of the object is not in it."""
        return self.part_ids >= 0

    @property
    def hand(self) -> np.ndarray:
        """Hand or gripper pixels, bool, shape (H, W)."""
        return self.part_ids == HAND


def render_clean(
    meshes: list[SceneMesh],
    *,
    T_camera_from_world: np.ndarray,
    intrinsics: Intrinsics,
    projector_baseline_m: float = PROJECTOR_BASELINE_M,
    ambient: float = AMBIENT,
    light_dir_camera=LIGHT_DIR_CAMERA,
) -> CleanFrame:
    """Ray-cast ``meshes`` through a pinhole camera.

    Parameters
    ----------
    meshes : list of SceneMesh
        World-frame geometry.
    T_camera_from_world : ndarray, shape (4, 4)
    intrinsics : Intrinsics
    projector_baseline_m : float
        Projector offset along camera +x used for the shadow map; 0 disables it.
    ambient : float
        Ambient share of the lighting (the rest is a directional light near the camera).
    light_dir_camera : array_like, shape (3,)
        Direction the directional light travels, camera frame (need not be unit length).

    Returns
    -------
    CleanFrame
    """
    scene = o3d.t.geometry.RaycastingScene()
    mesh_of_gid: dict[int, SceneMesh] = {}
    for m in meshes:
        gid = scene.add_triangles(
            o3d.core.Tensor(np.ascontiguousarray(m.vertices_m, dtype=np.float32)),
            o3d.core.Tensor(np.ascontiguousarray(m.triangles, dtype=np.uint32)),
        )
        mesh_of_gid[int(gid)] = m
    no_hit = max(mesh_of_gid, default=-1) + 1
    part_of = np.full(no_hit + 1, ROOM, dtype=np.int8)
    for gid, m in mesh_of_gid.items():
        part_of[gid] = m.part

    h, w = intrinsics.height_px, intrinsics.width_px
    # create_rays_pinhole shoots pixel (u, v) through (u + 0.5, v + 0.5) (pixel corners at
    # integers); shift the principal point so that integer coordinates are pixel centres.
    K_o3d = intrinsics.matrix
    K_o3d[0, 2] += 0.5
    K_o3d[1, 2] += 0.5
    rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(
        o3d.core.Tensor(K_o3d),
        o3d.core.Tensor(np.asarray(T_camera_from_world, dtype=np.float64)),
        w,
        h,
    )
    ans = scene.cast_rays(rays)
    rays_np = rays.numpy()
    t_hit = ans["t_hit"].numpy()
    gids = ans["geometry_ids"].numpy()
    normals = ans["primitive_normals"].numpy()

    origin = rays_np[..., :3]
    dirs = rays_np[..., 3:]
    hit = np.isfinite(t_hit)
    # t_hit is in units of the (unnormalised) ray direction: z-depth = t * (R d)_z.
    R_cw = np.asarray(T_camera_from_world)[:3, :3]
    dir_z = _dot3(dirs, R_cw[2].astype(np.float32))
    depth = np.where(hit, t_hit * dir_z, 0.0).astype(np.float32)

    gsafe = np.where(hit, gids, no_hit).astype(np.int64)
    part_ids = part_of[gsafe]

    dir_len = np.sqrt(_dot3(dirs, dirs.transpose(2, 0, 1)))
    ndotd = _dot3(normals, dirs.transpose(2, 0, 1)) / dir_len
    cos_inc = np.where(hit, np.abs(ndotd), 0.0).astype(np.float32)
    facing = -np.sign(ndotd)  # flips normals to face the camera

    R_wc = R_cw.T
    light_dir = R_wc @ (np.asarray(light_dir_camera, float) / np.linalg.norm(light_dir_camera))
    diffuse = np.clip(facing * _dot3(normals, light_dir.astype(np.float32)), 0.0, 1.0)
    shade = ambient + (1.0 - ambient) * diffuse

    points = origin + dirs * np.where(hit, t_hit, np.float32(0.0))[..., None]
    # Colour: group the hit pixels by geometry once, then texture each group in its own frame.
    flat_hit = np.flatnonzero(hit)
    flat_gid = gids.reshape(-1)[flat_hit]
    order = np.argsort(flat_gid, kind="stable")
    pix = flat_hit[order]
    gid_sorted = flat_gid[order]
    starts = np.flatnonzero(np.r_[True, gid_sorted[1:] != gid_sorted[:-1]])
    ends = np.r_[starts[1:], len(pix)]
    pts_flat = points.reshape(-1, 3)
    base = np.zeros((h * w, 3), dtype=np.float32)
    for a, b in zip(starts, ends):
        m = mesh_of_gid[int(gid_sorted[a])]
        sel = pix[a:b]
        local = _transform(m.T_local_from_world, pts_flat[sel])
        wgt = _pattern(local, m.piece.pattern, m.piece.cell_m)[:, None]
        base[sel] = np.asarray(m.piece.colour) * (1 - wgt) + np.asarray(m.piece.colour2) * wgt
    rgb = base.reshape(h, w, 3) * shade[..., None]

    shadowed = np.zeros((h, w), dtype=bool)
    if projector_baseline_m > 0 and np.any(hit):
        T_wc = _invert(np.asarray(T_camera_from_world, dtype=float))
        projector = T_wc[:3, :3] @ np.array([projector_baseline_m, 0.0, 0.0]) + T_wc[:3, 3]
        p_hit = points[hit]
        d = p_hit - projector
        length = np.linalg.norm(d, axis=-1)
        prays = np.concatenate([np.broadcast_to(projector, d.shape), d], axis=-1)
        pt = scene.cast_rays(o3d.core.Tensor(prays.astype(np.float32)))["t_hit"].numpy()
        # Occluded when something is hit more than 3 mm before the surface point itself.
        shadowed[hit] = pt < 1.0 - 0.003 / length

    albedo = (base @ np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)).reshape(h, w)
    return CleanFrame(depth, rgb.astype(np.float32), part_ids, cos_inc, shadowed, albedo)


def _depth_edges(depth_m: np.ndarray) -> np.ndarray:
    """Pixels next to a depth discontinuity (or next to a pixel without depth)."""
    z = depth_m
    valid = z > 0
    jump = np.zeros(z.shape, dtype=bool)
    thr = _jump_threshold_m(z)
    for axis in (0, 1):
        a = np.diff(z, axis=axis)
        va = valid.take(range(1, z.shape[axis]), axis=axis) & valid.take(
            range(0, z.shape[axis] - 1), axis=axis
        )
        t = np.minimum(
            thr.take(range(1, z.shape[axis]), axis=axis), thr.take(range(0, z.shape[axis] - 1), axis=axis)
        )
        big = (np.abs(a) > t) | (
            ~va
            & (
                valid.take(range(1, z.shape[axis]), axis=axis)
                | valid.take(range(0, z.shape[axis] - 1), axis=axis)
            )
        )
        if axis == 0:
            jump[1:, :] |= big
            jump[:-1, :] |= big
        else:
            jump[:, 1:] |= big
            jump[:, :-1] |= big
    return jump & valid


def _noisy_colour(rgb: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """``rgb`` (values 0-1) as 8-bit levels with Gaussian noise of ``sigma`` levels (no draw when
    ``sigma`` is 0), rounded and clipped to 0-255, uint8."""
    out = rgb.astype(np.float64) * 255.0
    if sigma > 0:
        out = out + rng.normal(0.0, sigma, size=out.shape)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def add_sensor_noise(
    frame: CleanFrame,
    *,
    noise: NoiseLevel,
    rng: np.random.Generator,
    disparity_bias_px: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Turn a clean rendering into what a structured-light RGB-D sensor would deliver.

    Steps, in order: grazing-angle dropouts, projector shadows, lateral jitter,
    flying pixels (a depth between the foreground's and the background's) and
    dropouts next to depth discontinuities, axial Gaussian noise ``sigma(z)``,
    a fixed disparity bias over the image (when given), disparity quantisation
    (step grows with z**2), random dropouts, speckle
    outliers, range limits, and rounding to the delivered depth unit (1 mm);
    colour gets Gaussian noise.

    Parameters
    ----------
    frame : CleanFrame
    noise : NoiseLevel
    rng : numpy.random.Generator
        The only source of randomness: the same state gives the same output.
    disparity_bias_px : ndarray, shape (H, W), optional
        A disparity error, pixels of ``noise.focal_px``, fixed over the image (a residual of the
        sensor's calibration): it moves depth by ``z**2 * bias / (focal_px * baseline_m)``, a bias
        that grows with the square of the range.

    Returns
    -------
    depth_m : ndarray, shape (H, W), float32
        z-depth in metres, 0 = no reading.
    rgb : ndarray, shape (H, W, 3), uint8
        RGB order.
    """
    z = frame.depth_m.astype(np.float64).copy()
    h, w = z.shape
    valid = z > 0

    rgb8 = _noisy_colour(frame.rgb, noise.rgb_sigma, rng)

    if noise.name == "none":
        return np.where(valid, z, 0.0).astype(np.float32), rgb8

    keep = valid.copy()

    # Grazing incidence: the projected pattern is too stretched to be decoded.
    angle = np.degrees(np.arccos(np.clip(frame.cos_incidence, 0.0, 1.0)))
    ramp = np.clip(
        (angle - noise.grazing_start_deg) / max(noise.grazing_end_deg - noise.grazing_start_deg, 1e-6),
        0.0,
        1.0,
    )
    keep &= ~(rng.random((h, w)) < noise.grazing_drop_prob * ramp)

    if noise.projector_shadow:
        keep &= ~frame.shadowed

    # Depth discontinuities: lateral jitter (take a neighbour's depth), then dropouts.
    edges = ndimage.binary_dilation(_depth_edges(z), iterations=1) & valid
    jitter = edges & (rng.random((h, w)) < noise.lateral_fraction)
    dv = rng.integers(-1, 2, size=(h, w))
    du = rng.integers(-1, 2, size=(h, w))
    vv, uu = np.nonzero(jitter)
    v2 = np.clip(vv + dv[vv, uu], 0, h - 1)
    u2 = np.clip(uu + du[vv, uu], 0, w - 1)
    z_src = z.copy()
    keep_src = keep.copy()
    z[vv, uu] = z_src[v2, u2]
    keep[vv, uu] = keep_src[v2, u2]
    z = _flying_pixels(z, edges, fraction=noise.flying_fraction, rng=rng)
    keep &= ~(edges & (rng.random((h, w)) < noise.edge_drop_prob))

    # Axial noise (Nguyen et al. 2012) and disparity quantisation.
    z = z + rng.normal(0.0, 1.0, size=(h, w)) * noise.axial_sigma_m(z)
    if disparity_bias_px is not None:  # 1 / z = d / (f b): a disparity error d' adds d' / (f b) to 1 / z
        zz = np.where(z > 1e-3, z, 1.0)
        z = np.where(z > 1e-3, 1.0 / (1.0 / zz + disparity_bias_px / (noise.focal_px * noise.baseline_m)), z)
    if noise.disparity_subpixel > 0:
        step_inv_m = noise.disparity_subpixel / (noise.focal_px * noise.baseline_m)
        zz = np.where(z > 1e-3, z, 1.0)
        z = np.where(z > 1e-3, 1.0 / (np.rint((1.0 / zz) / step_inv_m) * step_inv_m), z)

    keep &= ~(rng.random((h, w)) < noise.random_drop_fraction)
    speckle = keep & (rng.random((h, w)) < noise.speckle_fraction)
    z = np.where(speckle, z * rng.uniform(0.8, 1.25, size=(h, w)), z)

    keep &= (z >= noise.min_range_m) & (z <= noise.max_range_m)
    if noise.depth_step_m > 0:
        z = np.rint(z / noise.depth_step_m) * noise.depth_step_m
    return np.where(keep, z, 0.0).astype(np.float32), rgb8


def _flying_pixels(
    z: np.ndarray, edges: np.ndarray, *, fraction: float, rng: np.random.Generator
) -> np.ndarray:
    """Flying pixels: a share ``fraction`` of the ``edges`` pixels whose 3x3 neighbourhood spans a
    depth jump read a depth drawn uniformly between its nearest and farthest valid depth, as a
    sensor's matching window that straddles the foreground and the background does.

    The random draws do not depend on ``fraction`` (the same stream for every noise level)."""
    u = rng.random(z.shape)
    mix = rng.uniform(0.1, 0.9, size=z.shape)
    if fraction <= 0:
        return z
    valid = z > 0
    near = ndimage.minimum_filter(np.where(valid, z, np.inf), size=3, mode="nearest")
    far = ndimage.maximum_filter(np.where(valid, z, 0.0), size=3, mode="nearest")
    near = np.where(np.isfinite(near), near, 0.0)
    jump = valid & (far - near > _jump_threshold_m(near))
    fly = edges & jump & (u < fraction)
    return np.where(fly, near + mix * (far - near), z)


def _jump_threshold_m(z: np.ndarray) -> np.ndarray:
    """Depth difference between neighbouring pixels taken as a discontinuity, metres."""
    return 0.015 + 0.02 * z
