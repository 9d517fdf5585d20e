#!/usr/bin/env python3
"""Generate the HRP-2 model files in models/hrp2/ from the public reference data.

Inputs (see ../shared/data/README.md):
  - hrp2.rob: HRP-2's kinematic and inertial parameters (Klampt format).
  - hrp2_climbing32.pos: the stair-climbing joint trajectory (time + 40 columns).

Outputs (committed, do not edit by hand):
  - models/hrp2/hrp2.urdf: plain URDF plus `drake:` tags (rotor inertia and gear ratio
    in <transmission>, contact properties). Feet are split at the ankle F/T sensors and
    hands at the wrist F/T sensors by fixed joints; sole and IMU frames are massless
    links on fixed joints, so any URDF tool sees them.
  - models/hrp2/servo_ideal.yaml: the `ideal` preset of the emulated position servo,
    per joint, chosen so that the effective motor model (Kτ, Kv) of the right leg equals
    the paper's Table 1 (see models/hrp2/README.md for every choice). It is the prior
    that `hrp2-drake calibrate` starts from; the calibrated servo.yaml is its output.
  - models/hrp2/climbing32.pos.gz: the trajectory, time + the 30 modelled joints.

Usage:
  python scripts/make_hrp2_model.py [--data ../shared/data]
"""

from __future__ import annotations

import argparse
import gzip
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "models" / "hrp2"

# ---------------------------------------------------------------------------------
# Values not in hrp2.rob (sources in models/hrp2/README.md).
# ---------------------------------------------------------------------------------
ANKLE_TO_SOLE = 0.105  # m, sot-torque-control
ANKLE_TO_FOOT_FT = 0.085  # m, sot-torque-control
WRIST_FT_XYZ = (0.005, 0.0, -0.05925)  # m, in the last arm link (wrist pitch link)
WRIST_FT_YAW = -math.pi / 2  # rad, sensor frame rotated -90 deg about z
IMU_XYZ = (-0.13, 0.0, 0.118)  # m, in CHEST_LINK1
SOLE_X = (-0.105, 0.135)  # m, sole extent along x in the sole frame (0.24 m)
SOLE_Y = (-0.07, 0.07)  # m, sole extent along y (0.14 m)
SOLE_THICKNESS = 0.02  # m, foot plate between F/T sensor and sole
CONTACT_SPHERE_RADIUS = 0.005  # m, corner spheres of the sole

# Split of the ankle-roll (wrist-pitch) link at the F/T sensor: the COM height, in the
# original link frame, assumed for the part above the sensor and for the part below it.
# The masses follow from keeping the link's total mass and COM (see README).
SPLIT_COM_Z = {
    "foot": (-0.045, -0.095),  # ankle housing + sensor; foot plate below the sensor
    "hand": (-0.040, -0.100),  # wrist housing + sensor; palm below the sensor
}
FOOT_BOX = (0.24, 0.14, 0.02)  # m, inertia shape of the foot below the sensor
HAND_BOX = (0.06, 0.08, 0.10)  # m, inertia shape of the hand below the sensor


@dataclass
class Actuator:
    """HRP-2-like actuator choices (approximations, see README)."""

    gear_ratio: float  # harmonic drive + belt
    rotor_inertia: float  # kg m^2, motor side
    torque_constant: float  # N m / A, motor side, times drive efficiency
    k_tau: float  # target effective Kτ, rad / (N m)
    k_v: float  # target effective Kv, s
    coulomb: float  # N m, K3
    i_deadzone: float  # A
    i_max: float  # A
    asymmetry: float  # K1± = K1 (1 ± asymmetry)


