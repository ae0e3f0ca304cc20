"""Third-party plugins: the example package end to end, and every hook extended in-process.

1. ``examples/artclass-example-plugin`` is pip-installed (offline: ``--no-index --no-build-isolation``)
   into a private ``--target`` folder that only the subprocesses of this module see through
   ``PYTHONPATH``. The shared virtual environment is never modified, so tests running at the same
   time are not affected and there is nothing to uninstall; pytest removes the folder.
   ``artclass plugins`` must list its rule and ``artclass classify --rule example_centroid`` must use it.
2. ``test_hook_<name>``: one test per hook in ``artclass_core.hookspecs``, each registering a small
   plugin object through ``load_registry(extra_plugins=...)`` and checking that the pipeline (or the
   command line) really calls what was registered.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from artclass_core import (
    CellMotion,
    Cloud,
    Config,
    DecisionRule,
    Frame,
    InputError,
    Intrinsics,
    Params,
    Pipeline,
    PipelineParams,
    PluginError,
    Preprocessor,
    Reader,
    Registrar,
    Registration,
    RuleDecision,
    Segmenter,
    Sequence,
    hookimpl,
    load_registry,
    open_sequences,
    param,
)
from artclass_core.cli import build_parser

pytestmark = pytest.mark.slow  # builds and installs the example package, in subprocesses

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "artclass-example-plugin"
SAMPLE = ROOT / "sample_data" / "laptop_articulate"


# --------------------------------------------------------------------------------------------------
# 1. The example package, installed with pip and used through the real command line
# --------------------------------------------------------------------------------------------------


def _artclass_cmd() -> list[str]:
    exe = Path(sys.executable).parent / "artclass"
    return [str(exe)] if exe.is_file() else [sys.executable, "-m", "artclass_core.cli"]


@pytest.fixture(scope="module")
def plugin_env(tmp_path_factory) -> dict[str, str]:
    """Environment for subprocesses in which the example plugin is installed."""
    tmp = tmp_path_factory.mktemp("example_plugin")
    src = tmp / "src"
    # Build from a copy: a build writes egg-info/ next to the sources, never into the repository.
    shutil.copytree(EXAMPLE, src, ignore=shutil.ignore_patterns("build", "*.egg-info", "__pycache__"))
    target = tmp / "site"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "--quiet",
            "--disable-pip-version-check",
            "--no-deps",
            "--no-build-isolation",
            "--no-index",
            "--target",
            str(target),
            str(src),
        ],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 0, f"pip could not install the example plugin:\n{proc.stderr}"
    assert (target / "artclass_example_plugin" / "__init__.py").is_file()
    env = {k: v for k, v in os.environ.items() if k != "ARTCLASS_PLUGINS"}
    env["PYTHONPATH"] = os.pathsep.join([str(target), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    return env


@pytest.fixture(scope="module")
def articulated_sequence(tmp_path_factory) -> Path:
    """The bundled laptop sequence, or the same one rendered by the generator if not bundled."""
    if SAMPLE.is_dir():
        return SAMPLE
    from artclass_plugins.synth import generate_sequence

    return generate_sequence(
        tmp_path_factory.mktemp("seq") / "laptop_articulate",
        object_name="laptop",
        motion="articulate",
        noise="low",
        n_frames=16,
        seed=1,
        width=320,
        height=240,
    )


def _run(args: list[str], env: dict[str, str]) -> subprocess.CompletedProcess:
    return subprocess.run(_artclass_cmd() + args, capture_output=True, text=True, env=env, timeout=600)


def test_artclass_plugins_lists_the_example(plugin_env):
    proc = _run(["plugins", "--json"], plugin_env)
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert out["failures"] == {}
    rules = {r["name"]: r for r in out["plugins"]["rule"]}
    assert "example_centroid" in rules, f"rules listed: {sorted(rules)}"
    rule = rules["example_centroid"]
    assert "artclass-example-plugin" in rule["source"]  # its own distribution, not artclass
    assert [p["name"] for p in rule["params"]] == ["min_motion_m", "max_spread_m", "min_part_cells"]
    assert {"dense", "paper"} <= set(rules), "the built-in rules must still be there"
    text = _run(["plugins"], plugin_env)
    assert "example_centroid" in text.stdout


def test_example_is_absent_without_install():
    env = {k: v for k, v in os.environ.items() if k != "ARTCLASS_PLUGINS"}
    proc = _run(["plugins", "--json"], env)
    assert proc.returncode == 0, proc.stderr
    assert "example_centroid" not in {r["name"] for r in json.loads(proc.stdout)["plugins"]["rule"]}


def test_classify_with_the_example_rule(plugin_env, articulated_sequence):
    proc = _run(
        [
            "classify",
            str(articulated_sequence),
            "--rule",
            "example_centroid",
            "--json",
            "--no-cells",
            "--param",
            "max_spread_m=0.01",
        ],
        plugin_env,
    )
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout)
    assert result["plugins"]["rule"] == "example_centroid"
    assert result["params"]["rule"] == dict(min_motion_m=0.004, max_spread_m=0.01, min_part_cells=2)
    decided = [p for p in result["pairs"] if p["decision"] != "skipped"]
    assert decided, "no pair was decided"
    assert all(p["info"]["n_outlier_cells"] >= 0 for p in decided)  # the rule's own evidence is recorded
    assert result["label"] == "articulated", result["fractions"]  # a laptop opening: the lid moves alone
    assert result["fractions"]["AM"] > 0.5


def test_the_example_can_be_blocked(plugin_env, articulated_sequence):
    env = dict(plugin_env, ARTCLASS_PLUGINS="no:example_centroid")
    proc = _run(["classify", str(articulated_sequence), "--rule", "example_centroid"], env)
    assert proc.returncode == 2
    assert proc.stderr.startswith("artclass: error: unknown rule 'example_centroid'")
    assert "Traceback" not in proc.stderr


def test_example_rule_on_known_cell_motions(monkeypatch):
    """The example rule in-process, on cells whose motion is known exactly."""
    monkeypatch.syspath_prepend(str(EXAMPLE))
    from artclass_example_plugin import CentroidRule

    def cells(moves_m):
        out = []
        for n, t in enumerate(moves_m):
            T = np.eye(4)
            T[:3, 3] = t
            c = CellMotion((n, 0, 0), np.array([0.05 * n, 0.0, 0.6]), np.arange(10), np.arange(10))
            c.registration = Registration(T, 1.0, 0.0, 10)
            out.append(c)
        return out

    cloud = Cloud(0, np.zeros((0, 3)))
    rule = CentroidRule()
    still, moved = [0, 0, 0], [0.02, 0, 0]
    assert rule.decide(cells([still] * 6), source=cloud, target=cloud).decision == "NM"
    assert rule.decide(cells([moved] * 6), source=cloud, target=cloud).decision == "RM"
    out = rule.decide(cells([still] * 4 + [moved] * 3), source=cloud, target=cloud)
    assert out.decision == "AM"
    assert out.clusters == [0, 0, 0, 0, 1, 1, 1]
    # one stray cell is not a part (min_part_cells = 2)
    assert rule.decide(cells([moved] * 6 + [still]), source=cloud, target=cloud).decision == "RM"


# --------------------------------------------------------------------------------------------------
# 2. Every hook, extended by an in-process plugin object
# --------------------------------------------------------------------------------------------------

INTR = Intrinsics(150.0, 150.0, 79.5, 59.5, 160, 120)


def hinge_points(angle_rad: float, shift_m: np.ndarray) -> np.ndarray:
    """Two 12 x 16 cm plates side by side at 60 cm, facing the camera; the right one turned about
    the shared vertical edge by ``angle_rad``; everything then shifted by ``shift_m``."""
    g = np.linspace(0.0, 0.12, 121)
    h = np.linspace(-0.08, 0.08, 161)
    gx, gy = np.meshgrid(g, h)
    left = np.column_stack([-gx.ravel(), gy.ravel(), np.full(gx.size, 0.6)])
    right = np.column_stack(
        [gx.ravel() * np.cos(angle_rad), gy.ravel(), 0.6 + gx.ravel() * np.sin(angle_rad)]
    )
    return np.concatenate([left, right]) + shift_m


def render_depth(points: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """Z-buffer projection of points (metres) into a depth image (0 = no reading)."""
    u = np.round(points[:, 0] * intr.fx / points[:, 2] + intr.cx).astype(int)
    v = np.round(points[:, 1] * intr.fy / points[:, 2] + intr.cy).astype(int)
    ok = (u >= 0) & (u < intr.width) & (v >= 0) & (v < intr.height)
    depth = np.full((intr.height, intr.width), np.inf)
    np.minimum.at(depth, (v[ok], u[ok]), points[ok, 2])
    depth[np.isinf(depth)] = 0.0
    return depth.astype(np.float32)


class HingeSequence(Sequence):
    """In-memory sequence: the right plate opens by 3 degrees a frame (or the whole thing moves)."""

    def __init__(self, path: Path, *, motion: str = "hinge", n_frames: int = 4):
        super().__init__(
            name=f"hinge_{motion}",
            path=path,
            intrinsics=INTR,
            n_frames=n_frames,
            label="articulated" if motion == "hinge" else "rigid",
            has_masks=False,
        )
        self.motion = motion

    def load(self, i: int) -> Frame:
        if self.motion == "hinge":
            pts = hinge_points(np.radians(3.0 * i), np.zeros(3))
        else:
            pts = hinge_points(0.0, np.array([0.004, 0.0, 0.01]) * i)
        depth = render_depth(pts, INTR)
        return Frame(i, f"{i:04d}", np.zeros((INTR.height, INTR.width, 3), np.uint8), depth)


class HingeReader(Reader):
    name = "test_hinge"
    description = "test reader: a folder holding a file named hinge.txt with the motion"

    def sequences(self, path: Path) -> list[Sequence]:
        marker = Path(path) / "hinge.txt"
        if not marker.is_file():
            return []
        motion = marker.read_text().strip()
        if motion not in ("hinge", "carry"):
            raise InputError(f"unknown motion {motion!r}", path=marker)
        return [HingeSequence(Path(path), motion=motion)]


@dataclass(frozen=True)
class BandParams(Params):
    near_m: float = param(0.3, unit="m", bounds=(0.0, 10.0), help="Nearest depth that belongs to the object.")
    far_m: float = param(0.8, unit="m", bounds=(0.0, 10.0), help="Farthest depth that belongs to the object.")


class BandSegmenter(Segmenter):
    name = "test_band"
    description = "test segmenter: every pixel with a depth reading between near_m and far_m"
    Params = BandParams

    def segment(self, frame: Frame, *, sequence: Sequence) -> np.ndarray | None:
        return (frame.depth_m > self.params.near_m) & (frame.depth_m < self.params.far_m)


@dataclass(frozen=True)
class StrideParams(Params):
    stride: int = param(2, unit="points", bounds=(1, 100), help="Keep every stride-th back-projected point.")


class StridePreprocessor(Preprocessor):
    name = "test_stride"
    description = "test preprocessor: back-project and keep every n-th point, no filtering"
    Params = StrideParams

    def process(self, frame: Frame, mask: np.ndarray, *, intrinsics: Intrinsics) -> Cloud:
        points = intrinsics.backproject(frame.depth_m, mask)[:: self.params.stride]
        return Cloud(frame.index, points, None, dict(n_points=len(points), stride=self.params.stride))


class CentroidShiftRegistrar(Registrar):
    """Translation only: the difference of the cell's centroids. Records every call it gets."""

    name = "test_centroid_shift"
    description = "test registrar: translation between the cell's centroids"
    calls: list = []

    def register(self, source, target, *, source_normals, target_normals, cell_size_m) -> Registration:
        T = np.eye(4)
        T[:3, 3] = target.mean(0) - source.mean(0)
        reg = Registration(T, 1.0, 0.0, min(len(source), len(target)))
        type(self).calls.append((source.shape, target.shape, source_normals, cell_size_m, reg))
        return reg


