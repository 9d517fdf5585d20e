"""The robot's contacts with the ground, as a description holds them
(`RobotDescription.contacts`): plain data. A whole-body controller with contacts
(`hrp2_drake.control.balance`) reads each sole's rectangle (the centre of pressure
must stay inside it) and the friction coefficient.

    contacts:
      friction: 1.0
      soles:
        r_sole: {x: [-0.105, 0.135], y: [-0.07, 0.07]}

The balance controller's own settings that belong to the robot (the friction it
counts on, the least force per sole corner, its CoM gains) are `BalanceDescription`
(`RobotDescription.balance`).

A sole frame's origin lies on the sole's surface, its z axis is the sole's normal
(pointing up, into the foot, when the foot stands flat), its x axis points forward.
"""

import math
from dataclasses import dataclass, field

import numpy as np


@dataclass
class SoleDescription:
    """One flat sole: the rectangle of its frame's x-y plane that touches the ground.

    Args:
        x: [back, front] edges of the sole along its frame's x axis (m).
        y: [right, left] edges along its y axis (m).
    """

    x: list[float] = field(default_factory=lambda: [0.0, 0.0])
    y: list[float] = field(default_factory=lambda: [0.0, 0.0])

    def validate(self, where: str) -> None:
        for key in ("x", "y"):
            edges = getattr(self, key)
            if (
                len(edges) != 2
                or not all(math.isfinite(e) for e in edges)
                or not edges[0] < edges[1]
            ):
                raise ValueError(
                    f"{where}.{key}: expected [low, high] edges (m), low < high, "
                    f"got {edges}"
                )

    def corners(self) -> np.ndarray:
        """The sole's four corners in its frame (m), (4, 3): back right, back left,
        front right, front left; z = 0."""
        (x0, x1), (y0, y1) = self.x, self.y
        return np.array(
            [[x0, y0, 0.0], [x0, y1, 0.0], [x1, y0, 0.0], [x1, y1, 0.0]], dtype=float
        )


@dataclass
class ContactsDescription:
    """The soles a legged robot stands on (empty for a robot without feet).

    Args:
        friction: Coulomb friction coefficient μ of the soles on the ground.
        soles: each sole's rectangle, by the name of its frame (a frame of the
            model, e.g. HRP-2's "r_sole").
    """

    friction: float = 0.0
    soles: dict[str, SoleDescription] = field(default_factory=dict)

    def validate(self) -> None:
        """Raises ValueError naming the bad field (`contacts.<key>`)."""
        if not self.soles:
            return
        if not (math.isfinite(self.friction) and self.friction > 0):
            raise ValueError(f"contacts.friction: must be > 0, got {self.friction}")
        for name, sole in self.soles.items():
            sole.validate(f"contacts.soles.{name}")

    def check_model(self, plant) -> None:
        """Every sole names a frame of `plant` (a finalized MultibodyPlant)."""
        for name in self.soles:
            if not plant.HasFrameNamed(name):
                raise ValueError(
                    f"contacts.soles.{name}: no frame '{name}' in the model"
                )


@dataclass
class BalanceDescription:
    """What the whole-body balance controller (`control.balance`) takes from the
    robot (`RobotDescription.balance`): its settings measured or published for this
    robot, which a balance config leaves unset (None) to use
    (`BalanceConfig.for_robot`). Every field may be left out (None).

    Without them: `friction` has no generic value (it is the robot's soles on its
    floor: a value too high is a slip, too low gives up the force the robot has), so
    a balance controller whose config does not give it refuses to start, one line
    naming `balance.friction`; the others fall back to the QP's generic defaults
    (`GENERIC_BALANCE`).

    Args:
        friction: μ the balance QP assumes (its pyramids use μ/√2, inside the
            cone); at most `contacts.friction` (the ground's in simulation).
        min_normal_force: the least normal force of each sole corner (N).
        com_kp, com_kd: the CoM task's gains (1/s², 1/s).
    """

    friction: float | None = None
    min_normal_force: float | None = None
    com_kp: float | None = None
    com_kd: float | None = None

    def validate(self) -> None:
        """Raises ValueError naming the bad field (`balance.<key>`)."""
        for name, value in self.given().items():
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(
                    f"balance.{name}: must be finite and >= 0, got {value}"
                )
        if self.friction is not None and not self.friction > 0:
            raise ValueError(f"balance.friction: must be > 0, got {self.friction}")

    def given(self) -> dict[str, float]:
        """The settings this description gives, by name."""
        return {
            name: getattr(self, name)
            for name in ("friction", "min_normal_force", "com_kp", "com_kd")
            if getattr(self, name) is not None
        }


#: The balance QP's settings for a robot whose description gives none
#: (`BalanceDescription`): no least corner force, a CoM task of 30/s² critically
#: damped (2√30 ≈ 11/s). The friction has none.
GENERIC_BALANCE: dict[str, float] = {
    "min_normal_force": 0.0,
    "com_kp": 30.0,
    "com_kd": 11.0,
}
