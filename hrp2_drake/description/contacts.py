"""The robot's contacts with the ground, as a description holds them
(`RobotDescription.contacts`): plain data. A whole-body controller with contacts
(`hrp2_drake.control.balance`) reads each sole's rectangle (the centre of pressure
must stay inside it) and the friction coefficient.

    contacts:
      friction: 1.0
      soles:
        r_sole: {x: [-0.105, 0.135], y: [-0.07, 0.07]}

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