class MedianDepthRule(DecisionRule):
    name = "test_depth_step"
    description = "test rule: RM when the cells' median z shift exceeds 5 mm, else NM"

    def decide(self, cells, *, source, target) -> RuleDecision:
        dz = np.median([c.registration.T_target_from_source[2, 3] for c in cells if c.matched])
        clusters = [0 if c.matched else None for c in cells]
        return RuleDecision(
            "RM" if abs(dz) > 0.005 else "NM",
            clusters,
            [f"dz {dz:+.4f} m"],
            reason="median z shift",
            info=dict(dz_m=float(dz)),
        )


def _hinge_folder(tmp_path: Path, motion: str = "hinge") -> Path:
    folder = tmp_path / f"hinge_{motion}"
    folder.mkdir()
    (folder / "hinge.txt").write_text(motion)
    return folder


def _plugin(hook: str, *classes) -> SimpleNamespace:
    """A plugin object whose ``hook`` registers ``classes``."""

    @hookimpl(specname=hook)
    def impl(register):
        for cls in classes:
            register(cls)

    return SimpleNamespace(impl=impl, __name__=f"test plugin for {hook}")


READER = _plugin("register_readers", HingeReader)
SEGMENTER = _plugin("register_segmenters", BandSegmenter)


def test_hook_register_readers(tmp_path):
    registry = load_registry(extra_plugins=(READER,))
    assert "test_hinge" in registry.names("reader")
    assert "folder" in registry.names("reader")  # built-ins are still there
    seqs = open_sequences(registry, _hinge_folder(tmp_path))
    assert [type(s) for s in seqs] == [HingeSequence]
    frame = seqs[0][1]
    assert frame.depth_m.shape == (120, 160) and frame.depth_m.max() > 0.55
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "hinge.txt").write_text("wobble")
    with pytest.raises(InputError, match="hinge.txt: unknown motion 'wobble'"):
        open_sequences(registry, bad)
    with pytest.raises(InputError, match="not a sequence that any reader recognises"):
        open_sequences(registry, tmp_path)


