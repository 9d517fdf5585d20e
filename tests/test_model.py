"""models/hrp2: the generated URDF is plain URDF (plus drake: tags), complete, and
what scripts/make_hrp2_model.py writes from the reference data."""

import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from pydrake.multibody.plant import MultibodyPlant

from hrp2_drake.paper import hrp2

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


def test_urdf_is_a_plain_urdf_tree():
    """What any URDF tool needs: one root link, every other link the child of
    exactly one joint, joints naming existing links, revolute joints with limits."""
    root = ET.parse(hrp2.models_dir() / hrp2.URDF_FILE).getroot()
    assert root.tag == "robot"
    links = {link.get("name") for link in root.findall("link")}
    joints = root.findall("joint")
    children = [j.find("child").get("link") for j in joints]
    assert len(children) == len(set(children))
    assert {j.find("parent").get("link") for j in joints} <= links
    assert set(children) <= links
    assert links - set(children) == {hrp2.BASE_BODY}
    revolute = [j for j in joints if j.get("type") == "revolute"]
    assert [j.get("name") for j in revolute] == list(hrp2.JOINT_NAMES)
    for joint in revolute:
        limit = joint.find("limit")
        assert float(limit.get("lower")) < float(limit.get("upper"))
        assert float(limit.get("effort")) > 0
    fixed = {j.get("name") for j in joints if j.get("type") == "fixed"}
    assert set(hrp2.FT_SENSORS.values()) <= fixed
    assert len(root.findall("transmission")) == 30


def test_model_loads_with_sensor_frames_and_reflected_inertia():
    plant = MultibodyPlant(0.0)
    hrp2.add_hrp2(plant)
    plant.Finalize()
    indexing = hrp2.hrp2_joint_indexing(plant)
    context = plant.CreateDefaultContext()
    q = plant.GetPositions(context)
    q[indexing.q] = hrp2.half_sitting()
    plant.SetPositions(context, q)
    # Soles 0.105 m below the ankles, F/T 0.085 m below (sot-torque-control).
    for side in ("r", "l"):
        sole = plant.GetFrameByName(f"{side}_sole").CalcPoseInWorld(context)
        ankle = plant.GetBodyByName(f"{side.upper()}LEG_LINK5").EvalPoseInWorld(context)
        assert ankle.translation()[2] - sole.translation()[2] == pytest.approx(0.105)
    imu = plant.GetFrameByName(hrp2.IMU_FRAME)
    torso = plant.GetFrameByName(hrp2.IMU_BODY)
    np.testing.assert_allclose(
        imu.CalcPose(context, torso).translation(), [-0.13, 0.0, 0.118], atol=1e-12
    )
    # Gear ratios of 100-200 and the reflected inertia ρ² I_r in the mass matrix.
    plant.SetPositions(context, plant.GetDefaultPositions())
    mass_matrix = plant.CalcMassMatrix(context)
    for i in plant.GetJointActuatorIndices():
        actuator = plant.get_joint_actuator(i)
        assert 100 <= actuator.default_gear_ratio() <= 200
        reflected = (
            actuator.default_rotor_inertia() * actuator.default_gear_ratio() ** 2
        )
        v = actuator.joint().velocity_start()
        assert mass_matrix[v, v] >= reflected


def test_half_sitting_is_the_first_climbing_sample():
    t, q = hrp2.load_trajectory()
    assert q.shape == (3815, 30) and t[0] == 0.0
    assert t[-1] == pytest.approx(19.07)
    np.testing.assert_allclose(
        hrp2.half_sitting()[:6],
        [0, 3.529e-4, -0.453845, 0.8727609, -0.4189159, -3.529e-4],
    )


@pytest.mark.skipif(not SHARED_DATA.is_dir(), reason="../shared/data not available")
def test_generator_reproduces_the_committed_model(tmp_path):
    subprocess.run(
        [sys.executable, REPO / "scripts" / "make_hrp2_model.py", "--out", tmp_path],
        check=True,
        capture_output=True,
    )
    for name in ("hrp2.urdf", "servo_ideal.yaml", "climbing32.pos.gz"):
        committed = (hrp2.models_dir() / name).read_bytes()
        assert (tmp_path / name).read_bytes() == committed, name
