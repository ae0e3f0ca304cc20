"""URDF export: the file a maintained parser (yourdfpy) loads describes the tree that was written."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import yourdfpy

from artclass_core import InputError
from artclass_core.cli import main
from artclass_core.interfaces import JointEstimate
from artclass_plugins.joints.urdf import ArticulatedModel, Joint, Link, joint_from_estimate, write_urdf

rng = np.random.default_rng(0)
BOX = rng.uniform([-0.2, -0.1, 0.0], [0.2, 0.1, 0.3], (300, 3))  # the base, metres
LID = rng.uniform([-0.2, 0.0, -0.01], [0.2, 0.2, 0.01], (200, 3))  # the lid in its hinge frame
DRAWER = rng.uniform([-0.1, -0.1, -0.05], [0.1, 0.1, 0.05], (200, 3))
HINGE = np.array([0.0, 0.1, 0.3])


def lid_and_drawer() -> ArticulatedModel:
    lid = JointEstimate(
        "revolute",
        np.array([1.0, 0.0, 0.0]),
        HINGE,
        np.array([0.0, 0.4, 1.2, np.nan]),
        np.array([True, True, True, False]),
    )
    T_drawer = np.eye(4)
    T_drawer[:3, 3] = [0.0, -0.1, 0.1]
    return ArticulatedModel(
        "box",
        (Link("base", BOX), Link("lid", LID), Link("drawer", DRAWER)),
        (
            joint_from_estimate(lid, name="hinge", parent="base", child="lid"),
            Joint("slide", "base", "drawer", "prismatic", T_drawer, np.array([0.0, -1.0, 0.0]), (0.0, 0.25)),
        ),
    )


def test_urdf_round_trip_through_yourdfpy(tmp_path):
    path = write_urdf(lid_and_drawer(), tmp_path / "out")
    robot = yourdfpy.URDF.load(str(path), build_scene_graph=True, load_meshes=True)
    assert robot.base_link == "base"
    assert set(robot.link_map) == {"base", "lid", "drawer"}
    hinge, slide = robot.joint_map["hinge"], robot.joint_map["slide"]
    assert (hinge.type, hinge.parent, hinge.child) == ("revolute", "base", "lid")
    assert (slide.type, slide.parent, slide.child) == ("prismatic", "base", "drawer")
    np.testing.assert_allclose(hinge.axis, [1, 0, 0])
    np.testing.assert_allclose(slide.axis, [0, -1, 0])
    assert (hinge.limit.lower, hinge.limit.upper) == pytest.approx((0.0, 1.2))
    assert (slide.limit.lower, slide.limit.upper) == pytest.approx((0.0, 0.25))
    np.testing.assert_allclose(hinge.origin[:3, 3], HINGE)
    # the meshes load: each link's hull holds its points
    for name, points in (("base", BOX), ("lid", LID), ("drawer", DRAWER)):
        assert robot.link_map[name].visuals[0].geometry.mesh.filename == f"meshes/{name}.ply"
        mesh = robot.scene.geometry[f"{name}.ply"]
        np.testing.assert_allclose(mesh.bounds, [points.min(0), points.max(0)], atol=1e-9)


def test_moving_the_joint_in_the_parser_moves_the_link(tmp_path):
    robot = yourdfpy.URDF.load(
        str(write_urdf(lid_and_drawer(), tmp_path)), build_scene_graph=True, load_meshes=False
    )
    robot.update_cfg({"hinge": np.pi / 2, "slide": 0.2})
    T_lid = robot.get_transform("lid", "base")
    # a quarter turn about +x through the hinge: the lid's +y edge now points up (+z)
    np.testing.assert_allclose(T_lid[:3, :3] @ [0, 1, 0], [0, 0, 1], atol=1e-9)
    np.testing.assert_allclose(T_lid[:3, 3], HINGE, atol=1e-9)
    np.testing.assert_allclose(robot.get_transform("drawer", "base")[:3, 3], [0.0, -0.3, 0.1], atol=1e-9)


@pytest.mark.parametrize(
    "joints, problem",
    [
        ((Joint("j", "base", "nowhere", "fixed"),), "no link named 'nowhere'"),
        ((Joint("j", "base", "lid", "screw"),), "no URDF equivalent"),
        ((Joint("a", "lid", "lid2", "fixed"), Joint("b", "lid2", "lid", "fixed")), "do not make one tree"),
    ],
)
def test_bad_models_are_refused_with_one_line(tmp_path, joints, problem):
    model = ArticulatedModel("bad", (Link("base", BOX), Link("lid", LID), Link("lid2", LID)), joints)
    with pytest.raises(InputError, match=problem) as err:
        write_urdf(model, tmp_path)
    assert "\n" not in str(err.value)


def test_a_flat_part_is_refused(tmp_path):
    flat = np.c_[rng.uniform(size=(50, 2)), np.zeros(50)]
    with pytest.raises(InputError, match="'sheet'"):
        write_urdf(ArticulatedModel("m", (Link("sheet", flat),), ()), tmp_path)


# -- the command line: a video's parts and joints, exported ---------------------------------------------

LAPTOP = Path(__file__).resolve().parents[1] / "sample_data" / "laptop_articulate"


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    out = tmp_path_factory.mktemp("urdf")
    assert main(["export", str(LAPTOP), "--urdf", str(out), "--workers", "1"]) == 0
    return out


def test_export_writes_the_laptops_hinge(exported):
    robot = yourdfpy.URDF.load(
        str(exported / "laptop_articulate.urdf"), build_scene_graph=True, load_meshes=True
    )
    assert robot.base_link == "base" and set(robot.link_map) == {"base", "part1"}
    (joint,) = robot.joint_map.values()
    assert (joint.type, joint.parent, joint.child) == ("revolute", "base", "part1")
    assert np.linalg.norm(joint.axis) == pytest.approx(1.0)
    assert (
        joint.limit.lower == pytest.approx(0.0, abs=0.02) and 0.3 < joint.limit.upper < 1.0
    )  # the lid opens
    # the lid's hull hangs near its hinge (the joint frame sits on the axis, near the part)
    lid = robot.scene.geometry["part1.ply"]
    assert np.linalg.norm(lid.bounds, axis=1).min() < 0.3


def test_export_refuses_to_write_into_the_sequence(tmp_path, capsys):
    assert main(["export", str(LAPTOP), "--urdf", str(LAPTOP / "urdf"), "--workers", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "own folder" in err
    assert not (LAPTOP / "urdf").exists()


def test_classify_json_has_parts_and_joints(capsys):
    assert main(["classify", str(LAPTOP), "--json", "--no-cells", "--workers", "1"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [p["name"] for p in out["parts"]] == ["base", "part1"]
    (joint,) = out["joints"]
    assert joint["type"] == "revolute" and (joint["parent"], joint["child"]) == (0, 1)
    assert re.fullmatch(
        r"revolute joint, axis \d+ deg from vertical, 0-\d+ deg over the video", joint["summary"]
    )
    assert len(joint["states"]) == out["sequence"]["n_frames"]