def test_hook_register_segmenters(tmp_path):
    registry = load_registry(extra_plugins=(READER, SEGMENTER))
    seq = open_sequences(registry, _hinge_folder(tmp_path))[0]
    pipe = Pipeline(registry, Config(segmenter="test_band", pipeline=PipelineParams(k=1)))
    fr = pipe.frame(seq, 0)
    assert fr.mask_pixels == int(np.count_nonzero(seq[0].depth_m)) > 1000
    narrow = Config(segmenter="test_band", segmenter_params=BandParams(near_m=0.0, far_m=0.1))
    assert Pipeline(registry, narrow).frame(seq, 0).skipped == "no object found"


def test_hook_register_preprocessors(tmp_path):
    registry = load_registry(
        extra_plugins=(READER, SEGMENTER, _plugin("register_preprocessors", StridePreprocessor))
    )
    seq = open_sequences(registry, _hinge_folder(tmp_path))[0]
    config = Config(
        segmenter="test_band",
        preprocessor="test_stride",
        preprocessor_params=StrideParams(stride=3),
        registrar="icp_point_to_point",
        pipeline=PipelineParams(k=1),
    )
    result = Pipeline(registry, config).run(seq)
    n_pixels = int(np.count_nonzero(seq[0].depth_m))
    assert result.frames[0].info == dict(n_points=len(range(0, n_pixels, 3)), stride=3)
    assert result.params["preprocessor"] == dict(stride=3)
    assert result.plugins["preprocessor"] == "test_stride"


