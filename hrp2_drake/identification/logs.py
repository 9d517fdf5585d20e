"""Every log the project reads, in one place: this project's npz logs, a robot's own
JSON or CSV logs (its description's `LogFormat`), all read into one `RobotLog` on a
uniform grid. `identify`, `estimate`, `validate` and `calibrate --log` read their
`--log` files with `read_robot_log` (`read_logs`: several, with the report's rows of
those resampled); `excitation.collect`'s arrays become a `RobotLog` with
`RobotLog.from_arrays`.

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
- **The lowest rate.** What a filter window needs: a window (s) must span at least
  `MIN_RAW_SAMPLES_PER_WINDOW` raw samples (`check_window_rate`); a rate outside
  `PLAUSIBLE_RATES` is a timestamp read in the wrong unit.
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
- "npz": this project's own logs (`save_log`; any file ending in .npz), already on a
  constant grid, with the robot's sensors under their station port names.

Another format: write `def read_xyz(path: Path) -> RawLog` (columns as 1-D arrays,
top-level scalars in `meta`) and add it to `IMPORTERS` under its `format` name.

Every problem of a file is one ValueError naming the file and the column: an
unknown column (with the ones it has), text or NaN where numbers belong, a timestamp
going backwards, no valid sample, too few samples, a rate too low for the windows.
"""

import codecs
import csv
import dataclasses
import json
import math
import os
import zipfile
import zlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hrp2_drake.description import RobotDescription
from hrp2_drake.description.logs import LogFormat

#: Raw sampling rates (Hz) outside which a log's timestamps are in another unit than
#: `logs.time_unit` says (ms read as s: 1000 times too slow; s read as ms: too fast).
PLAUSIBLE_RATES = (1.0, 10_000.0)
#: Fewest raw samples a filter window may span (as on the grid, `window_samples`):
#: between 2 raw samples the grid is a straight line (interpolated), so a window
#: spanning fewer than 3 sees no curvature (q̈ = 0) and nothing of the motion.
MIN_RAW_SAMPLES_PER_WINDOW = 3
#: Fewest samples of a log.
MIN_SAMPLES = 10
#: Signals every identification log holds (besides "t", "phase", "excited_joint"):
#: what a real robot records, rad. A robot with an IMU adds its
#: `IMU_LOG_SIGNALS` (m/s², rad/s), and every F/T sensor s its "wrench_<s>"
#: ([N·m; N]).
IDENTIFICATION_LOG_SIGNALS = ("q_cmd", "q_measured")
IMU_LOG_SIGNALS = ("imu_linear_acceleration", "imu_angular_velocity")


@dataclass
class RawLog:
    """A file's content before resampling: columns (1-D arrays of one value per
    sample) and the file's top-level scalars."""

    columns: dict[str, np.ndarray]
    meta: dict[str, object] = field(default_factory=dict)


