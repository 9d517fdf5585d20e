"""Robot logs as they come from a robot: any rate, jitter, servo off, several files.

A real robot records timestamped samples at its own rate (a Dynamixel bus at about
190 Hz, a motor board at 1 kHz), with jitter, and with stretches where the servo is
off. `read_robot_log` reads one such file through the robot description's
`LogFormat` and puts it on the framework's grid:

- **The grid.** Uniform, at `LogFormat.rate` (default 1 kHz, the controller's
  period), from the first timestamp to the last, re-zeroed to start at 0 s.
  Measured signals (`position`) are linearly interpolated between raw samples; the
  command and the servo's state (`command`, `valid`) are held from the raw sample at
  or before each grid point (zero-order hold: what the servo received between two
  writes). Filter windows and strides are given in seconds (`window_samples`), so one
  config works at any rate.
- **The valid mask.** True where the servo is on (the `valid` column; no column:
  always). Identification keeps a sample only if its whole filter window is valid.
- **The gain.** A log may state the servo's gain (`gain`: a top-level key of a JSON
  file, or a constant column of a CSV file), in the servo's own units: the motor model
  then pools logs of several gains (`motor_model.MotorModel.at_gain`).
- **Segments.** Each file is its own segment: nothing filters across two files.

Importers, by `LogFormat.format`:
- "json": an object whose `samples` key holds a list of records (one per sample,
  BAM's "entries"), or, with `samples` empty, one list per column; top-level scalars
  (the gain) beside them.
- "csv": a header row of column names, then one row per sample (`#` comments).
- "npz": this project's own identification logs (`excitation.save_log`), already on
  a constant grid.

Another format: write `def read_xyz(path: Path) -> RawLog` (columns as 1-D arrays,
top-level scalars in `meta`) and add it to `IMPORTERS` under its `format` name.

Every problem of a file is one ValueError naming the file and the column: an
unknown column (with the ones it has), text or NaN where numbers belong, a timestamp
going backwards, no valid sample, a rate outside 50 Hz to 10 kHz, too few samples.
"""

import csv
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Mapping, Sequence

import numpy as np

# The format is the robot description's (plain data), imported here for this module's users.
from hrp2_drake.description.logs import FORMATS, LogFormat  # noqa: F401

#: Raw sampling rates a log may have (Hz): below, a servo's motion is not resolved.
MIN_RAW_RATE, MAX_RAW_RATE = 50.0, 10_000.0
#: Fewest samples of a log.
MIN_SAMPLES = 10


@dataclass
class RawLog:
    """A file's content before resampling: columns (1-D arrays of one value per
    sample) and the file's top-level scalars."""

    columns: dict[str, np.ndarray]
    meta: dict[str, object] = field(default_factory=dict)


@dataclass
class RobotLog:
    """One log on the framework's uniform grid (one segment).

    Attributes:
        source: the file.
        t: grid times (s), from 0, (m,).
        q_measured, q_cmd: joint positions and commands (rad), (m, n), joint order.
        valid: True where the servo is on, (m,).
        gain: the servo gain the log states (its own units), or None.
        joint_names: the columns' joints.
        raw_rate: median sampling rate of the file (Hz).
        longest_gap: the longest interval between two raw samples (s) and where it
            starts (s on the grid).
        meta: the file's top-level scalars (JSON).
    """

    source: str
    t: np.ndarray
    q_measured: np.ndarray
    q_cmd: np.ndarray
    valid: np.ndarray
    gain: float | None
    joint_names: list[str]
    raw_rate: float
    longest_gap: tuple[float, float] = (0.0, 0.0)
    meta: dict[str, object] = field(default_factory=dict)

    @property
    def period(self) -> float:
        return float(self.t[1] - self.t[0])

    @property
    def name(self) -> str:
        return Path(self.source).stem

    def arrays(self) -> dict[str, np.ndarray]:
        """The log as this project's identification log: "t", "q_cmd",
        "q_measured" and "valid" (`dataset.noncausal_estimates` reads it)."""
        return {
            "t": self.t,
            "q_cmd": self.q_cmd,
            "q_measured": self.q_measured,
            "valid": self.valid.astype(np.int8),
        }

    def window_samples(self, seconds: float, what: str = "window") -> int:
        """An odd number of grid samples spanning `seconds` (at least 3)."""
        return window_samples(seconds, self.period, what)

    def slice(self, start: float, end: float) -> "RobotLog":
        """The part of the log between `start` and `end` (s), re-zeroed."""
        keep = (self.t >= start) & (self.t <= end)
        return RobotLog(
            self.source, self.t[keep] - self.t[keep][0], self.q_measured[keep],
            self.q_cmd[keep], self.valid[keep], self.gain, self.joint_names,
            self.raw_rate, self.longest_gap, self.meta,
        )