def test_hook_register_registrars(tmp_path):
    CentroidShiftRegistrar.calls = []
    registry = load_registry(
        extra_plugins=(READER, SEGMENTER, _plugin("register_registrars", CentroidShiftRegistrar))
    )
    seq = open_sequences(registry, _hinge_folder(tmp_path, "carry"))[0]
    config = Config(segmenter="test_band", registrar="test_centroid_shift", pipeline=PipelineParams(k=1))
    result = Pipeline(registry, config).run(seq)
    registered = [c for p in result.pairs for c in p.cells if c.registration is not None]
    assert registered and result.plugins["registrar"] == "test_centroid_shift"
    # Every cell's registration is one our registrar returned (the pipeline may also call it on
    # whole clouds, e.g. to pre-align them, so there can be more calls than cells).
    returned = {id(call[-1]): call for call in CentroidShiftRegistrar.calls}
    assert len(returned) >= len(registered)
    for cell in registered:
        src_shape, tgt_shape, normals, x, _ = returned[id(cell.registration)]
        assert src_shape == (len(cell.source_idx), 3) and tgt_shape == (len(cell.target_idx), 3)
        assert normals is not None and normals.shape == src_shape  # the preprocessor supplies normals
        assert x == pytest.approx(
            next(p.cell_size_m for p in result.pairs if any(c is cell for c in p.cells))
        )
    # the whole object moved 10 mm towards +z per frame: the registrar's z shifts say so
    dz = np.median([c.registration.T_target_from_source[2, 3] for c in registered])
    assert dz == pytest.approx(0.01, abs=0.003)


