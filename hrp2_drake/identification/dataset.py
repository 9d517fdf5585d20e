"""Non-causal estimation over an identification log (paper Sec. 3.4.3).

Offline there is no need to wait for the future: every signal is filtered by a
Savitzky-Golay window centred on its sample (no delay), so q, q̇, q̈, the IMU and F/T
readings, and Δq all refer to the same instant. τ̂ then comes from the same
floating-base estimator as online (`FloatingBaseTorqueEstimator.estimate`).
"""

import codecs
import dataclasses
import math
import os
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Mapping, Sequence

import numpy as np

from hrp2_drake.estimation.savitzky_golay import savgol_filter_offline
from hrp2_drake.estimation.torque_estimator import FloatingBaseTorqueEstimator
from hrp2_drake.identification.logs import window_samples


@dataclass
class IdentificationData:
    """Aligned, non-causal estimates of a log, every `stride`-th sample.

    Attributes:
        t: sample times (s), (m,).
        q, dq, ddq: joint positions (rad), velocities (rad/s), accelerations (rad/s²),
            (m, n), estimator joint order.
        tau: estimated joint torques τ̂ (N·m), (m, n).
        delta_q: Δq = q_cmd − q, smoothed by the same window (rad), (m, n).
        phase, excited_joint: the log's labels (see excitation.py), (m,); -1 where
            the log has none.
        tau_true: ground-truth joint torques if the log has them (simulation), else None.
        segment: the index of the log each sample comes from (`estimate_segments`).
        gain: the servo gain of each sample's log (NaN: the log states none).
        usable: inside its log's filter edges with its whole window valid (servo on).
        saturated: (m, n), the servo's output near its limit within the window.
    """

    t: np.ndarray
    q: np.ndarray
    dq: np.ndarray
    ddq: np.ndarray
    tau: np.ndarray
    delta_q: np.ndarray
    phase: np.ndarray
    excited_joint: np.ndarray
    tau_true: np.ndarray | None = None
    segment: np.ndarray | None = None
    gain: np.ndarray | None = None
    usable: np.ndarray | None = None
    saturated: np.ndarray | None = None

    def joint(self, j: int, mask: np.ndarray | None = None):
        """(τ̂, q̇, Δq) of joint j (1-D arrays), the samples of `mask` only."""
        mask = slice(None) if mask is None else mask
        return self.tau[mask, j], self.dq[mask, j], self.delta_q[mask, j]


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
                    raise ValueError(f"{path}: array '{key}' cannot be read: {error}")
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


