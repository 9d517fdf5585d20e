"""The tests' wiring of a torque-controlled joint subset into a whole-robot diagram
by hand (the package wires its chains from a table: `assembly.builders`):
`make_joint_selector` takes the subset's entries of a whole-robot vector,
`JointCommandMerger` puts the subset's q_cmd back into the whole robot's command,
and `connect_inverse_dynamics` connects the inverse dynamics' τ_d and its terms to the
Δq controller of the same joints.
"""

from collections.abc import Sequence

import numpy as np
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import MatrixGain, Selector, SelectorParams

from hrp2_drake.control.inverse_dynamics import (
    TORQUE_COMPONENTS,
    InverseDynamicsController,
)
from hrp2_drake.control.torque_controller import DeltaQTorqueController


class JointCommandMerger(Selector):
    """The whole-robot position command: a full reference with the entries of the
    torque-controlled joints replaced by the torque controller's q_cmd.

    .. code-block:: text

                       ┌────────────────────┐
        q_ref ────────►│                    │
                       │ JointCommandMerger ├──► q_cmd
        q_controlled ─►│                    │
                       └────────────────────┘

    Inputs:
        q_ref (N): the position reference of every joint (rad), all_joint_names
            order: the joints not in joint_names stay position controlled.
        q_controlled (n): DeltaQTorqueController's q_cmd (rad), joint_names order.

    Output:
        q_cmd (N): q_ref with the joint_names entries replaced by q_controlled
            (direct feedthrough, no state: it is wiring).

    A Drake Selector (C++, entries copied): wiring that runs at every plant step needs
    no Python.
    """

    def __init__(self, all_joint_names: Sequence[str], joint_names: Sequence[str]):
        """
        Args:
            all_joint_names: the N joints of the command (e.g. HRP-2's JOINT_NAMES).
            joint_names: the n torque-controlled joints, each among all_joint_names.

        Raises:
            KeyError: a joint of joint_names is not in all_joint_names.
            ValueError: duplicated names.
        """
        rows = _selection_rows(all_joint_names, joint_names, "JointCommandMerger")
        N, n = len(all_joint_names), len(joint_names)
        # Entry i of q_cmd: q_ref[i], or q_controlled[k] if joint i is controlled
        # joint k.
        source = {i: (0, i) for i in range(N)} | {
            int(row): (1, k) for k, row in enumerate(rows)
        }
        Params = SelectorParams
        super().__init__(
            Params(
                inputs=[
                    Params.InputPortParams(name="q_ref", size=N),
                    Params.InputPortParams(name="q_controlled", size=n),
                ],
                outputs=[
                    Params.OutputPortParams(
                        name="q_cmd",
                        selections=[
                            Params.OutputSelection(
                                input_port_index=port, input_offset=k
                            )
                            for port, k in (source[i] for i in range(N))
                        ],
                    )
                ],
            )
        )


def _selection_rows(
    all_joint_names: Sequence[str], joint_names: Sequence[str], where: str
) -> np.ndarray:
    all_joint_names, joint_names = list(all_joint_names), list(joint_names)
    for names, what in (
        (all_joint_names, "all_joint_names"),
        (joint_names, "joint_names"),
    ):
        duplicates = sorted({j for j in names if names.count(j) > 1})
        if duplicates:
            raise ValueError(f"{where}: duplicated joints {duplicates} in {what}")
    missing = [j for j in joint_names if j not in all_joint_names]
    if missing:
        raise KeyError(f"{where}: joints {missing} are not among all_joint_names")
    return np.array([all_joint_names.index(j) for j in joint_names], dtype=int)


def make_joint_selector(
    all_joint_names: Sequence[str], joint_names: Sequence[str]
) -> MatrixGain:
    """A MatrixGain (ports u0 → y0) that selects the joint_names entries of an
    all_joint_names vector, e.g. the right leg's q_measured from the station's."""
    rows = _selection_rows(all_joint_names, joint_names, "make_joint_selector")
    select = np.zeros((len(rows), len(all_joint_names)))
    select[np.arange(len(rows)), rows] = 1.0
    return MatrixGain(select)


def connect_inverse_dynamics(
    builder: DiagramBuilder,
    inverse_dynamics: InverseDynamicsController,
    torque_controller: DeltaQTorqueController,
) -> None:
    """Connects tau_desired and the five tau_* terms of `inverse_dynamics` to
    `torque_controller` (both already in `builder`, for the same joints)."""
    if tuple(inverse_dynamics.joint_names()) != tuple(torque_controller.joint_names()):
        raise ValueError(
            "connect_inverse_dynamics: the controllers' joints differ: "
            f"{inverse_dynamics.joint_names()} vs {torque_controller.joint_names()}"
        )
    for name in ("tau_desired", *TORQUE_COMPONENTS):
        builder.Connect(
            inverse_dynamics.GetOutputPort(name), torque_controller.GetInputPort(name)
        )