def window_samples(seconds: float, period: float, what: str = "window") -> int:
    """The odd number of samples of period `period` closest to `seconds` (>= 3): a
    centred Savitzky-Golay window needs a middle sample.

    Raises:
        ValueError: `seconds` is not finite and positive, or spans fewer than 3
            samples.
    """
    if not (math.isfinite(seconds) and seconds > 0):
        raise ValueError(f"{what}: must be a finite duration > 0 (s), got {seconds}")
    n = int(round(seconds / period))
    n += 1 - n % 2
    if n < 3:
        raise ValueError(
            f"{what}: {seconds:g} s spans fewer than 3 samples of {period * 1e3:g} ms"
        )
    return n


# ---------------------------------------------------------------------- importers
def read_json(path: Path, log_format: LogFormat) -> RawLog:
    """A JSON log: records under `samples`, or one list per column."""
    try:
        document = json.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a text (UTF-8) file, expected JSON") from None
    except json.JSONDecodeError as error:
        raise ValueError(f"{path}: not valid JSON: {error}") from None
    if not isinstance(document, dict):
        raise ValueError(f"{path}: expected a JSON object at the top level")
    meta = {k: v for k, v in document.items() if not isinstance(v, (list, dict))}
    if log_format.samples:
        records = document.get(log_format.samples)
        if not isinstance(records, list) or not records:
            raise ValueError(
                f"{path}: key '{log_format.samples}' (logs.samples) is "
                f"{'missing' if records is None else 'not a list of samples'}; "
                f"the file has {sorted(document)}"
            )
        if not all(isinstance(r, dict) for r in records):
            raise ValueError(f"{path}: '{log_format.samples}' holds non-records")
        keys = list(records[0])
        columns = {key: [r.get(key) for r in records] for key in keys}
    else:
        columns = {k: v for k, v in document.items() if isinstance(v, list)}
    return RawLog({k: _numbers(path, k, v) for k, v in columns.items()}, meta)


def read_csv(path: Path, log_format: LogFormat) -> RawLog:
    """A CSV log: a header of column names, one row per sample."""
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a text (UTF-8) file, expected CSV") from None
    rows = [r for r in csv.reader(line for line in text.splitlines()
                                  if line.strip() and not line.lstrip().startswith("#"))]
    if len(rows) < 2:
        raise ValueError(f"{path}: expected a header row and samples, got {len(rows)} rows")
    header = [h.strip() for h in rows[0]]
    for k, row in enumerate(rows[1:], start=2):
        if len(row) != len(header):
            raise ValueError(
                f"{path}: row {k} has {len(row)} values, the header {len(header)} columns"
            )
    columns = {name: [row[i].strip() for row in rows[1:]] for i, name in enumerate(header)}
    return RawLog({k: _numbers(path, k, v) for k, v in columns.items()})


#: Readers of raw logs by `LogFormat.format` ("npz" is read by `read_robot_log`).
IMPORTERS: dict[str, Callable[[Path, LogFormat], RawLog]] = {
    "json": read_json,
    "csv": read_csv,
}


def _numbers(path: Path, key: str, values: Sequence) -> np.ndarray:
    """A column as float64: numbers as they are, booleans (and "true"/"false") as
    1/0, numeric text parsed; anything else (other text, null, a list) becomes NaN,
    which `_column` reports with its count and first sample if the column is used."""
    converted = []
    for value in values:
        if isinstance(value, bool):
            converted.append(float(value))
        elif isinstance(value, (int, float)):
            converted.append(float(value))
        elif isinstance(value, str):
            text = value.strip().lower()
            if text in ("true", "false"):
                converted.append(float(text == "true"))
                continue
            try:
                converted.append(float(text))
            except ValueError:
                converted.append(math.nan)
        else:
            converted.append(math.nan)
    return np.asarray(converted, float)