def noncausal_torques(
    log: Mapping[str, np.ndarray],
    columns: Sequence[int],
    estimator: FloatingBaseTorqueEstimator,
    window: int,
    samples: np.ndarray,
    offsets: np.ndarray | None = None,
) -> tuple[list, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The estimator's `TorqueEstimate` at each of `samples` (indices), from centred
    Savitzky-Golay estimates of the log's encoders (`columns`: the estimator's joints,
    order 2), IMU (if the estimator has one) and F/T sensors (order 1); also
    (q, q̇, q̈) at those samples. `offsets` (k, 6): the F/T sensors' biases, subtracted
    from their compensated readings (as the online calibration does).

    Raises:
        ValueError: the log is shorter than the window, or lacks a signal the
            estimator needs.
    """
    t = np.asarray(log["t"], float)
    if len(t) < window:
        raise ValueError(f"the log has {len(t)} samples, fewer than the window {window}")
    config = estimator.config()
    imu = bool(config.imu_frame)
    signals = ["imu_linear_acceleration", "imu_angular_velocity"] if imu else []
    signals += [f"wrench_{name}" for name in config.sensors]
    absent = [s for s in signals if s not in log]
    if absent:
        raise ValueError(f"the log lacks {absent}, which the estimator needs")
    dt = float(np.median(np.diff(t)))
    q, dq, ddq = savgol_filter_offline(log["q_measured"][:, columns], dt, window, 2)
    if imu:  # else a fixed base: the estimator knows its motion (none) and gravity
        acc = savgol_filter_offline(log["imu_linear_acceleration"], dt, window, 1)[0]
        gyro, alpha, _ = savgol_filter_offline(log["imu_angular_velocity"], dt, window, 1)
    wrenches = np.zeros((len(t), len(config.sensors), 6))
    for s, name in enumerate(config.sensors):
        wrenches[:, s] = savgol_filter_offline(log[f"wrench_{name}"], dt, window, 1)[0]
    estimates = [
        estimator.estimate(
            q[k], dq[k], ddq[k],
            *((acc[k], gyro[k], alpha[k]) if imu else (None, None, None)),
            wrenches[k],
            offsets,
        )
        for k in samples
    ]
    return estimates, (q[samples], dq[samples], ddq[samples])


def noncausal_estimates(
    log: dict[str, np.ndarray],
    log_joint_names: Sequence[str],
    estimator: FloatingBaseTorqueEstimator,
    window: int = 81,
    stride: int = 5,
) -> IdentificationData:
    """Filters a log with centred Savitzky-Golay windows and estimates τ̂ per sample.

    Args:
        log: an identification log (excitation.load_log): "t", "q_cmd", "q_measured",
            "imu_linear_acceleration", "imu_angular_velocity", "wrench_<sensor>" for
            every sensor of the estimator.
        log_joint_names: joint names of the log's columns; must contain the
            estimator's joints.
        estimator: the floating-base estimator (its config names joints and sensors).
        window: Savitzky-Golay window N, odd (centred windows need a middle sample; the
            paper's 80 becomes 81). Encoders and Δq: order 2; IMU and F/T: order 1.
        stride: keep every stride-th sample (neighbouring samples at 1 kHz add little).

    Raises:
        ValueError: the log lacks a signal, has NaN or text, its time is not
            increasing on a constant grid (`check_log`), or it is shorter than the
            window.
        KeyError: an estimator joint is not in the log.
    """
    check_log(log, log_joint_names)
    t = np.asarray(log["t"], float)
    cols = log_columns(log_joint_names, estimator.config().joints)
    keep = np.arange(0, len(t), stride)
    estimates, (q, dq, ddq) = noncausal_torques(log, cols, estimator, window, keep)
    tau = np.array([e.tau for e in estimates]).reshape(len(keep), len(cols))
    dt = float(np.median(np.diff(t)))
    delta_q = savgol_filter_offline(log["q_cmd"][:, cols] - log["q_measured"][:, cols], dt, window, 2)[0]
    tau_true = log["joint_torque_true"][keep][:, cols] if "joint_torque_true" in log else None
    # Unlabelled logs (e.g. from a real robot): phase and excited joint -1.
    labels = {
        key: np.asarray(log[key])[keep] if key in log else np.full(len(keep), -1)
        for key in ("phase", "excited_joint")
    }
    return IdentificationData(
        t[keep], q, dq, ddq, tau, delta_q[keep],
        labels["phase"], labels["excited_joint"], tau_true,
    )


@dataclass
class LogSegment:
    """One log of an identification: nothing filters across two segments.

    Attributes:
        log: the log's arrays ("t", "q_cmd", "q_measured", optional "valid", the
            sensors the estimator needs, optional labels and truth).
        joint_names: the joints of its columns.
        gain: the servo gain it was recorded at (its own units), or None.
        source: the file, for messages.
        longest_gap: the longest interval between two raw samples (s) and where it
            starts (s): a gap longer than the filter window cannot be filtered.
    """

    log: dict[str, np.ndarray]
    joint_names: list[str]
    gain: float | None = None
    source: str = "the log"
    longest_gap: tuple[float, float] = (0.0, 0.0)


def estimate_segments(
    segments: Sequence[LogSegment],
    estimator: FloatingBaseTorqueEstimator,
    window: float,
    stride: float,
    saturation_error: Callable[[float | None], float] = lambda gain: math.inf,
    saturation_margin: float = 1.0,
) -> IdentificationData:
    """`noncausal_estimates` of each log, concatenated, with the masks a fit needs.

    Args:
        window, stride: in seconds: the odd number of samples nearest to `window`
            at each log's own period, one sample every `stride` seconds.
        saturation_error: |q_cmd − q| (rad) at which the servo's output saturates at a
            gain (inf: never); a sample is `saturated` where any raw sample of its
            window exceeds `saturation_margin` times it.

    Raises:
        ValueError: naming the log: a log shorter than the window, and
            `noncausal_estimates`' errors.
    """
    parts = []
    joints = estimator.config().joints
    for k, segment in enumerate(segments):
        log = segment.log
        t = np.asarray(log["t"], float)
        period = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
        n_window = window_samples(window, period, f"{segment.source}: window")
        n_stride = max(1, int(round(stride / period)))
        try:
            data = noncausal_estimates(log, segment.joint_names, estimator, n_window, n_stride)
        except ValueError as error:
            raise ValueError(f"{segment.source}: {error}") from None
        keep = np.arange(0, len(t), n_stride)
        cols = log_columns(segment.joint_names, joints)
        invalid = np.asarray(log.get("valid", np.ones(len(t))))[:] == 0
        margin = n_window * period  # the filters' edges: fitted, not centred
        inside = (data.t > data.t[0] + margin) & (data.t < data.t[-1] - margin)
        error = np.abs(log["q_cmd"][:, cols] - log["q_measured"][:, cols])
        limit = saturation_margin * saturation_error(segment.gain)
        data.segment = np.full(len(keep), k)
        data.gain = np.full(len(keep), math.nan if segment.gain is None else segment.gain)
        data.usable = inside & ~_within_window(invalid, n_window)[keep]
        data.saturated = _within_window(error >= limit, n_window)[keep]
        parts.append(data)
    return _concatenate(parts)


def _within_window(mask: np.ndarray, window: int) -> np.ndarray:
    """True where any sample of the centred window of `window` samples is in `mask`
    ((m,) or (m, n), per column)."""
    kernel = np.ones(window)
    columns = mask.reshape(len(mask), -1).astype(float)
    spread = np.column_stack(
        [np.convolve(c, kernel, mode="same") > 0.5 for c in columns.T]
    )
    return spread.reshape(mask.shape)


def _concatenate(parts: Sequence[IdentificationData]) -> IdentificationData:
    """One IdentificationData of several logs' (their samples one after another)."""
    if len(parts) == 1:
        return parts[0]
    names = [f.name for f in dataclasses.fields(IdentificationData)]
    joined = {}
    for name in names:
        values = [getattr(p, name) for p in parts]
        joined[name] = None if any(v is None for v in values) else np.concatenate(values)
    return IdentificationData(**joined)


def split_blocks(t: np.ndarray, block: float = 1.0, held_out_every: int = 3) -> np.ndarray:
    """Boolean mask of held-out samples: every `held_out_every`-th block of `block`
    seconds (contiguous blocks, so held-out samples are not neighbours of training
    ones)."""
    return (np.floor((t - t[0]) / block).astype(int) % held_out_every) == held_out_every - 1