@dataclass
class RobotLog:
    """One log on a uniform grid (one segment), whatever file it came from.

    Attributes:
        source: the file.
        t: grid times (s), from 0, (m,).
        q_measured, q_cmd: joint positions and commands (rad), (m, n), joint order
            (a log without commands, read for estimation only: q_cmd = q_measured).
        valid: True where the servo is on, (m,).
        gain: the servo gain the log states (its own units), or None.
        joint_names: the columns' joints.
        raw_rate: median sampling rate of the file (Hz).
        longest_gap: the longest interval between two raw samples (s) and where it
            starts (s on the grid).
        meta: the file's top-level scalars (JSON).
        sensors: the IMU's and F/T sensors' readings under their station port names
            (`IMU_LOG_SIGNALS`: (m, 3); "wrench_<sensor>": (m, 6), [N·m; N]).
        phase, excited_joint: the collection's labels per sample (`excitation`),
            (m,), or None (an unlabelled log).
        tau_true: ground-truth joint torques (N·m), (m, n), joint order, or None
            (simulation only, for evaluation).
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
    sensors: dict[str, np.ndarray] = field(default_factory=dict)
    phase: np.ndarray | None = None
    excited_joint: np.ndarray | None = None
    tau_true: np.ndarray | None = None

    @classmethod
    def from_arrays(
        cls,
        arrays: Mapping[str, np.ndarray],
        log_joint_names: Sequence[str],
        joint_names: Sequence[str],
        gain: float | None = None,
        source: str = "the log",
    ) -> "RobotLog":
        """A log of this project's arrays ("t", "q_measured", "q_cmd", optional
        "valid", the sensors, labels and truth; `excitation.collect`, `load_log`),
        checked (`check_log`), its joint columns taken in `joint_names` order."""
        check_log(arrays, log_joint_names, source, joint_names)
        columns = log_columns(log_joint_names, joint_names)
        t = np.asarray(arrays["t"], float)
        valid = arrays.get("valid")
        truth = arrays.get("joint_torque_true")
        labels = {
            k: np.asarray(arrays[k]) for k in ("phase", "excited_joint") if k in arrays
        }
        return cls(
            source=source,
            t=t - t[0],
            q_measured=np.asarray(arrays["q_measured"], float)[:, columns],
            q_cmd=np.asarray(arrays["q_cmd"], float)[:, columns],
            valid=np.ones(len(t), bool) if valid is None else np.asarray(valid) != 0,
            gain=gain,
            joint_names=list(joint_names),
            raw_rate=float(1.0 / np.median(np.diff(t))),
            sensors={
                k: np.asarray(v, float)
                for k, v in arrays.items()
                if k in IMU_LOG_SIGNALS or k.startswith("wrench_")
            },
            phase=labels.get("phase"),
            excited_joint=labels.get("excited_joint"),
            tau_true=None if truth is None else np.asarray(truth, float)[:, columns],
        )

    @property
    def period(self) -> float:
        return float(self.t[1] - self.t[0])

    @property
    def name(self) -> str:
        return Path(self.source).stem

    def window_samples(self, seconds: float, what: str = "window") -> int:
        """An odd number of grid samples spanning `seconds` (at least 3)."""
        return window_samples(seconds, self.period, what)

    def slice(self, start: float, end: float) -> "RobotLog":
        """The part of the log between `start` and `end` (s), re-zeroed."""
        keep = (self.t >= start) & (self.t <= end)

        def part(array):
            return None if array is None else array[keep]

        return dataclasses.replace(
            self,
            t=self.t[keep] - self.t[keep][0],
            q_measured=self.q_measured[keep],
            q_cmd=self.q_cmd[keep],
            valid=self.valid[keep],
            sensors={k: v[keep] for k, v in self.sensors.items()},
            phase=part(self.phase),
            excited_joint=part(self.excited_joint),
            tau_true=part(self.tau_true),
        )


def check_window_rate(log: RobotLog, window: float, what: str) -> None:
    """Raises ValueError unless the filter window `window` (s, named `what`) spans at
    least `MIN_RAW_SAMPLES_PER_WINDOW` of the log's raw samples: the lowest rate a
    log may have is what its windows need."""
    spanned = window * log.raw_rate
    if spanned < MIN_RAW_SAMPLES_PER_WINDOW:
        raise ValueError(
            f"{log.source}: sampled at {log.raw_rate:.4g} Hz (median), so the filter "
            f"window {window:g} s ({what}) spans {spanned:.2f} raw samples, fewer than "
            f"the {MIN_RAW_SAMPLES_PER_WINDOW} a window needs: log at "
            f">= {MIN_RAW_SAMPLES_PER_WINDOW / window:.4g} Hz or widen the window to "
            f">= {MIN_RAW_SAMPLES_PER_WINDOW / log.raw_rate:.4g} s"
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
    lines = [
        line
        for line in text.splitlines()
        if line.strip() and not line.lstrip().startswith("#")
    ]
    rows = list(csv.reader(lines))
    if len(rows) < 2:
        raise ValueError(
            f"{path}: expected a header row and samples, got {len(rows)} rows"
        )
    header = [h.strip() for h in rows[0]]
    for k, row in enumerate(rows[1:], start=2):
        if len(row) != len(header):
            raise ValueError(
                f"{path}: row {k} has {len(row)} values, the header "
                f"{len(header)} columns"
            )
    columns = {
        name: [row[i].strip() for row in rows[1:]] for i, name in enumerate(header)
    }
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
    path: str | Path,
    log_format: LogFormat,
    joint_names: Sequence[str],
    command: bool = True,
) -> RobotLog:
    """Reads one log file, any format, into a `RobotLog` (module docstring): a file
    ending in .npz (or a robot whose format is "npz") as this project's log, any other
    through `log_format`, resampled to its uniform grid.

    Args:
        joint_names: the robot's joints, the log's columns in this order.
        command: whether the log must hold the commanded positions; without
            (estimation), an npz log may also leave out `joint_names` (then its
            columns are `joint_names`).

    Raises:
        FileNotFoundError, IsADirectoryError: `path` is not a file.
        ValueError: one line naming the file and what is wrong with it.
    """
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"log '{path}' is a folder, expected a log file")
    if not path.is_file():
        raise FileNotFoundError(f"log '{path}' not found")
    if log_format.format == "npz" or path.suffix.lower() == ".npz":
        return _from_npz(path, joint_names, command)
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


def _joint_columns(
    raw: RawLog, keys: Sequence[str], source: str, field_name: str
) -> np.ndarray:
    return np.column_stack(
        [_column(raw, key, source, f"{field_name}[{k}]") for k, key in enumerate(keys)]
    )


def _check_time(t: np.ndarray, source: str, key: str) -> None:
    if len(t) < MIN_SAMPLES:
        raise ValueError(
            f"{source}: {len(t)} samples, fewer than {MIN_SAMPLES}: not a log to "
            "identify from"
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
    low, high = PLAUSIBLE_RATES
    if not 0.98 * low <= rate <= 1.02 * high:  # 2%: clock jitter
        raise ValueError(
            f"{source}: sampled at {rate:.4g} Hz (median), outside the {low:g} Hz to "
            f"{high:g} Hz of a robot's log: are its timestamps in the unit "
            f"logs.time_unit says?"
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
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, float))
        or not (math.isfinite(value) and value > 0)
    ):
        raise ValueError(
            f"{source}: gain '{key}' (logs.gain) is {value!r}, expected a number > 0"
        )
    return float(value)


def _from_npz(path: Path, joint_names: Sequence[str], command: bool) -> RobotLog:
    """This project's log (already on a constant grid): `load_log`, then
    `RobotLog.from_arrays` (which checks it)."""
    log, names = load_log(path, None if command else joint_names, command)
    gain = log.pop("gain", None)
    if "q_cmd" not in log:  # estimation only: the estimator reads no command
        log["q_cmd"] = log["q_measured"]
    return RobotLog.from_arrays(
        log,
        names,
        joint_names,
        None if gain is None else float(np.ravel(gain)[0]),
        str(path),
    )


# ---------------------------------------------------------------------- npz
#: Arrays of a log with a known number of columns (and what they are).
_LOG_WIDTHS = {
    "imu_linear_acceleration": (3, "axes"),
    "imu_angular_velocity": (3, "axes"),
}

#: The per-sample arrays of a log besides "t": one value per sample, 1-D.
_LOG_LABELS = {"phase": "phase label", "excited_joint": "joint index", "valid": "flag"}

#: Largest relative deviation of a log's sampling period from its median: the
#: Savitzky-Golay filters assume a constant period.
MAX_PERIOD_JITTER = 0.1


def read_npz(
    path: str | Path, what: str = "log", scalars: bool = False
) -> dict[str, np.ndarray]:
    """The arrays of an .npz archive (numpy.savez), read without pickle. Every problem
    of the file is one error naming it and, where one is to blame, the array: not
    found, a folder, not an .npz archive (text, a lone .npy, a truncated zip), an
    entry that is not an array, an array whose header declares more data than the
    archive holds (or than this machine's memory), Python objects, damaged data.

    Args:
        what: what the file is, for the messages ("log", "identification log").
        scalars: accept 0-d arrays (a log's arrays hold one value per sample: no).

    Raises:
        FileNotFoundError, IsADirectoryError, ValueError.
    """
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"{what} '{path}' is a folder, expected an .npz file")
    if not path.is_file():
        raise FileNotFoundError(f"{what} '{path}' not found")
    if not zipfile.is_zipfile(path):
        raise ValueError(
            f"{path}: {_not_npz(path)}, expected an .npz archive (numpy.savez)"
        )
    arrays = {}
    damaged = (OSError, EOFError, zipfile.BadZipFile, zlib.error)
    try:
        with zipfile.ZipFile(path) as archive:
            for info in archive.infolist():
                _check_npz_entry(path, archive, info)
        with np.load(path, allow_pickle=False) as data:
            for key in data.files:
                try:
                    arrays[key] = data[key]
                except (ValueError, *damaged) as error:
                    raise ValueError(
                        f"{path}: array '{key}' cannot be read: {error}"
                    ) from None
    except damaged as error:
        raise ValueError(f"{path}: a damaged .npz archive: {error}") from None
    single = [key for key, value in arrays.items() if value.ndim == 0]
    if single and not scalars:
        raise ValueError(
            f"{path}: array '{single[0]}' is a scalar, expected one value per sample"
        )
    return arrays


def _not_npz(path: Path) -> str:
    """What a file that is no zip archive seems to be."""
    with open(path, "rb") as file:
        head = file.read(512)
    if head.startswith(b"\x93NUMPY"):
        return "a single .npy array"
    if head.startswith(b"PK"):
        return "a truncated or damaged zip file"
    if not head:
        return "an empty file"
    try:
        codecs.getincrementaldecoder("utf-8")().decode(head)  # may end mid-character
    except UnicodeDecodeError:
        return "not a zip file"
    return "not a zip file" if b"\0" in head else "a text file"


def _check_npz_entry(
    path: Path, archive: zipfile.ZipFile, info: zipfile.ZipInfo
) -> None:
    """Raises ValueError unless the archive entry is a .npy array of numbers whose
    header agrees with the bytes the archive holds (and fits in memory)."""
    name = info.filename
    if info.is_dir() or not name.endswith(".npy"):
        raise ValueError(
            f"{path}: entry '{name}' is not an array (.npy): an .npz log holds "
            "arrays only"
        )
    key = name[: -len(".npy")]
    with archive.open(info) as entry:
        try:
            version = np.lib.format.read_magic(entry)
            read_header = (
                np.lib.format.read_array_header_1_0
                if version == (1, 0)
                else np.lib.format.read_array_header_2_0
            )
            shape, _, dtype = read_header(entry)
            header_bytes = entry.tell()
        except ValueError as error:
            raise ValueError(
                f"{path}: array '{key}' is not a .npy array: {error}"
            ) from None
    if dtype.hasobject:
        raise ValueError(
            f"{path}: array '{key}' holds Python objects (pickled data), expected "
            "numbers"
        )
    declared = math.prod(shape) * dtype.itemsize
    held = info.file_size - header_bytes
    if declared != held:
        raise ValueError(
            f"{path}: array '{key}': its header declares shape {shape} "
            f"({_bytes(declared)}), the archive holds {_bytes(held)} of it"
        )
    memory = _physical_memory()
    if memory and declared > memory:
        raise ValueError(
            f"{path}: array '{key}' of shape {shape} needs {_bytes(declared)}, more "
            f"than this machine's memory ({_bytes(memory)})"
        )


def _bytes(n: int) -> str:
    for unit in ("bytes", "kB", "MB", "GB", "TB"):
        if abs(n) < 1000 or unit == "TB":
            return f"{n:.0f} {unit}" if unit == "bytes" else f"{n:.3g} {unit}"
        n /= 1000
    return f"{n} TB"


def _physical_memory() -> int | None:
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, ValueError, OSError):
        return None


def check_log(
    log: Mapping[str, np.ndarray],
    log_joint_names: Sequence[str],
    source: str = "the log",
    joints: Sequence[str] = (),
) -> None:
    """Raises ValueError naming `source` and the array unless the log can be filtered.

    Every array must hold finite numbers (not text or objects); "t" must be 1-D and
    strictly increasing on a constant grid (each period within MAX_PERIOD_JITTER of
    the median); "q_cmd", "q_measured" and "joint_torque_true" must be (samples,
    joints), the IMU's arrays (samples, 3), each "wrench_<sensor>" (samples, 6);
    `joints` must all be among `log_joint_names`.
    """
    for key, value in log.items():
        array = np.asarray(value)
        if array.dtype.kind not in "biuf":
            kind = "text" if array.dtype.kind in "US" else f"'{array.dtype}' values"
            raise ValueError(f"{source}: array '{key}' holds {kind}, expected numbers")
        if array.dtype.kind == "f" and not np.all(np.isfinite(array)):
            bad = ~np.isfinite(array.reshape(len(array), -1) if array.ndim else array)
            first = int(np.argwhere(bad)[0][0]) if array.ndim else 0
            raise ValueError(
                f"{source}: array '{key}' has {np.count_nonzero(bad)} NaN or inf "
                f"values (first at sample {first})"
            )
    t = np.asarray(log["t"])
    if t.ndim != 1 or t.size < 2:
        raise ValueError(
            f"{source}: array 't' must be 1-D with 2 or more samples, "
            f"got shape {t.shape}"
        )
    steps = np.diff(t.astype(float))
    if np.any(steps <= 0):
        k = int(np.flatnonzero(steps <= 0)[0]) + 1
        raise ValueError(
            f"{source}: array 't' must be strictly increasing, sample {k} has "
            f"t = {t[k]:.6g} s after {t[k - 1]:.6g} s"
        )
    period = float(np.median(steps))
    jitter = np.abs(steps - period) > MAX_PERIOD_JITTER * period
    if np.any(jitter):
        k = int(np.flatnonzero(jitter)[0]) + 1
        raise ValueError(
            f"{source}: array 't' is not sampled at a constant period: step "
            f"{steps[k - 1]:.6g} s before sample {k}, median {period:.6g} s "
            f"({np.count_nonzero(jitter)} steps off by more than "
            f"{MAX_PERIOD_JITTER:.0%})"
        )
    n = len(log_joint_names)
    for key, value in log.items():
        width, what = _LOG_WIDTHS.get(key, (None, ""))
        if key in ("q_cmd", "q_measured", "joint_torque_true"):
            width, what = n, "joints"
        elif key.startswith("wrench_"):
            width, what = 6, "[torque; force]"
        elif key in _LOG_LABELS and np.shape(value) != (t.size,):
            raise ValueError(
                f"{source}: array '{key}' has shape {np.shape(value)}, expected "
                f"({t.size},) (one {_LOG_LABELS[key]} per sample)"
            )
        if width is not None and np.shape(value) != (t.size, width):
            raise ValueError(
                f"{source}: array '{key}' has shape {np.shape(value)}, expected "
                f"({t.size}, {width}) (samples, {what})"
            )
    missing = [j for j in joints if j not in log_joint_names]
    if missing:
        shown = ", ".join(missing[:3]) + (", ..." if len(missing) > 3 else "")
        raise ValueError(
            f"{source}: array 'joint_names' lacks {len(missing)} of the "
            f"{len(joints)} joints needed ({shown})"
        )


def log_columns(log_joint_names: Sequence[str], joints: Sequence[str]) -> list[int]:
    """The log's column of each of `joints`; KeyError naming the missing ones."""
    column = {name: i for i, name in enumerate(log_joint_names)}
    missing = [j for j in joints if j not in column]
    if missing:
        raise KeyError(f"the log has no column for joints {missing}")
    return [column[j] for j in joints]


def save_log(
    path: str | Path, log: dict[str, np.ndarray], joint_names: Sequence[str]
) -> None:
    """Writes an identification log (.npz, one array per signal, plus joint names)."""
    np.savez_compressed(path, joint_names=np.array(list(joint_names)), **log)


def load_log(
    path: str | Path,
    default_names: Sequence[str] | None = None,
    command: bool = True,
) -> tuple[dict[str, np.ndarray], list[str]]:
    """Reads a log written by `save_log` or by a real robot in the same format: its
    arrays and its joint names.

    Args:
        default_names: the joint names of a log without `joint_names` (None: it must
            have them).
        command: whether "q_cmd" must be there (estimation needs none).

    Raises:
        FileNotFoundError, IsADirectoryError: `path` is not a file.
        ValueError: not a readable .npz archive (`read_npz`), a required signal is
            missing, or sizes disagree.
    """
    what = "identification log" if command else "log"
    log = read_npz(path, what)
    required = ["t", "q_measured"] + ["q_cmd"] * command
    required += ["joint_names"] * (default_names is None)
    missing = [key for key in required if key not in log]
    if missing:
        raise ValueError(f"{path}: {what} lacks {missing}")
    names = [str(n) for n in log.pop("joint_names", default_names)]
    m, n = len(log["t"]), len(names)
    for key, value in log.items():
        if value.shape[0] != m:
            raise ValueError(
                f"{path}: '{key}' has {value.shape[0]} samples, 't' has {m}"
            )
    for key in ("q_cmd", "q_measured"):
        if key in log and log[key].shape != (m, n):
            raise ValueError(
                f"{path}: '{key}' has shape {log[key].shape}, expected ({m}, {n})"
            )
    return log, names


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
            `save_log`), or a column the format names is missing.
    """
    path = Path(path)
    needed = [log_format.time, *log_format.position, *log_format.command]
    needed += [log_format.valid] if log_format.valid else []
    missing = [key for key in needed if key not in columns]
    if missing:
        raise ValueError(
            f"write_robot_log: columns {missing} missing (the log format's)"
        )
    meta = dict(meta or {})
    names = list(columns)
    if log_format.format == "json":
        data = {name: np.asarray(columns[name]).tolist() for name in names}
        if log_format.samples:
            count = len(data[names[0]])
            document = {
                **meta,
                log_format.samples: [
                    {name: data[name][k] for name in names} for k in range(count)
                ],
            }
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
                writer.writerow(
                    [repr(float(columns[n][k])) for n in names]
                    + [repr(float(v)) for v in constant.values()]
                )
    else:
        raise ValueError(
            f"write_robot_log: format '{log_format.format}' is this project's own log "
            "(save_log)"
        )
    return path


def read_logs(
    paths: Sequence[Path], robot: RobotDescription
) -> tuple[list[RobotLog], list[dict]]:
    """Each log file as one log (`read_robot_log`: this project's .npz as it is,
    any other through the robot description's log format, resampled to its grid), and
    one report row per log that was resampled."""
    logs, rows = [], []
    for path in paths:
        log = read_robot_log(path, robot.logs, robot.joints)
        logs.append(log)
        if Path(path).suffix.lower() != ".npz" and robot.logs.format != "npz":
            rows += describe([log])
    return logs, rows