def test_hook_register_rules(tmp_path):
    registry = load_registry(extra_plugins=(READER, SEGMENTER, _plugin("register_rules", MedianDepthRule)))
    config = Config(segmenter="test_band", rule="test_depth_step", pipeline=PipelineParams(k=1, alpha=0.0))
    moving = Pipeline(registry, config).run(open_sequences(registry, _hinge_folder(tmp_path, "carry"))[0])
    assert moving.plugins["rule"] == "test_depth_step"
    assert moving.label == "rigid" and moving.fractions["RM"] == 1.0
    assert all(p.reason == "median z shift" and p.info["dz_m"] > 0.005 for p in moving.pairs)
    cells = [c for p in moving.pairs for c in p.cells if c.matched]
    assert cells and all(c.cluster == 0 and c.key.startswith("dz +0.0") for c in cells)


def test_hook_register_commands(capsys):
    def hello(args) -> int:
        print(f"hello {args.who}")
        return 7

    @hookimpl
    def register_commands(subparsers):
        p = subparsers.add_parser("test-hello", help="say hello")
        p.add_argument("who")
        p.set_defaults(func=hello)

    registry = load_registry(extra_plugins=(SimpleNamespace(register_commands=register_commands),))
    parser = build_parser(registry)
    args = parser.parse_args(["test-hello", "plugins"])
    assert args.func(args) == 7
    assert capsys.readouterr().out == "hello plugins\n"
    with pytest.raises(SystemExit):
        parser.parse_args(["test-goodbye"])


def test_a_duplicate_name_names_both_plugins():
    class Impostor(MedianDepthRule):
        name = "paper"

    with pytest.raises(PluginError, match="rule name 'paper' is registered twice: by artclass_plugins.rules"):
        load_registry(extra_plugins=(_plugin("register_rules", Impostor),))


def test_a_badly_formed_class_is_refused():
    class NoMethod:
        name = "test_nothing"
        description = "has no decide"
        Params = Params

    with pytest.raises(PluginError, match="missing method `decide`"):
        load_registry(extra_plugins=(_plugin("register_rules", NoMethod),))