# Right leg: the paper's Table 1 (10^3 kτ, 10^3 kv).
TABLE1 = {
    "hip_yaw": (0.212e-3, 13.0e-3),
    "hip_roll": (0.030e-3, 6.332e-3),
    "hip_pitch": (0.12e-3, 7.0e-3),
    "knee": (0.051e-3, 6.561e-3),
    "ankle_pitch": (0.177e-3, 7.698e-3),
    "ankle_roll": (0.240e-3, 6.0e-3),
}
LEG_GEAR = (160.0, 200.0, 180.0, 200.0, 180.0, 160.0)
LEG_ROTOR = 1.34e-5  # 150 W class brushed DC motor
ARM_ROTOR = 6.9e-6  # 90 W class
SMALL_ROTOR = 1.0e-6  # 20 W class (head, wrists)
GRIPPER_ROTOR = 5.0e-7
VISCOUS_PHYSICAL_SHARE = 0.2  # share of Kv/Kτ that is real viscous friction K2
V_COULOMB = 0.05  # rad/s, smoothing of sign(q̇) in the friction and K1± blend
ENCODER_COUNTS = 4000  # motor-side counts per revolution (1000-line quadrature)


def leg_actuators() -> list[Actuator]:
    return [
        Actuator(g, LEG_ROTOR, 0.024, kt, kv, 2.0, 0.3, 40.0, 0.08)
        for g, (kt, kv) in zip(LEG_GEAR, TABLE1.values())
    ]


def other_actuators() -> dict[str, Actuator]:
    chest = Actuator(160.0, LEG_ROTOR, 0.024, 0.10e-3, 8.0e-3, 2.0, 0.3, 40.0, 0.05)
    head = Actuator(120.0, SMALL_ROTOR, 0.012, 2.0e-3, 10.0e-3, 0.2, 0.2, 10.0, 0.05)
    shoulder = Actuator(160.0, ARM_ROTOR, 0.020, 0.5e-3, 8.0e-3, 2.0, 0.3, 20.0, 0.05)
    wrist = Actuator(120.0, SMALL_ROTOR, 0.012, 2.0e-3, 10.0e-3, 0.2, 0.2, 10.0, 0.05)
    gripper = Actuator(
        100.0, GRIPPER_ROTOR, 0.010, 20.0e-3, 50.0e-3, 0.05, 0.1, 5.0, 0.0
    )
    arm = [shoulder] * 4 + [wrist] * 2 + [gripper]
    out = {"CHEST_JOINT0": chest, "CHEST_JOINT1": chest}
    out |= {"HEAD_JOINT0": head, "HEAD_JOINT1": head}
    for side in ("RARM", "LARM"):
        out |= {f"{side}_JOINT{i}": a for i, a in enumerate(arm)}
    return out


def servo_parameters(a: Actuator) -> dict[str, float]:
    """Servo gains (paper eq. 3, 5) that give the target effective Kτ and Kv.

    Kτ = 1 / (K1 K4), Kv = (K1 K5 + K2) / (K1 K4) (docs/architecture.md).
    """
    k1 = a.torque_constant * a.gear_ratio
    k4 = 1.0 / (k1 * a.k_tau)
    damping = a.k_v / a.k_tau  # N m s / rad, total = K1 K5 + K2
    k2 = VISCOUS_PHYSICAL_SHARE * damping
    k5 = (damping - k2) / k1
    return dict(
        k1=k1,
        k1_asymmetry=a.asymmetry,
        k2=k2,
        k3=a.coulomb,
        k4=k4,
        k5=k5,
        i_deadzone=a.i_deadzone,
        i_max=a.i_max,
        v_coulomb=V_COULOMB,
        encoder_resolution=2 * math.pi / (ENCODER_COUNTS * a.gear_ratio),
    )


# ---------------------------------------------------------------------------------
# hrp2.rob parsing
# ---------------------------------------------------------------------------------
def read_rob(path: Path) -> dict[str, list[str]]:
    text = path.read_text().replace("\\\n", " ")
    fields: dict[str, list[str]] = {}
    for line in text.splitlines():
        parts = line.split()
        if parts and not parts[0].startswith("#"):
            fields.setdefault(parts[0], parts[1:])
    return fields


@dataclass
class Link:
    name: str
    parent: str | None
    joint: str | None
    xyz: np.ndarray  # joint origin in the parent link frame
    rpy: tuple[float, float, float]
    axis: np.ndarray
    lower: float
    upper: float
    mass: float
    com: np.ndarray
    inertia: np.ndarray  # about the COM, link frame
    actuator: Actuator | None = None


