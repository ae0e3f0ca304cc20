"""Dataset readers: each on a fixture in its own layout, the reader contract for every registered
reader, and the YCB-Video reader on the real recordings in ../shared/data/ycbv."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import scipy.io

from artclass_core import InputError, find_sequences, load_registry, open_sequences
from artclass_core.cli import main
from artclass_plugins.readers import folder as folder_mod
from artclass_plugins.readers import rbo as rbo_mod
from artclass_plugins.readers import tum as tum_mod
from artclass_plugins.readers import ycbv as ycbv_mod
from artclass_plugins.readers.tum import associate

from fixtures_layouts import (
    CAMERA_STEP_M,
    CX,
    CY,
    FX,
    FY,
    HEIGHT,
    RBO_RATE_HZ,
    WIDTH,
    YCBV_IDS,
    angles,
    layout_root,
    render,
    snapshot,
    write_camera_info,
    write_folder,
    write_rbo,
    write_tum,
    write_ycbv,
)

REGISTRY = load_registry()
READERS = REGISTRY.names("reader")
LAYOUTS = ("folder", "ycbv", "rbo", "tum")
DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
YCBV = DATA / "ycbv"
needs_ycbv = pytest.mark.skipif(not YCBV.is_dir(), reason=f"real data folder {YCBV} is absent")

# The depth of each layout is quantised by its storage: 1 mm (folder, 1000/m), 0.1 mm (YCB-Video),
# 0.2 mm (TUM, 5000/m); the RBO text matrix keeps 1 um.
DEPTH_TOL_M = dict(folder=6e-4, ycbv=6e-5, tum=1.1e-4, rbo=2e-6)
# The functions each reader module calls to read one frame's files (patched to count file reads).
FRAME_READERS = dict(
    folder=(folder_mod, ("read_rgb", "read_depth", "read_mask")),
    ycbv=(ycbv_mod, ("read_rgb", "read_depth", "read_label")),
    rbo=(rbo_mod, ("read_rgb", "read_depth_txt")),
    tum=(tum_mod, ("read_rgb", "read_depth")),
)


@pytest.fixture(scope="module")
def layouts(tmp_path_factory) -> dict[str, Path]:
    return layout_root(tmp_path_factory.mktemp("layouts"))


def first_sequence(path, name=None):
    seqs = REGISTRY.create("reader", name).sequences(path) if name else open_sequences(REGISTRY, path)
    assert seqs, f"no sequence read from {path}"
    return seqs[0]


# -- the reader contract, for every registered reader -----------------------------------------------
def test_builtin_readers_are_registered():
    assert set(LAYOUTS) <= set(READERS)
    for name in LAYOUTS:
        cls = REGISTRY.get("reader", name)
        assert cls.description and "\n" not in cls.description
        cls.Params()  # defaults within bounds


@pytest.mark.parametrize("reader", READERS)
def test_reader_returns_nothing_for_foreign_folders(reader, layouts, tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    plain_file = tmp_path / "notes.txt"
    plain_file.write_text("not a dataset\n")
    r = REGISTRY.create("reader", reader)
    for path in (
        empty,
        plain_file,
        tmp_path / "missing",
        *(p for name, p in layouts.items() if name != reader),
    ):
        assert r.sequences(path) == [], f"reader {reader!r} claimed {path}"


@pytest.mark.parametrize("layout", LAYOUTS)
def test_exactly_one_reader_claims_each_layout(layout, layouts):
    claims = [name for name in READERS if REGISTRY.create("reader", name).sequences(layouts[layout])]
    assert claims == [layout]


# -- frames: lazy, right types and sizes, exact metres ------------------------------------------------
@pytest.mark.parametrize("layout", LAYOUTS)
def test_frames_are_read_lazily(layout, layouts, monkeypatch):
    module, names = FRAME_READERS[layout]
    calls: list[str] = []
    for fname in names:
        original = getattr(module, fname)
        monkeypatch.setattr(
            module,
            fname,
            lambda path, *a, _f=original, **kw: (calls.append(str(path)), _f(path, *a, **kw))[1],
        )
    seq = first_sequence(layouts[layout], layout)
    assert len(calls) <= 1, f"sequences() read frame files up front: {calls}"  # at most one, for the size
    calls.clear()
    frame = seq[5]
    assert frame.index == 5
    assert len(calls) == len(names) and len(set(calls)) == len(names), calls
    assert any(frame.name in Path(c).name for c in calls)
    calls.clear()
    seq[5]  # cached
    assert calls == []


@pytest.mark.parametrize("layout", LAYOUTS)
def test_frames_have_the_documented_types_and_exact_depth(layout, layouts):
    seqs = REGISTRY.create("reader", layout).sequences(layouts[layout])
    moving = layout != "ycbv"
    for seq in seqs:
        assert (seq.intrinsics.width, seq.intrinsics.height) == (WIDTH, HEIGHT)
        assert len(seq) == 8
        for i in range(len(seq)):
            f = seq[i]
            truth = render(angles(8, moving=moving)[i], seed=i)
            assert f.rgb.dtype == np.uint8 and f.rgb.shape == (HEIGHT, WIDTH, 3)
            assert f.depth_m.dtype == np.float32 and f.depth_m.shape == (HEIGHT, WIDTH)
            np.testing.assert_array_equal(f.rgb, truth.rgb)  # RGB order, lossless
            valid = f.depth_m > 0
            assert valid.mean() > 0.99
            np.testing.assert_allclose(f.depth_m[valid], truth.depth_m[valid], atol=DEPTH_TOL_M[layout])
        with pytest.raises(IndexError):
            seq[len(seq)]


def test_folder_reader(layouts, tmp_path):
    seq = first_sequence(layouts["folder"], "folder")
    assert (seq.label, seq.object_name, seq.has_masks) == ("articulated", "flap_box", True)
    assert (seq.intrinsics.fx, seq.intrinsics.fy, seq.intrinsics.cx, seq.intrinsics.cy) == (FX, FY, CX, CY)
    for i in (0, 7):
        np.testing.assert_array_equal(seq[i].mask, render(angles(8)[i]).mask)
    assert seq.pair_truth(0, 5) == "AM"  # the flap turns 0.43 rad over 5 frames
    still = first_sequence(
        write_folder(tmp_path, "still", moving=False, label="static", masks=False), "folder"
    )
    assert still.has_masks is False and still[0].mask is None
    assert still.pair_truth(0, 5) == "NM"
    # Masks that do not match the frames are bad input, named.
    bad = write_folder(tmp_path, "bad_masks")
    (bad / "mask" / "000003.png").unlink()
    with pytest.raises(InputError, match="7 masks for 8 frames") as exc:
        REGISTRY.create("reader", "folder").sequences(bad)
    assert exc.value.path == str(bad / "mask")


def test_folder_pair_truth_follows_what_the_sensor_sees_of_the_part(tmp_path):
    seq_dir = write_folder(tmp_path, "seen")
    truth = json.loads((seq_dir / "truth.json").read_text())
    q = truth["joint_positions"]
    assert abs(q[5] - q[0]) > np.radians(3)  # the joint truth alone says AM

    def truth_with(share, reach_m):
        truth["part_visibility"] = [{"share": share, "axis_distance_m": reach_m}] * len(q)
        (seq_dir / "truth.json").write_text(json.dumps(truth))
        return first_sequence(seq_dir, "folder").pair_truth(0, 5)

    assert truth_with(0.3, 0.10) == "AM"  # a large part, its far end moves centimetres
    assert truth_with(0.02, 0.10) is None  # the part is barely in view (seen edge-on)
    assert truth_with(0.3, 0.002) == "NM"  # its visible points stay within a millimetre
    assert truth_with(0.3, 0.008) is None  # 1-5 mm: within the ambiguous band


def _two_part_truth(
    motion_of_part: np.ndarray, *, part_px: int = 5000, noise_a_m: float = 0.0012, n_frames: int = 2
) -> dict:
    """Hand-made observable truth: a 30 x 30 cm grey base and a 10 x 2 cm flat lever lying on it,
    1 m in front of the camera, the lever seen on ``part_px`` pixels. Frame 1 moves the lever by
    ``motion_of_part`` (4x4, in the base's frame); nothing else moves. The points are in a plane (a
    texture-less surface turning in its own plane looks the same to the camera)."""
    camera_from_base = np.eye(4)
    camera_from_base[2, 3] = 1.0
    grid = np.stack(np.meshgrid(np.linspace(-0.15, 0.15, 16), np.linspace(-0.15, 0.15, 16)), -1).reshape(
        -1, 2
    )
    base = np.column_stack([grid, np.zeros(len(grid))])
    lever = np.column_stack(
        [np.linspace(0.0, 0.10, 64).repeat(4), np.tile(np.linspace(-0.01, 0.01, 4), 64), np.full(256, -0.005)]
    )  # from its pivot at the origin
    poses = [
        [camera_from_base.tolist(), (camera_from_base @ np.linalg.matrix_power(motion_of_part, f)).tolist()]
        for f in range(n_frames)
    ]
    return dict(
        object_poses=[camera_from_base.tolist()] * n_frames,
        joint_type="revolute",
        parts=[dict(name="base", parent=-1, joint=None), dict(name="lever", parent=0, joint=0)],
        part_poses=poses,
        part_valid_px=[[40000, part_px]] * n_frames,
        part_points_m=[[base.tolist(), lever.tolist()]] * n_frames,
        sensor=dict(
            fx_px=570.0, axial_a_m=noise_a_m, axial_b_per_m=0.0019, axial_reference_m=0.4, depth_step_m=0.001
        ),
    )


def _turn_z(angle_deg: float) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))
    T[:2, :2] = [[c, -s], [s, c]]
    return T


def _shift_x(d_m: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = d_m
    return T


def test_observable_truth_thresholds_follow_the_sensor_noise():
    truth = folder_mod.observable_pair_truth
    # At 1 m: sigma = 1.2 mm + 1.9 mm/m * 0.36 m^2 = 1.88 mm; one pixel = 1.75 mm; AM above 7.4 mm.
    sigma, pixel = 0.0012 + 0.0019 * 0.6**2, 1.0 / 570.0
    # A lever turning 10 degrees in its own plane about its pivot: its median point (5 cm out) moves
    # 8.7 mm, and so does the base's median point (about 5 cm from the pivot) in the lever's frame.
    assert truth(_two_part_truth(_turn_z(10.0)), 0, 1) == "AM"
    assert truth(_two_part_truth(_turn_z(10.0)), 1, 0) == "AM"
    # The same turn is ambiguous for a noisier sensor, whose 3 sigma + 1 px exceeds it...
    assert truth(_two_part_truth(_turn_z(10.0), noise_a_m=0.003), 0, 1) is None
    # ...and below one sigma it is no motion at all.
    assert truth(_two_part_truth(_shift_x(0.0005)), 0, 1) == "NM"
    assert truth(_two_part_truth(_shift_x(2 * sigma)), 0, 1) is None
    assert truth(_two_part_truth(_shift_x(3 * sigma + pixel + 0.0005)), 0, 1) == "AM"
    # A part the sensor sees on too few pixels shows no articulation, however far it moves.
    assert truth(_two_part_truth(_turn_z(30.0), part_px=25), 0, 1) == "NM"
    assert truth(_two_part_truth(_turn_z(30.0), part_px=799), 0, 1) == "NM"  # < 2 % of the object
    assert truth(_two_part_truth(_turn_z(30.0), part_px=1000), 0, 1) == "AM"


def test_observable_truth_of_a_moving_part_whose_base_is_hidden_is_a_rigid_motion():
    truth = folder_mod.observable_pair_truth
    pull = _shift_x(0.03)  # a drawer pulled out by 3 cm from a static carcass
    assert truth(_two_part_truth(pull, part_px=1000), 0, 1) == "AM"
    hidden = _two_part_truth(pull, part_px=1000)
    hidden["part_valid_px"] = [[20, 1000]] * 2  # the carcass has depth on 20 pixels only
    assert truth(hidden, 0, 1) == "RM"  # the sensor sees one part move, not a joint
    hidden["part_valid_px"] = [[20, 20]] * 2  # neither part is seen: the object's own pose decides
    assert truth(hidden, 0, 1) == "NM"


def test_observable_truth_judges_each_side_in_the_others_frame():
    # A lever turning about an axis through its own median point barely moves its median point, but
    # the base's points, seen from the lever, swing round by centimetres: the smaller side decides.
    spin = np.linalg.inv(_shift_x(0.05)) @ _turn_z(1.0) @ _shift_x(0.05)  # about the lever's centre
    motions = folder_mod.observable_joint_motions(_two_part_truth(spin), 0, 1)
    (m,) = motions
    assert m["valid"] and m["moving"]["displacement_m"] < m["rest"]["displacement_m"]
    assert m["moving"]["depth_m"] == pytest.approx(0.995, abs=1e-3)  # the lever lies 5 mm nearer


def test_folder_pair_truth_is_observable_for_new_truth_and_legacy_for_old(tmp_path):
    seq_dir = write_folder(tmp_path, "both")
    old = json.loads((seq_dir / "truth.json").read_text())
    seq = first_sequence(seq_dir, "folder")
    assert seq.pair_truth(0, 5) == seq.pair_truth_legacy(0, 5) == "AM"  # old truth: old rule
    # With per-part data, the observable rule decides: a 0.5 mm motion per frame is no articulation.
    new = dict(old, **_two_part_truth(_shift_x(0.0005), n_frames=len(old["joint_positions"])))
    (seq_dir / "truth.json").write_text(json.dumps(new))
    seq = first_sequence(seq_dir, "folder")
    assert seq.pair_truth(0, 1) == "NM" and seq.pair_truth_legacy(0, 5) == "AM"


def test_ycbv_reader_on_fixture(layouts):
    seqs = REGISTRY.create("reader", "ycbv").sequences(layouts["ycbv"])
    assert [s.name for s in seqs] == ["0000/025_mug", "0000/061_foam_brick"]
    assert [s.object_name for s in seqs] == ["025_mug", "061_foam_brick"]
    mug, brick = seqs
    assert mug.label == "rigid" and mug.accepted_labels == ("rigid", "static") and mug.has_masks
    truth = render(angles(8, moving=False)[2], seed=2)
    np.testing.assert_array_equal(mug[2].mask, truth.box)
    np.testing.assert_array_equal(brick[2].mask, truth.flap)
    # The camera drifts 0.6 mm per frame: 0.6 mm between neighbours is no motion, 3 mm over 5 frames is.
    assert CAMERA_STEP_M * 5 > 0.002 > CAMERA_STEP_M
    assert [mug.pair_truth(i, i + 1) for i in range(7)] == ["NM"] * 7
    assert [mug.pair_truth(i, i + 5) for i in range(3)] == ["RM"] * 3
    assert mug.meta["object_id"] == YCBV_IDS[0]


def test_ycbv_meta_without_intrinsics_is_named(tmp_path):
    scene = write_ycbv(tmp_path, n_frames=3, drop=("intrinsic_matrix",))
    with pytest.raises(InputError, match="missing 'intrinsic_matrix'") as exc:
        REGISTRY.create("reader", "ycbv").sequences(scene)
    assert exc.value.path == str(scene / "000001-meta.mat")


def test_ycbv_single_object_scene(tmp_path):
    (mug,) = REGISTRY.create("reader", "ycbv").sequences(write_ycbv(tmp_path, n_objects=1))
    assert mug.name == "0000/025_mug"
    assert (mug.pair_truth(0, 1), mug.pair_truth(0, 5)) == ("NM", "RM")


def test_ycbv_intrinsics_are_checked_on_every_frame(tmp_path):
    scene = write_ycbv(tmp_path)
    meta = scipy.io.loadmat(scene / "000004-meta.mat")
    meta["intrinsic_matrix"][0, 0] = 2 * FX
    scipy.io.savemat(scene / "000004-meta.mat", {k: v for k, v in meta.items() if not k.startswith("__")})
    mug = REGISTRY.create("reader", "ycbv").sequences(scene)[0]
    assert mug[2].mask.any()
    with pytest.raises(InputError, match="intrinsic_matrix differs from the first frame's") as exc:
        mug[3]
    assert exc.value.path == str(scene / "000004-meta.mat")


def test_ycbv_missing_frame_file_is_named(tmp_path):
    scene = write_ycbv(tmp_path, n_frames=3)
    (scene / "000002-label.png").unlink()
    with pytest.raises(InputError, match="frame 000002 has no 000002-label.png") as exc:
        REGISTRY.create("reader", "ycbv").sequences(scene)
    assert exc.value.path == str(scene / "000002-label.png")


def test_rbo_reader(layouts, tmp_path):
    seq = first_sequence(layouts["rbo"], "rbo")
    assert (seq.name, seq.object_name, seq.label, seq.has_masks) == (
        "flapbox01_o",
        "flapbox",
        "articulated",
        False,
    )
    assert (seq.intrinsics.fx, seq.intrinsics.cy) == (FX, CY)
    assert len(seq) == 8 and seq.meta["n_rgb"] == 9  # the colour frame without depth is dropped
    times = [seq[i].time_s for i in range(8)]
    np.testing.assert_allclose(np.diff(times), 1 / RBO_RATE_HZ, atol=1e-5)
    assert seq[0].depth_m[0, 0] == 0.0  # NaN = no reading -> 0
    np.testing.assert_allclose([seq.joint_positions(i)["j_0_1"] for i in range(8)], angles(8), atol=1e-5)
    assert [seq.pair_truth(i, i + 5) for i in range(3)] == ["AM"] * 3

    still = first_sequence(write_rbo(tmp_path, "still01_o", moving=False), "rbo")
    assert still.label == "static" and still.accepted_labels == ("static", "rigid")
    assert still.pair_truth(0, 7) == "NM"
    # A re-export in millimetres is recognised per frame and gives the same metres.
    mm = first_sequence(write_rbo(tmp_path, "mm01_o", depth_unit_per_metre=1000.0), "rbo")
    np.testing.assert_allclose(mm[3].depth_m, seq[3].depth_m, atol=1e-5)


def test_rbo_camera_info_is_required_and_checked(tmp_path):
    seq = write_rbo(tmp_path, "nocam01_o", camera_info=False)
    with pytest.raises(InputError, match="no camera intrinsics") as exc:
        REGISTRY.create("reader", "rbo").sequences(seq)
    assert exc.value.path == str(seq)
    write_camera_info(seq / "camera_rgb_camera_info.csv", fx=0.0)
    with pytest.raises(InputError, match="'field.K0' must be a positive") as exc:
        REGISTRY.create("reader", "rbo").sequences(seq)
    assert exc.value.path == str(seq / "camera_rgb_camera_info.csv")


def test_rbo_without_joint_states_has_no_truth(tmp_path):
    seq = write_rbo(tmp_path, "nojs01_o")
    (seq / "flapbox_joint_states.csv").unlink()
    s = first_sequence(seq, "rbo")
    assert s.label is None and s.pair_truth(0, 5) is None and len(s) == 8


def test_tum_reader(layouts, tmp_path):
    seq = first_sequence(layouts["tum"], "tum")
    assert seq.label is None and seq.has_masks is False
    assert len(seq) == 8 and seq.meta["n_associated"] == 8  # the unpaired depth frame is left out
    assert seq.meta["intrinsics_source"] == "freiburg1"
    assert (seq.intrinsics.fx, seq.intrinsics.fy, seq.intrinsics.cx, seq.intrinsics.cy) == (
        517.3,
        516.5,
        318.6,
        255.3,
    )
    assert seq.pair_truth(0, 5) is None
    np.testing.assert_allclose(seq.world_from_camera(3)[:3, 3], [0.003, 0, 0])
    # No calibration in the folder name: the ROS default.
    plain = shutil.copytree(layouts["tum"], tmp_path / "my_recording")
    s = first_sequence(plain, "tum")
    assert s.meta["intrinsics_source"] == "ros_default" and s.intrinsics.fx == 525.0
    # meta.json gives intrinsics and a label.
    own = write_tum(
        tmp_path,
        "rgbd_dataset_freiburg2_labelled",
        config=dict(fx=FX, fy=FY, cx=CX, cy=CY, label="articulated", object="flap_box"),
    )
    s = first_sequence(own)  # through open_sequences: the folder reader must not claim it
    assert type(s).__name__ == "TumSequence"
    assert (s.intrinsics.fx, s.label, s.object_name, s.meta["intrinsics_source"]) == (
        FX,
        "articulated",
        "flap_box",
        "meta.json",
    )


def test_tum_associations_and_given_intrinsics(tmp_path):
    # ORB-SLAM2's associations.txt decides the pairs, whatever the timestamps (recorders that write
    # frame durations instead of times cannot be associated by time); given intrinsics win.
    seq = write_tum(tmp_path, "desk")
    rgb = sorted((seq / "rgb").iterdir())[:3]
    depth = sorted((seq / "depth").iterdir())[:3]
    lines = [f"0.016 rgb/{a.name} 0.016 depth/{b.name}" for a, b in zip(rgb, depth)]
    (seq / "associations.txt").write_text("\n".join(lines) + "\n")
    reader = REGISTRY.create(
        "reader", "tum", tum_mod.TumParams(fx=600, fy=601, cx=300, cy=200, depth_scale=2500)
    )
    (s,) = reader.sequences(seq)
    assert len(s) == 3 and s.meta["intrinsics_source"] == "reader parameters"
    assert (s.intrinsics.fx, s.intrinsics.fy, s.intrinsics.cx, s.intrinsics.cy) == (600, 601, 300, 200)
    frame = s.load(1)
    assert frame.name == rgb[1].stem
    # Depth read at half TUM's scale doubles: the fixture's depth was written at 5000 units a metre.
    (ref,) = REGISTRY.create("reader", "tum").sequences(seq)
    np.testing.assert_allclose(frame.depth_m, 2 * ref.load(1).depth_m)
    with pytest.raises(InputError, match="all four intrinsics"):
        REGISTRY.create("reader", "tum", tum_mod.TumParams(fx=600)).sequences(seq)


def test_a_worker_opens_a_sequence_with_the_reader_values_it_was_opened_with(tmp_path):
    # A Dask worker re-opens each sequence from its path: with the reader parameters given here.
    from artclass_core import find_sequences, open_sequences
    from artclass_core.sweep import SequenceSource

    seq = write_tum(tmp_path, "desk")
    values = dict(fx="600", fy="601", cx="300", cy="200")
    opened = (
        open_sequences(REGISTRY, seq, reader_values=values)
        + find_sequences(REGISTRY, tmp_path, labelled_only=False, reader_values=values)[0]
    )
    for s in opened:
        again = SequenceSource.of(s).open(REGISTRY)
        assert s.opened_with[0] == "tum" and again.intrinsics.fx == s.intrinsics.fx == 600


def test_tum_bad_list_line_is_named(tmp_path):
    seq = write_tum(tmp_path)
    (seq / "rgb.txt").write_text("# fine\n1305031102.0 rgb/a.png\nnot-a-time rgb/b.png\n")
    with pytest.raises(InputError, match="line 3") as exc:
        REGISTRY.create("reader", "tum").sequences(seq)
    assert exc.value.path == str(seq / "rgb.txt")


def test_associate_is_greedy_one_to_one():
    # Depth 0.010 is 0.002 from colour 0.012 and 0.010 from colour 0.0: it goes to the closer one.
    assert associate([0.0, 0.012], [0.010], max_diff_s=0.02) == [(1, 0)]
    assert associate([0.0, 1.0], [0.019, 1.02], max_diff_s=0.02) == [(0, 0)]  # 0.02 is not < 0.02
    assert associate([2.0, 1.0], [1.001, 2.001], max_diff_s=0.02) == [(0, 1), (1, 0)]
    assert associate([], [1.0], max_diff_s=0.02) == []


# -- finding sequences under a root that holds every layout -------------------------------------------
def test_find_sequences_over_mixed_layouts(tmp_path):
    paths = layout_root(tmp_path)
    bad = write_folder(tmp_path / "broken", "no_fx")
    meta = json.loads((bad / "meta.json").read_text())
    del meta["fx"]
    (bad / "meta.json").write_text(json.dumps(meta))
    before = snapshot(tmp_path)

    found, errors = find_sequences(REGISTRY, tmp_path, labelled_only=False)
    assert sorted(s.name for s in found) == sorted(
        ["folder_seq", "0000/025_mug", "0000/061_foam_brick", "flapbox01_o", "rgbd_dataset_freiburg1_flapbox"]
    )
    assert {type(s).__name__ for s in found} == {
        "FolderSequence",
        "YcbvSequence",
        "RboSequence",
        "TumSequence",
    }
    assert len(errors) == 1 and errors[0].path == str(bad / "meta.json") and "'fx'" in errors[0].problem
    labelled, _ = find_sequences(REGISTRY, tmp_path)
    assert "rgbd_dataset_freiburg1_flapbox" not in {s.name for s in labelled} and len(labelled) == 4
    only_rbo, _ = find_sequences(REGISTRY, tmp_path, reader="rbo")
    assert [s.name for s in only_rbo] == ["flapbox01_o"]
    assert snapshot(tmp_path) == before
    assert paths["tum"].is_dir()


def test_find_sequences_follows_links_and_ends_a_link_loop(tmp_path):
    data = tmp_path / "data"
    write_folder(data / "real", "seq")
    picked = tmp_path / "picked"
    picked.mkdir()
    (picked / "seq").symlink_to(data / "real" / "seq", target_is_directory=True)  # a hand-picked subset
    (picked / "again").symlink_to(picked, target_is_directory=True)  # a loop
    found, errors = find_sequences(REGISTRY, picked, labelled_only=False)
    assert [s.name for s in found] == ["seq"] and not errors


def test_open_sequences_selects_by_name(layouts):
    scene = layouts["ycbv"]
    assert [s.name for s in open_sequences(REGISTRY, f"{scene}#025_mug")] == ["0000/025_mug"]
    assert [s.name for s in open_sequences(REGISTRY, f"{scene}#0000/061_foam_brick")] == [
        "0000/061_foam_brick"
    ]
    with pytest.raises(
        InputError, match="no sequence named 'banana'; found: 0000/025_mug, 0000/061_foam_brick"
    ):
        open_sequences(REGISTRY, f"{scene}#banana")


# -- YCB-Video reader on the real recordings -----------------------------------------------------------
@needs_ycbv
def test_ycbv_real_scenes_list_their_objects():
    r = REGISTRY.create("reader", "ycbv")
    assert [s.name for s in r.sequences(YCBV / "0000")] == [
        "0000/009_gelatin_box",
        "0000/025_mug",
        "0000/061_foam_brick",
    ]
    s1 = r.sequences(YCBV / "0001")
    assert [s.object_name for s in s1] == [
        "002_master_chef_can",
        "003_cracker_box",
        "004_sugar_box",
        "006_mustard_bottle",
    ]
    assert [len(s) for s in s1] == [5] * 4
    assert r.sequences(YCBV) == []  # the dataset root is not a scene


@needs_ycbv
def test_ycbv_real_frames(monkeypatch):
    calls = []
    original = ycbv_mod.read_rgb
    monkeypatch.setattr(ycbv_mod, "read_rgb", lambda p: (calls.append(p), original(p))[1])
    seqs = REGISTRY.create("reader", "ycbv").sequences(YCBV / "0000")
    assert calls == []  # nothing but the first depth and a few meta.mat read up front
    for seq in seqs:
        K = seq.intrinsics
        np.testing.assert_allclose([K.fx, K.fy, K.cx, K.cy], [1066.778, 1067.487, 312.9869, 241.3109])
        assert (K.width, K.height, seq.meta["depth_units_per_metre"]) == (640, 480, 10000)
        assert seq.label == "rigid" and set(seq.accepted_labels) == {"rigid", "static"}
        for i in (0, 9):
            f = seq[i]
            assert f.rgb.shape == (480, 640, 3) and f.rgb.dtype == np.uint8
            assert f.depth_m.shape == (480, 640) and f.depth_m.dtype == np.float32
            assert f.mask.dtype == bool and f.mask.sum() > 2000
            z = f.depth_m[f.mask & (f.depth_m > 0)]
            assert 0.3 < np.median(z) < 3.0
            # The annotated pose, the intrinsics, the mask and the depth agree: the object's origin
            # projects near the mask's centroid, at about the depth seen there.
            T = seq.scene.pose(i, seq.meta["object_id"])
            u, v = K.fx * T[0, 3] / T[2, 3] + K.cx, K.fy * T[1, 3] / T[2, 3] + K.cy
            rows, cols = np.nonzero(f.mask)
            assert np.hypot(u - cols.mean(), v - rows.mean()) < 40
            assert abs(T[2, 3] - np.median(z)) < 0.1
    assert len(calls) == 2 * len(seqs)


@needs_ycbv
def test_ycbv_real_pair_truth_follows_the_camera():
    mug = open_sequences(REGISTRY, f"{YCBV / '0000'}#025_mug")[0]
    truths = {(i, j): mug.pair_truth(i, j) for i in range(10) for j in range(i + 1, 10)}
    assert "AM" not in truths.values()
    assert truths[(0, 1)] == "NM"  # under a millimetre between neighbours
    assert truths[(0, 9)] == "RM"  # the camera moved about 5 mm over the ten frames


@pytest.mark.slow
@needs_ycbv
def test_cli_classifies_a_real_ycbv_object(capsys):
    assert main(["classify", f"{YCBV / '0000'}#025_mug", "--json", "--no-cells"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["sequence"]["name"] == "0000/025_mug" and out["sequence"]["truth"] == "rigid"
    assert out["sequence"]["n_frames"] == 10 and out["plugins"]["segmenter"] == "mask"
    assert [p["truth"] for p in out["pairs"]] == ["RM"] * 5
    assert out["label"] in ("articulated", "rigid", "static")


@needs_ycbv
def test_cli_classify_asks_to_choose_in_a_scene(capsys):
    assert main(["classify", str(YCBV / "0000")]) == 2
    err = capsys.readouterr().err
    assert "holds 3 sequences (0000/009_gelatin_box, 0000/025_mug, 0000/061_foam_brick)" in err


# -- a third-party reader registers through the same hook ---------------------------------------------
class _NpzPlugin:
    """A plugin object providing a reader of ``sequence.npz`` (arrays rgb (N,H,W,3), depth_m (N,H,W), K)."""

    from artclass_core import hookimpl as _hookimpl

    @staticmethod
    @_hookimpl
    def register_readers(register):
        from artclass_core import Frame, Intrinsics, Reader, Sequence

        class NpzSequence(Sequence):
            def __init__(self, path):
                self.data = np.load(path)
                n, h, w = self.data["depth_m"].shape
                fx, fy, cx, cy = self.data["K"]
                super().__init__(
                    name=path.parent.name,
                    path=path,
                    n_frames=n,
                    intrinsics=Intrinsics(fx, fy, cx, cy, width=w, height=h),
                )

            def load(self, i):
                return Frame(i, str(i), self.data["rgb"][i], self.data["depth_m"][i])

        class NpzReader(Reader):
            name = "npz"
            description = "one sequence.npz holding rgb, depth_m and K"

            def sequences(self, path):
                path = Path(path)
                return [NpzSequence(path / "sequence.npz")] if (path / "sequence.npz").is_file() else []

        register(NpzReader)


def test_hook_register_readers(tmp_path, layouts):
    registry = load_registry(extra_plugins=(_NpzPlugin,))
    assert "npz" in registry.names("reader") and set(LAYOUTS) <= set(registry.names("reader"))
    seq_dir = tmp_path / "npz_seq"
    seq_dir.mkdir()
    truth = render(0.3)
    np.savez(
        seq_dir / "sequence.npz",
        rgb=truth.rgb[None].repeat(3, 0),
        depth_m=truth.depth_m[None].repeat(3, 0).astype(np.float32),
        K=np.array([FX, FY, CX, CY]),
    )
    (seq,) = open_sequences(registry, seq_dir)
    assert type(seq).__name__ == "NpzSequence" and len(seq) == 3
    np.testing.assert_array_equal(seq[2].depth_m, truth.depth_m.astype(np.float32))
    assert registry.create("reader", "npz").sequences(layouts["tum"]) == []
    assert [type(s).__name__ for s in open_sequences(registry, layouts["tum"])] == ["TumSequence"]