# ---------------------------------------------------------------------- assembly
def read_robot_log(
    path: str | Path, log_format: LogFormat, joint_names: Sequence[str]
) -> RobotLog:
    """Reads one log file and resamples it to the uniform grid (module docstring).

    Raises:
        FileNotFoundError, IsADirectoryError: `path` is not a file.
        ValueError: one line naming the file and what is wrong with it.
    """
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"log '{path}' is a folder, expected a log file")
    if not path.is_file():
        raise FileNotFoundError(f"log '{path}' not found")
    if log_format.format == "npz":
        return _from_npz(path, log_format, joint_names)
    raw = IMPORTERS[log_format.format](path, log_format)
    return resample(raw, log_format, joint_names, str(path))


def resample(
    raw: RawLog, log_format: LogFormat, joint_names: Sequence[str], source: str
) -> RobotLog:
    """Puts a raw log on the uniform grid of `log_format.rate` (module docstring)."""
    t_raw = _column(raw, log_format.time, source, "logs.time") * log_format.time_unit
    positions = _joint_columns(raw, log_format.position, source, "logs.position")
    commands = _joint_columns(raw, log_format.command, source, "logs.command")
    valid_raw = (
        _column(raw, log_format.valid, source, "logs.valid") != 0
        if log_format.valid
        else np.ones(len(t_raw), bool)
    )
    _check_time(t_raw, source, log_format.time)
    if not np.any(valid_raw):
        raise ValueError(
            f"{source}: no valid sample: column '{log_format.valid}' (logs.valid) is "
            "false throughout (the servo was never on)"
        )
    positions *= log_format.position_unit
    commands *= log_format.position_unit
    grid = np.arange(0.0, t_raw[-1] - t_raw[0], 1.0 / log_format.rate)
    raw_t = t_raw - t_raw[0]
    held = np.searchsorted(raw_t, grid, side="right") - 1
    q = np.column_stack([np.interp(grid, raw_t, p) for p in positions.T])
    steps = np.diff(raw_t)
    gap = int(np.argmax(steps))
    return RobotLog(
        source=source,
        t=grid,
        q_measured=q,
        q_cmd=commands[held],
        valid=valid_raw[held],
        gain=_gain(raw, log_format, source),
        joint_names=list(joint_names),
        raw_rate=float(1.0 / np.median(steps)),
        longest_gap=(float(steps[gap]), float(raw_t[gap])),
        meta=dict(raw.meta),
    )


def _column(raw: RawLog, key: str, source: str, field_name: str) -> np.ndarray:
    if key not in raw.columns:
        raise ValueError(
            f"{source}: no column '{key}' ({field_name}); the log has "
            f"{sorted(raw.columns)}"
        )
    values = raw.columns[key]
    bad = ~np.isfinite(values)
    if np.any(bad):
        raise ValueError(
            f"{source}: column '{key}' ({field_name}) has {np.count_nonzero(bad)} "
            f"values that are not numbers (first at sample {int(np.argmax(bad))})"
        )
    return values.copy()


def _joint_columns(raw: RawLog, keys: Sequence[str], source: str, field_name: str) -> np.ndarray:
    return np.column_stack(
        [_column(raw, key, source, f"{field_name}[{k}]") for k, key in enumerate(keys)]
    )


def _check_time(t: np.ndarray, source: str, key: str) -> None:
    if len(t) < MIN_SAMPLES:
        raise ValueError(
            f"{source}: {len(t)} samples, fewer than {MIN_SAMPLES}: not a log to identify from"
        )
    steps = np.diff(t)
    if np.any(steps <= 0):
        k = int(np.flatnonzero(steps <= 0)[0]) + 1
        what = "goes backwards" if steps[k - 1] < 0 else "repeats"
        raise ValueError(
            f"{source}: timestamp '{key}' {what} at sample {k}: {t[k]:.6g} s after "
            f"{t[k - 1]:.6g} s"
        )
    rate = 1.0 / float(np.median(steps))
    if not 0.98 * MIN_RAW_RATE <= rate <= 1.02 * MAX_RAW_RATE:  # 2%: clock jitter
        raise ValueError(
            f"{source}: sampled at {rate:.4g} Hz (median), outside the "
            f"{MIN_RAW_RATE:g} Hz to {MAX_RAW_RATE:g} Hz a log may have: is "
            "logs.time_unit right?"
        )


def _gain(raw: RawLog, log_format: LogFormat, source: str) -> float | None:
    key = log_format.gain
    if not key:
        return None
    if key in raw.meta:
        value = raw.meta[key]
    elif key in raw.columns:
        values = raw.columns[key]
        if np.ptp(values) > 0:
            raise ValueError(
                f"{source}: gain column '{key}' (logs.gain) changes within the log "
                f"({values.min():g} to {values.max():g}); one gain per log"
            )
        value = values[0]
    else:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (
        math.isfinite(value) and value > 0
    ):
        raise ValueError(
            f"{source}: gain '{key}' (logs.gain) is {value!r}, expected a number > 0"
        )
    return float(value)