def rob_links(rob: dict[str, list[str]]) -> list[Link]:
    names = [s.strip('"') for s in rob["links"]]
    parents = [int(p) for p in rob["parents"]]
    axis = np.array(rob["axis"], float).reshape(-1, 3)
    tparent = np.array(rob["Tparent"], float).reshape(-1, 12)
    mass = np.array(rob["mass"], float)
    com = np.array(rob["com"], float).reshape(-1, 3)
    inertia = np.array(rob["inertia"], float).reshape(-1, 3, 3)
    qmin = np.radians(np.array(rob["qmindeg"], float))
    qmax = np.radians(np.array(rob["qmaxdeg"], float))
    assert np.allclose(tparent[6:, :9], np.eye(3).T.ravel()), "non-identity rotation"
    base = 5  # the six base coordinates are 0-5; 5 carries the waist body
    link_name = {base: "BODY"}
    for i in range(base + 1, len(names)):
        link_name[i] = names[i].replace("JOINT", "LINK")
    links = [
        Link(
            "BODY",
            None,
            None,
            np.zeros(3),
            (0, 0, 0),
            np.zeros(3),
            0,
            0,
            mass[base],
            com[base],
            sym(inertia[base]),
        )
    ]
    for i in range(base + 1, len(names)):
        links.append(
            Link(
                link_name[i],
                link_name[parents[i]],
                names[i],
                tparent[i, 9:],
                (0.0, 0.0, 0.0),
                axis[i],
                qmin[i],
                qmax[i],
                mass[i],
                com[i],
                sym(inertia[i]),
            )
        )
    return links


def sym(a: np.ndarray) -> np.ndarray:
    return 0.5 * (a + a.T)


def box_inertia(m: float, size: tuple[float, float, float]) -> np.ndarray:
    x, y, z = size
    return m / 12.0 * np.diag([y * y + z * z, x * x + z * z, x * x + y * y])


def shift(m: float, d: np.ndarray) -> np.ndarray:
    """Parallel-axis term m (|d|^2 I - d d^T)."""
    return m * (d @ d * np.eye(3) - np.outer(d, d))


def is_physical(inertia: np.ndarray) -> bool:
    ev = np.linalg.eigvalsh(inertia)
    return ev.min() > 0 and 2 * ev.max() <= ev.sum() + 1e-12


def split_link(link: Link, kind: str, box: tuple[float, float, float]):
    """Split `link` into (upper, lower) mass properties keeping total mass and COM.

    Returns (m_u, com_u, I_u, m_l, com_l, I_l), COMs in the original link frame and
    inertias about the part's own COM.
    """
    z_u, z_l = SPLIT_COM_Z[kind]
    m, c = link.mass, link.com
    m_u = m * (c[2] - z_l) / (z_u - z_l)
    m_l = m - m_u
    com_u = np.array([c[0], c[1], z_u])
    com_l = np.array([c[0], c[1], z_l])
    for scale in np.linspace(1.0, 0.1, 19):
        i_l = scale * box_inertia(m_l, box)
        i_u = link.inertia - i_l - shift(m_l, com_l - c) - shift(m_u, com_u - c)
        if is_physical(i_u):
            return m_u, com_u, i_u, m_l, com_l, i_l
    raise RuntimeError(f"cannot split {link.name}")


# ---------------------------------------------------------------------------------
# URDF writing
# ---------------------------------------------------------------------------------
def f(x: float) -> str:
    return f"{x:.9g}"


def v3(v) -> str:
    return " ".join(f(float(x)) for x in v)


def inertial_xml(m: float, com, inertia: np.ndarray) -> str:
    i = inertia
    return (
        f'    <inertial>\n      <origin xyz="{v3(com)}" rpy="0 0 0"/>\n'
        f'      <mass value="{f(m)}"/>\n'
        f'      <inertia ixx="{f(i[0, 0])}" ixy="{f(i[0, 1])}" ixz="{f(i[0, 2])}" '
        f'iyy="{f(i[1, 1])}" iyz="{f(i[1, 2])}" izz="{f(i[2, 2])}"/>\n    </inertial>\n'
    )


