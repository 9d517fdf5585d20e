"""How a robot's own logs are read (`RobotDescription.logs`), as plain data.
`hrp2_drake.identification.logs` reads and resamples them.
"""

import math
from dataclasses import dataclass, field

#: Log formats `identification.logs.read_robot_log` reads (its `IMPORTERS` has their
#: readers).
FORMATS = ("npz", "json", "csv")


@dataclass
class LogFormat:
    """How a robot's logs are read (a robot description's `logs`).

    Args:
        format: "npz" (this project's identification logs), "json" or "csv".
        time: the timestamp column.
        time_unit: seconds per unit of `time` (1e-3 for milliseconds).
        samples: JSON: the key of the list of per-sample records (BAM: "entries");
            empty: the file holds one list per column.
        position: the measured position column of each joint, in the description's
            `joints` order.
        command: the commanded position column of each joint, same order.
        position_unit: rad per unit of `position` and `command` (pi / 180: degrees).
        valid: a column that is true (non-zero) where the servo is on; empty: on
            throughout.
        gain: where the log states the servo's gain, in the servo's own units: JSON,
            a top-level key; CSV, a column (constant over the file); empty: logs state
            no gain.
        rate: the uniform grid every log is resampled to (Hz).
    """

    format: str = "npz"
    time: str = "t"
    time_unit: float = 1.0
    samples: str = ""
    position: list[str] = field(default_factory=list)
    command: list[str] = field(default_factory=list)
    position_unit: float = 1.0
    valid: str = ""
    gain: str = ""
    rate: float = 1000.0

    def validate(self, joints: int) -> None:
        """Raises ValueError naming the field (`joints`: how many the robot has)."""
        if self.format not in FORMATS:
            raise ValueError(f"logs.format: '{self.format}', expected one of {FORMATS}")
        for name in ("time_unit", "position_unit", "rate"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"logs.{name}: must be finite and > 0, got {value}")
        if self.format == "npz":
            return
        if not self.time:
            raise ValueError("logs.time: empty, expected the timestamp column")
        for name in ("position", "command"):
            columns = getattr(self, name)
            if len(columns) != joints:
                raise ValueError(
                    f"logs.{name}: {len(columns)} columns for {joints} joints "
                    "(one per joint, in the order of `joints`)"
                )