def _from_npz(path: Path, log_format: LogFormat, joint_names: Sequence[str]) -> RobotLog:
    """This project's identification log (already on a constant grid)."""
    from hrp2_drake.identification.dataset import check_log
    from hrp2_drake.identification.excitation import load_log

    log, names = load_log(path)
    check_log(log, names, str(path), joint_names)
    columns = [names.index(j) for j in joint_names]
    t = np.asarray(log["t"], float)
    valid = np.asarray(log["valid"]) != 0 if "valid" in log else np.ones(len(t), bool)
    gain = log.get("gain")
    return RobotLog(
        source=str(path),
        t=t - t[0],
        q_measured=np.asarray(log["q_measured"], float)[:, columns],
        q_cmd=np.asarray(log["q_cmd"], float)[:, columns],
        valid=valid,
        gain=float(gain[0]) if gain is not None else None,
        joint_names=list(joint_names),
        raw_rate=float(1.0 / np.median(np.diff(t))),
    )


def check_gains(logs: Sequence[RobotLog], needed: bool) -> None:
    """Raises ValueError naming the first log without a gain when `needed` (pooling
    logs of several gains, or transferring a model to another gain needs each one)."""
    if not needed:
        return
    missing = [log.source for log in logs if log.gain is None]
    if missing:
        raise ValueError(
            f"{missing[0]}: states no servo gain (logs.gain), but pooling logs of "
            "several gains needs each log's gain"
        )


def gains_differ(logs: Sequence[RobotLog]) -> bool:
    """Whether the logs state more than one gain (or some state one and some not)."""
    return len({log.gain for log in logs}) > 1


def describe(logs: Sequence[RobotLog]) -> list[Mapping[str, object]]:
    """One row per log for reports: name, raw rate, duration, gain, valid share."""
    return [
        {
            "log": log.name,
            "raw_rate_hz": round(log.raw_rate, 1),
            "duration_s": round(float(log.t[-1]), 3),
            "gain": log.gain,
            "valid_share": round(float(np.mean(log.valid)), 3),
            "longest_gap_s": round(log.longest_gap[0], 4),
        }
        for log in logs
    ]


# ---------------------------------------------------------------------- exporters
def write_robot_log(
    path: str | Path,
    log_format: LogFormat,
    columns: Mapping[str, np.ndarray],
    meta: Mapping[str, object] | None = None,
) -> Path:
    """Writes a log as a robot records it, in its description's format, so that
    `read_robot_log` reads it back: `columns` by name (1-D arrays, one value per
    sample: the format's time, position, command and valid columns among them),
    `meta` the file's top-level values (JSON: the gain under `log_format.gain`;
    CSV: each a constant column). Returns the path written.

    Raises:
        ValueError: the format is this project's npz (written by
            `excitation.save_log`), or a column the format names is missing.
    """
    path = Path(path)
    needed = [log_format.time, *log_format.position, *log_format.command]
    needed += [log_format.valid] if log_format.valid else []
    missing = [key for key in needed if key not in columns]
    if missing:
        raise ValueError(f"write_robot_log: columns {missing} missing (the log format's)")
    meta = dict(meta or {})
    names = list(columns)
    if log_format.format == "json":
        data = {name: np.asarray(columns[name]).tolist() for name in names}
        if log_format.samples:
            count = len(data[names[0]])
            document = {**meta, log_format.samples: [
                {name: data[name][k] for name in names} for k in range(count)
            ]}
        else:
            document = {**meta, **data}
        path.write_text(json.dumps(document))
    elif log_format.format == "csv":
        constant = {k: v for k, v in meta.items() if isinstance(v, (int, float))}
        header = names + list(constant)
        count = len(np.asarray(columns[names[0]]))
        with path.open("w", newline="") as file:
            writer = csv.writer(file)
            writer.writerow(header)
            for k in range(count):
                writer.writerow([repr(float(columns[n][k])) for n in names]
                                + [repr(float(v)) for v in constant.values()])
    else:
        raise ValueError(
            f"write_robot_log: format '{log_format.format}' is this project's own log "
            "(identification.excitation.save_log)"
        )
    return path