def segment_visual(p0, p1, radius: float, color: str) -> str:
    """A cylinder from p0 to p1 (link frame)."""
    from pydrake.math import RollPitchYaw, RotationMatrix

    d = np.asarray(p1, float) - np.asarray(p0, float)
    length = float(np.linalg.norm(d))
    if length < 1e-6:
        return sphere_visual(p0, radius, color)
    rpy = RollPitchYaw(RotationMatrix.MakeFromOneVector(d / length, 2)).vector()
    mid = 0.5 * (np.asarray(p0) + np.asarray(p1))
    return (
        f'    <visual>\n      <origin xyz="{v3(mid)}" rpy="{v3(rpy)}"/>\n'
        f'      <geometry><cylinder radius="{f(radius)}" length="{f(length)}"/>'
        "</geometry>\n"
        f'      <material name="{color}"/>\n    </visual>\n'
    )


def sphere_visual(p, radius: float, color: str) -> str:
    return (
        f'    <visual>\n      <origin xyz="{v3(p)}" rpy="0 0 0"/>\n'
        f'      <geometry><sphere radius="{f(radius)}"/></geometry>\n'
        f'      <material name="{color}"/>\n    </visual>\n'
    )


def box_visual(p, size, color: str, rpy=(0, 0, 0)) -> str:
    return (
        f'    <visual>\n      <origin xyz="{v3(p)}" rpy="{v3(rpy)}"/>\n'
        f'      <geometry><box size="{v3(size)}"/></geometry>\n'
        f'      <material name="{color}"/>\n    </visual>\n'
    )


def sole_collisions(z_sole: float) -> str:
    r = CONTACT_SPHERE_RADIUS
    out = ""
    for k, (x, y) in enumerate([(x, y) for x in SOLE_X for y in SOLE_Y]):
        out += (
            f'    <collision name="sole_corner_{k}">\n'
            f'      <origin xyz="{v3((x, y, z_sole + r))}" rpy="0 0 0"/>\n'
            f'      <geometry><sphere radius="{f(r)}"/></geometry>\n'
            "      <drake:proximity_properties>\n"
            '        <drake:mu_dynamic value="1.0"/>\n'
            '        <drake:mu_static value="1.0"/>\n'
            "      </drake:proximity_properties>\n"
            "    </collision>\n"
        )
    return out


def fixed_joint(name: str, parent: str, child: str, xyz, rpy=(0, 0, 0)) -> str:
    return (
        f'  <joint name="{name}" type="fixed">\n'
        f'    <parent link="{parent}"/>\n    <child link="{child}"/>\n'
        f'    <origin xyz="{v3(xyz)}" rpy="{v3(rpy)}"/>\n  </joint>\n'
    )


