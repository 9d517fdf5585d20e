"""Ground truth of a simulated robot, for evaluation only: what the emulated servo's
hidden parameters imply, and the soles' contact forces and centres of pressure from
the plant's contact results. Estimators, identification and controllers never read
it."""

from collections.abc import Sequence

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.multibody.plant import ContactResults, MultibodyPlant
from pydrake.systems.framework import Context, LeafSystem

from hrp2_drake.description import RobotDescription
from hrp2_drake.identification.motor_model import MotorModel
from hrp2_drake.robot.servo import effective_motor_parameters, load_servo_params


def true_motor_model(
    robot: RobotDescription,
    joint_names: Sequence[str] = (),
    direction: int = 0,
    servo_file: str = "",
) -> MotorModel:
    """The emulated servo's effective Kτ, Kv, Kc of `joint_names` (default: the
    robot's controlled joints). `servo_file` as `StationConfig.servo_file` (empty:
    the description's servo_file)."""
    joints = list(joint_names or robot.controlled_joints)
    params = load_servo_params(servo_file, robot.source_file)
    eff = effective_motor_parameters(params, joints, direction)
    return MotorModel(joints, eff["k_tau"], eff["k_v"], eff["k_c"])


class SoleContacts(LeafSystem):
    """Each sole's contact force and centre of pressure, from the plant's contact
    results: ground truth, for evaluation only.

    .. code-block:: text

                         ┌──────────────┐
        contact_results ►│ SoleContacts ├──► soles (5 per sole)
                         └──────────────┘

    Output: per sole [f_x, f_y, f_z, p_x, p_y]: the total force the ground exerts on
    the sole's body (N, world) and its centre of pressure on the ground (m, world;
    NaN when the sole carries no normal force). Point contacts only (the station's).
    """

    def __init__(self, plant: MultibodyPlant, soles: list[str]):
        super().__init__()
        # Each sole's body and every body welded to it (the contact geometry may sit
        # on a welded link).
        self._bodies = [
            {b.index() for b in plant.GetBodiesWeldedTo(plant.GetFrameByName(s).body())}
            for s in soles
        ]
        self._results = self.DeclareAbstractInputPort(
            "contact_results", AbstractValue.Make(ContactResults())
        )
        self.DeclareVectorOutputPort("soles", 5 * len(soles), self._calc)

    def _calc(self, context: Context, output) -> None:
        results = self._results.Eval(context)
        force = np.zeros((len(self._bodies), 3))
        moment = np.zeros((len(self._bodies), 2))
        for i in range(results.num_point_pair_contacts()):
            info = results.point_pair_contact_info(i)
            for sign, body in ((1.0, info.bodyB_index()), (-1.0, info.bodyA_index())):
                for k, bodies in enumerate(self._bodies):
                    if body not in bodies:
                        continue
                    f = sign * info.contact_force()
                    force[k] += f
                    moment[k] += f[2] * info.contact_point()[:2]
        values = np.full((len(self._bodies), 5), np.nan)
        values[:, :3] = force
        loaded = force[:, 2] > 1e-9
        values[loaded, 3:] = moment[loaded] / force[loaded, 2:3]
        output.set_value(values.ravel())