def write_urdf(links: list[Link], servo: dict[str, dict]) -> str:
    children: dict[str, list[Link]] = {}
    for link in links:
        if link.parent:
            children.setdefault(link.parent, []).append(link)

    out = [
        '<?xml version="1.0"?>\n',
        "<!-- Generated by scripts/make_hrp2_model.py from ../shared/data/hrp2.rob;\n"
        "     do not edit by hand. Sources of every number: models/hrp2/README.md. "
        "-->\n",
        '<robot name="hrp2" xmlns:drake="http://drake.mit.edu">\n',
        '  <material name="grey"><color rgba="0.7 0.7 0.72 1"/></material>\n',
        '  <material name="blue"><color rgba="0.25 0.35 0.7 1"/></material>\n',
        '  <material name="dark"><color rgba="0.2 0.2 0.2 1"/></material>\n',
        '  <material name="sensor"><color rgba="0.9 0.6 0.1 1"/></material>\n',
    ]
    extra: list[str] = []
    for link in links:
        kind = None
        if link.name.endswith("LEG_LINK5"):
            kind = "foot"
        elif link.name.endswith("ARM_LINK5"):
            kind = "hand"
        visuals = ""
        color = "blue" if "LEG" in link.name or "ARM" in link.name else "grey"
        for ch in children.get(link.name, []):
            visuals += segment_visual(
                (0, 0, 0), ch.xyz, 0.035 if "LEG" in link.name else 0.03, color
            )
        if link.name == "BODY":
            visuals += box_visual((-0.01, 0, 0.12), (0.2, 0.24, 0.2), "grey")
        elif link.name == "CHEST_LINK1":
            visuals += box_visual((-0.03, 0, 0.15), (0.24, 0.32, 0.3), "grey")
        elif link.name == "HEAD_LINK1":
            visuals += sphere_visual((0, 0, 0.1), 0.1, "grey")
        if kind is None:
            visuals += sphere_visual(link.com, 0.025, "dark")
            if link.name.endswith("ARM_LINK6"):
                visuals += box_visual((0, 0, -0.05), (0.02, 0.02, 0.1), "dark")
            out.append(f'  <link name="{link.name}">\n')
            out.append(inertial_xml(link.mass, link.com, link.inertia))
            out.append(visuals + "  </link>\n")
        else:
            box = FOOT_BOX if kind == "foot" else HAND_BOX
            m_u, com_u, i_u, m_l, com_l, i_l = split_link(link, kind, box)
            side = link.name.split("_")[0]  # RLEG, LLEG, RARM, LARM
            out.append(f'  <link name="{link.name}">\n')
            out.append(inertial_xml(m_u, com_u, i_u))
            out.append(visuals + sphere_visual((0, 0, 0), 0.04, color) + "  </link>\n")
            if kind == "foot":
                p_s = np.array([0.0, 0.0, -ANKLE_TO_FOOT_FT])
                yaw = 0.0
                lower = f"{side}_FOOT"
                sole = ANKLE_TO_FOOT_FT - ANKLE_TO_SOLE  # sole z in the foot frame
            else:
                p_s = np.array(WRIST_FT_XYZ)
                yaw = WRIST_FT_YAW
                lower = f"{side}_HAND"
            rz = np.array(
                [
                    [math.cos(yaw), -math.sin(yaw), 0],
                    [math.sin(yaw), math.cos(yaw), 0],
                    [0, 0, 1],
                ]
            )
            # Lower part, expressed in the sensor frame (origin p_s, rotation rz).
            com_s = rz.T @ (com_l - p_s)
            i_s = rz.T @ i_l @ rz
            lower_xml = f'  <link name="{lower}">\n' + inertial_xml(m_l, com_s, i_s)
            lower_xml += sphere_visual((0, 0, 0), 0.03, "sensor")
            if kind == "foot":
                cx = 0.5 * (SOLE_X[0] + SOLE_X[1])
                lower_xml += box_visual(
                    (cx, 0, sole + SOLE_THICKNESS / 2),
                    (SOLE_X[1] - SOLE_X[0], SOLE_Y[1] - SOLE_Y[0], SOLE_THICKNESS),
                    "dark",
                )
                lower_xml += sole_collisions(sole)
            else:
                lower_xml += box_visual(rz.T @ (com_l - p_s), HAND_BOX, "dark")
            out.append(lower_xml + "  </link>\n")
            extra.append(
                fixed_joint(f"{side}_FT_SENSOR", link.name, lower, p_s, (0, 0, yaw))
            )
            if kind == "foot":
                sole_link = f"{side[0].lower()}_sole"
                out.append(f'  <link name="{sole_link}"/>\n')
                extra.append(
                    fixed_joint(f"{sole_link}_joint", lower, sole_link, (0, 0, sole))
                )
            # Re-parent the children (the gripper) onto the lower part, keeping their
            # pose: joint frame expressed in the sensor frame.
            for ch in children.get(link.name, []):
                ch.parent = lower
                ch.xyz = rz.T @ (ch.xyz - p_s)
                ch.rpy = (0.0, 0.0, -yaw)
    out.append('  <link name="imu"/>\n')
    extra.append(fixed_joint("imu_joint", "CHEST_LINK1", "imu", IMU_XYZ))

    for link in links:
        if link.joint is None:
            continue
        sp = servo[link.joint]
        a = link.actuator
        # Never reached by the servo: Drake clamps actuation at the effort limit, so
        # leave room for motor torque plus friction while braking at 2x velmax.
        effort = (
            sp["k1"] * (1 + sp["k1_asymmetry"]) * sp["i_max"]
            + 6.0 * sp["k2"]
            + sp["k3"]
        )
        out.append(
            f'  <joint name="{link.joint}" type="revolute">\n'
            f'    <parent link="{link.parent}"/>\n    <child link="{link.name}"/>\n'
            f'    <origin xyz="{v3(link.xyz)}" rpy="{v3(link.rpy)}"/>\n'
            f'    <axis xyz="{v3(link.axis)}"/>\n'
            f'    <limit lower="{f(link.lower)}" upper="{f(link.upper)}" '
            f'effort="{f(effort)}" velocity="3"/>\n'
            '    <dynamics damping="0" friction="0"/>\n'
            "  </joint>\n"
        )
        out.append(
            f'  <transmission name="{link.joint}_transmission">\n'
            "    <type>transmission_interface/SimpleTransmission</type>\n"
            f'    <joint name="{link.joint}">\n'
            "      <hardwareInterface>EffortJointInterface</hardwareInterface>\n"
            "    </joint>\n"
            f'    <actuator name="{link.joint}_motor">\n'
            f'      <drake:rotor_inertia value="{f(a.rotor_inertia)}"/>\n'
            f'      <drake:gear_ratio value="{f(a.gear_ratio)}"/>\n'
            "    </actuator>\n  </transmission>\n"
        )
    out.extend(extra)
    out.append("</robot>\n")
    return "".join(out)


def write_servo_yaml(servo: dict[str, dict]) -> str:
    lines = [
        (
            "# The `ideal` preset of the emulated HRP-2 position servo "
            "(docs/architecture.md): the"
        ),
        (
            "# paper's eq. 6 with a small dead zone and Coulomb term, no latency, no "
            "voltage"
        ),
        (
            "# limit, direction switching at sign(q_dot). For tests of the exact "
            "linear law;"
        ),
        "# the simulated robot uses the calibrated servo.yaml (hrp2-drake calibrate).",
        "# Generated by scripts/make_hrp2_model.py; sources in models/hrp2/README.md.",
        "# Only hrp2_drake/robot/ reads this file: estimation, identification and",
        "# control must find everything from signals, as on the real robot.",
        "# Units: k1 N m/A, k2 N m s/rad, k3 N m, k4 A/rad, k5 A s/rad, i_* A,",
        "# v_coulomb rad/s, encoder_resolution rad.",
        "joints:",
    ]
    for name, p in servo.items():
        lines.append(f"  {name}:")
        lines += [f"    {k}: {v:.9g}" for k, v in p.items()]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    parser.add_argument("--out", type=Path, default=OUT, help="default: models/hrp2")
    args = parser.parse_args()
    out = args.out

    links = rob_links(read_rob(args.data / "hrp2.rob"))
    joints = [l for l in links if l.joint]
    actuators = dict(zip([l.joint for l in joints[:6]], leg_actuators()))
    actuators |= dict(zip([l.joint for l in joints[6:12]], leg_actuators()))
    actuators |= other_actuators()
    for link in joints:
        link.actuator = actuators[link.joint]
    servo = {l.joint: servo_parameters(l.actuator) for l in joints}

    out.mkdir(parents=True, exist_ok=True)
    (out / "hrp2.urdf").write_text(write_urdf(links, servo))
    (out / "servo_ideal.yaml").write_text(write_servo_yaml(servo))

    traj = np.loadtxt(args.data / "hrp2_climbing32.pos")[:, :31]
    with gzip.GzipFile(out / "climbing32.pos.gz", "wb", mtime=0) as stream:
        np.savetxt(stream, traj, fmt="%.7g")  # mtime=0: reproducible bytes
    print(
        f"wrote {out}/hrp2.urdf, servo_ideal.yaml, climbing32.pos.gz "
        f"({len(joints)} joints, {sum(l.mass for l in links):.3f} kg)"
    )


if __name__ == "__main__":
    main()
