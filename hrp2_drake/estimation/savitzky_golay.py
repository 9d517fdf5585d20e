"""Savitzky-Golay estimation of signals and their derivatives (paper Sec. 2.1, 3.4.3).

A Savitzky-Golay filter fits a polynomial of order p to the last N samples of a signal
by least squares and evaluates the polynomial and its derivatives at one point of the
window. With a constant sampling period the least-squares pseudo-inverse is a constant
matrix, so each estimate is one weighted sum of the window's samples (paper Sec. 2.1).

- `savgol_coefficients` gives those weights.
- `SavitzkyGolayFilter` is the causal, 1 kHz LeafSystem used in the controller's
  diagram; `SavitzkyGolayFilterStep` is its per-tick arithmetic on plain arrays
  (hrp2_drake.step).
- `savgol_filter_offline` applies the same weights to whole logged arrays, centred on
  every sample (the non-causal estimation used for identification, paper Sec. 3.4.3).

Evaluation point: "end" evaluates the fit at the newest sample (no delay, noisier);
"centre" evaluates it at the middle of the window, (N - 1) / 2 samples in the past (the
paper's choice: N = 80 at 1 kHz, i.e. 39.5 ms, which the paper rounds to 40 ms).

Per-signal windows (the paper's future work: "the same delay for all the sensors ...
there is room for improvement"): `SavitzkyGolayFilter` may fit each signal over its own
window N_i, every window centred on one instant, the centre of the longest, (N_max −
1) / 2 samples back: a shorter window skips the newest samples. Every estimate then
refers to the same instant (what eq. 2 needs to combine them). Evaluating a shorter
window at its own end instead would not align them: a fit's highest derivative (q̈ of
a parabola, the angular acceleration of a line) is one number for the whole window
and describes its centre wherever the fit is evaluated.
"""

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import correlate1d

from hrp2_drake.kernels import kernel
from hrp2_drake.step import Step, StepSystem

EVALUATION_POINTS = ("centre", "end")
ORDERS = (1, 2)
# SavitzkyGolayFilterStep's ring-buffer state: bookkeeping, then the samples.
_NEWEST_ROW, _NUM_SAMPLES, _CONSECUTIVE_BAD, _TOTAL_BAD, _RING_START = range(5)
# SavitzkyGolayFilterStep's packed constants (`_pack`): a header, then the weights.
(
    _DELAY,  # s
    _SPAN,  # N, the ring's rows
    _SIGNALS,  # k
    _ROWS,  # order + 1 estimates per signal
    # 1: one (order + 1, N) weight matrix for every signal; 0: (order + 1, N, k)
    _SHARED,
    _RING,  # where the named arrays start in the state: ring,
    _FIT,  # value (then the derivatives),
    _TIME,  # evaluation_time,
    _FAULT,  # input_fault
    _WEIGHTS,  # then the weights
) = range(10)
_ESTIMATES = ("value", "derivative", "second_derivative")  # state and port names
_FILTER = "SavitzkyGolayFilter"  # the name in error messages


def _check_parameters(window: int, order: int, evaluation: str, where: str) -> None:
    """Raises ValueError naming `where`, the field and its value if a parameter is
    bad."""
    if not _is_integer(order) or order not in ORDERS:
        raise ValueError(f"{where}: order={order!r} must be one of {ORDERS}")
    if not _is_integer(window) or window < order + 1:
        raise ValueError(
            f"{where}: window={window!r} must be an integer >= order + 1 = {order + 1} "
            "(a polynomial of order p needs at least p + 1 samples)"
        )
    check_evaluation(evaluation, f"{where}: evaluation")


def check_evaluation(evaluation: str, where: str) -> None:
    """Raises ValueError naming `where` (the field, e.g.
    "TorqueControlConfig.estimator.evaluation") unless `evaluation` is a point a
    filter can be evaluated at (`EVALUATION_POINTS`): the one check of the three
    places that take it (the filter, the estimator's config, the torque control's)."""
    if evaluation not in EVALUATION_POINTS:
        raise ValueError(f"{where}={evaluation!r} must be one of {EVALUATION_POINTS}")


def _is_integer(value) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def _check_period(dt: float, name: str, where: str) -> None:
    if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0.0):
        raise ValueError(f"{where}: {name}={dt!r} must be a finite number > 0 (s)")


def _check_filter(
    num_signals: int,
    window: int | Sequence[int],
    order: int,
    period: float,
    evaluation: str,
    span: int | None,
) -> tuple[int, tuple[int, ...], int]:
    """Checks SavitzkyGolayFilter's arguments; returns (k, the window of each signal,
    the span N). Raises ValueError naming the bad argument."""
    where = _FILTER
    if not _is_integer(num_signals) or num_signals < 1:
        raise ValueError(
            f"{where}: num_signals={num_signals!r} must be an integer >= 1"
        )
    k = int(num_signals)
    per_signal = isinstance(window, (list, tuple, np.ndarray))
    windows = list(window) if per_signal else [window] * k
    if len(windows) != k:
        raise ValueError(
            f"{where}: window has {len(windows)} values for {k} signals "
            "(give one window, or one per signal)"
        )
    for n in windows:
        _check_parameters(n, order, evaluation, where)
    _check_period(period, "period", where)
    windows = tuple(int(n) for n in windows)
    if span is not None and (not _is_integer(span) or span < max(windows)):
        raise ValueError(
            f"{where}: span={span!r} must be an integer >= the longest window, "
            f"{max(windows)}"
        )
    N = max(windows) if span is None else int(span)
    if len(set(windows + (N,))) > 1:
        if evaluation != "centre":
            raise ValueError(
                f"{where}: windows shorter than the span need evaluation='centre' "
                f"(every window centred on one instant), got {evaluation!r}"
            )
        odd = [n for n in windows if (N - n) % 2]
        if odd:
            raise ValueError(
                f"{where}: windows {sorted(set(odd))} differ in parity from the "
                f"span, {N}: their centres cannot coincide with its centre"
            )
    return k, windows, N


def _fit_weights(window: int, order: int, positions: np.ndarray) -> np.ndarray:
    """Least-squares weights in sample units.

    Returns W of shape (order + 1, len(positions), window): W[d, j] @ y is the d-th
    derivative (per sample^d) at fractional sample index positions[j] (0 = oldest) of
    the polynomial of `order` fitted to the window's samples y (oldest..newest).
    """
    # Sample times centred on the window keep the Vandermonde matrix well conditioned.
    centre = (window - 1) / 2
    s = np.arange(window) - centre
    powers = np.arange(order + 1)
    fit = np.linalg.pinv(s[:, np.newaxis] ** powers)  # (order + 1, window): y -> c_i
    p = np.asarray(positions, dtype=float) - centre
    weights = np.zeros((order + 1, len(p), window))
    for d in range(order + 1):
        # d/ds^d of sum_i c_i s^i = sum_{i >= d} i! / (i - d)! c_i s^(i - d).
        for i in range(d, order + 1):
            factor = math.factorial(i) / math.factorial(i - d)
            weights[d] += factor * np.outer(p ** (i - d), fit[i])
    return weights


def savgol_coefficients(
    window: int, order: int, dt: float, evaluation: str = "centre"
) -> np.ndarray:
    """Savitzky-Golay weights for the value and derivatives at one point of the window.

    Args:
        window: number of samples N in the window.
        order: polynomial order p, 1 or 2.
        dt: sampling period (s).
        evaluation: "centre" (fractional sample index (N - 1) / 2, a delay of
            (N - 1) / 2 * dt) or "end" (the newest sample, no delay).

    Returns:
        Array of shape (order + 1, window). Row d applied (dot product) to the samples
        ordered oldest..newest gives the d-th time derivative of the fitted polynomial
        at the evaluation point (signal units / s^d). For order 1 there is no row 2: a
        line's second derivative is not an estimate of the signal's.
        Row d equals scipy.signal.savgol_coeffs(window, order, deriv=d, delta=dt,
        pos=(window - 1) / 2 or window - 1, use="dot").

    Raises:
        ValueError: a bad window, order, dt or evaluation (named in the message).
    """
    _check_parameters(window, order, evaluation, "savgol_coefficients")
    _check_period(dt, "dt", "savgol_coefficients")
    position = (window - 1) / 2 if evaluation == "centre" else window - 1
    weights = _fit_weights(window, order, [position])[:, 0, :]
    return weights / dt ** np.arange(order + 1)[:, np.newaxis]


@dataclass
class SavitzkyGolayConfig:
    """Parameters of one Savitzky-Golay filter (the paper, Sec. 5.1: N = 80, p = 2 for
    the encoders, p = 1 for the IMU and F/T sensors, centred evaluation).

    Args:
        window: number of samples N fitted at each step (>= order + 1).
        order: polynomial order p, 1 or 2.
        evaluation: "centre" (delay (N - 1) / 2 samples, smoother) or "end" (no delay).
    """

    window: int = 80
    order: int = 2
    evaluation: str = "centre"

    def __post_init__(self):
        self.validate()

    def validate(self) -> None:
        """Raises ValueError naming the bad field. Call it after yaml_load_typed, which
        sets fields after construction (SavitzkyGolayFilter.from_config does)."""
        _check_parameters(
            self.window, self.order, self.evaluation, "SavitzkyGolayConfig"
        )


# Whole: one compiled pass on the tick's arrays; a split costs calls (scripts/bench.py)
@kernel
def savgol_step(t, signal, state, constants):
    """`SavitzkyGolayFilterStep.step`'s arithmetic: takes the sample `signal` (k) taken
    at t into `state` (the step's whole state vector) and writes the estimates there,
    with the constants `_pack` made (header, then the weights).

    Each estimate is a sum over the window's N samples, oldest to newest, one product
    and one addition per sample (no fma, numba's default): independent of the ring's
    position. The previous numpy code summed the same products in ring order, in BLAS
    (gemm, gemv, with fma): the estimates differ by rounding only (module tests and
    the step's docstring say how much)."""
    N = int(constants[_SPAN])
    k = int(constants[_SIGNALS])
    rows = int(constants[_ROWS])
    if signal.shape[0] != k:
        raise ValueError(
            "SavitzkyGolayFilterStep.step: the signal's size is not num_signals()"
        )
    # Views with indices from 0 (no wraparound test per access, distinct arrays: the
    # innermost loops vectorise).
    ring = int(constants[_RING])
    book = state[ring : ring + _RING_START]
    samples = state[ring + _RING_START : ring + _RING_START + N * k].reshape((N, k))
    fit = int(constants[_FIT])
    estimates = state[fit : fit + rows * k].reshape((rows, k))
    num_samples = int(book[_NUM_SAMPLES])
    previous = int(book[_NEWEST_ROW])
    row = (previous + 1) % N if num_samples > 0 else N - 1
    newest = samples[row]
    good = True
    for i in range(k):
        if not math.isfinite(signal[i]):
            good = False
            break
    if good:
        if book[_CONSECUTIVE_BAD]:
            book[_CONSECUTIVE_BAD] = 0.0
            state[int(constants[_FAULT])] = 0.0
        for i in range(k):
            newest[i] = signal[i]
    else:
        # Each bad entry holds the previous sample's value (0 before any); the
        # previous sample's row is not the newest's (N >= 2).
        held = samples[previous]
        for i in range(k):
            value = signal[i]
            if math.isfinite(value):
                newest[i] = value
            elif num_samples > 0:
                newest[i] = held[i]
            else:
                newest[i] = 0.0
        book[_CONSECUTIVE_BAD] += 1.0
        book[_TOTAL_BAD] += 1.0
        state[int(constants[_FAULT])] = book[_CONSECUTIVE_BAD]
    book[_NEWEST_ROW] = row
    book[_NUM_SAMPLES] = min(num_samples + 1, N)
    if num_samples == 0:
        # Start-up: the window is the first sample N times, whose fit is a constant.
        for r in range(N):
            if r != row:
                samples[r, :] = newest
        estimates[0, :] = newest
        estimates[1:, :] = 0.0
    else:
        estimates[:, :] = 0.0
        weights = constants[_WEIGHTS:]
        if constants[_SHARED] != 0.0:
            shared = weights.reshape((rows, N))
            for j in range(
                N
            ):  # window column j (0 = oldest): ring row (row + 1 + j) % N
                x = samples[(row + 1 + j) % N]
                for d in range(rows):
                    w = shared[d, j]
                    out = estimates[d]
                    for i in range(k):
                        out[i] += w * x[i]
        else:
            each = weights.reshape((rows, N, k))
            for j in range(N):
                x = samples[(row + 1 + j) % N]
                for d in range(rows):
                    w = each[d, j]
                    out = estimates[d]
                    for i in range(k):
                        out[i] += w[i] * x[i]
    state[int(constants[_TIME])] = t - constants[_DELAY]


class SavitzkyGolayFilterStep(Step):
    """The per-tick arithmetic of `SavitzkyGolayFilter` (its docstring: start-up, bad
    samples, per-signal windows), on plain arrays: `initialize(t, signal)` and
    `step(t, signal)` update the state in place.

    Named state arrays (`Step`), the outputs named like the filter's ports:
        ring (4 + N k): bookkeeping [newest row, number of samples (<= N),
            consecutive bad samples, total bad samples], then the last N samples
            (N, k), row-major (N = window(), the span).
        value, derivative (k each), second_derivative (k, order 2 only): the fitted
            polynomial and its time derivatives at the evaluation point (signal
            units, /s, /s²).
        evaluation_time (1): the time (s) they refer to, t − delay().
        input_fault (1): consecutive bad (NaN or infinite) samples, held.

    Per step, one numba kernel (`savgol_step`, on the state vector and one array of
    constants packed at construction, `_pack`): the sample checked entry by entry and
    written into the ring, then each estimate a weighted sum over the window's N
    samples, oldest to newest (no refit, no shift, no allocation).

    Rounding: the sums are the only reduction. The numpy code before the kernel
    (BLAS gemm/gemv over the ring in its own order, with fma) rounded them
    differently; on HRP-2's closed loop (3 s, the sinusoid), the largest differences
    were, tuned right leg (windows 4 to 18): values 4e-16 rad, q̇ 5e-14 rad/s, q̈
    4.3e-11 rad/s² (of |q̈| up to 9.8: 4e-12 relative), F/T and IMU 7e-13 (4e-16
    relative); one window of 80: q̈ 9e-13 rad/s² (3e-13 relative). That is each
    method's own rounding (against the exact sums, q̈: 2.4e-11 here, 1.9e-11 BLAS):
    a 4-sample second derivative weighs samples by about 1/dt² = 1e6 and cancels.
    Everything else (the ring, the counts, the held entries, start-up,
    evaluation_time) is elementwise: bitwise.
    """

    def __init__(
        self,
        num_signals: int,
        window: int | Sequence[int],
        order: int,
        period: float,
        evaluation: str,
        span: int | None = None,
    ):
        """
        Args: those of `SavitzkyGolayFilter` (same checks and messages).

        Raises:
            ValueError: a bad argument, named.
        """
        super().__init__()
        k, windows, N = _check_filter(
            num_signals, window, order, period, evaluation, span
        )
        self._num_signals = k
        self._windows = windows
        self._window = N
        self._order = order
        self._period = float(period)
        self._evaluation = evaluation
        self._delay = (N - 1) / 2 * self._period if evaluation == "centre" else 0.0
        self._declare("ring", np.zeros(_RING_START + N * k))
        for name in _ESTIMATES[: order + 1]:
            self._declare(name, np.zeros(k))
        self._declare("evaluation_time", np.zeros(1))
        self._declare("input_fault", np.zeros(1))
        self._finalize()
        self._constants = self._pack()

    def _pack(self) -> np.ndarray:
        """The kernel's constants, one float64 vector: the header (`_DELAY`..`_FAULT`:
        the delay, N, k, order + 1, whether one weight matrix serves every signal, the
        rows of the named arrays in the state), then the weights.

        The weights of each window are savgol_coefficients' (order + 1, N_i), placed
        in N columns so that its centre is the span's (a shorter window skips the
        (N − N_i) / 2 newest and oldest samples; zeros there). One window: that
        (order + 1, N) matrix. Several: (order + 1, N, k), signal i's in [:, :, i]
        (the kernel's innermost loop runs over the signals)."""
        N, k, rows = self._window, self._num_signals, self._order + 1
        padded = {}
        for n in sorted(set(self._windows)):
            weights = np.zeros((rows, N))
            start = (N - n) // 2
            weights[:, start : start + n] = savgol_coefficients(
                n, self._order, self._period, self._evaluation
            )
            padded[n] = weights
        shared = len(padded) == 1
        if shared:
            weights = padded[self._windows[0]]
        else:
            weights = np.stack([padded[n] for n in self._windows], axis=2)
        header = np.zeros(_WEIGHTS)
        header[[_DELAY, _SPAN, _SIGNALS, _ROWS, _SHARED]] = [
            self._delay,
            N,
            k,
            rows,
            float(shared),
        ]
        ring, fit = self.rows("ring"), self.rows("value")
        time, fault = self.rows("evaluation_time"), self.rows("input_fault")
        if self.rows(_ESTIMATES[self._order]).stop != fit.start + rows * k:
            # The kernel writes the estimates as one (order + 1, k) block.
            raise AssertionError(
                "SavitzkyGolayFilterStep: the estimates are not contiguous"
            )
        header[[_RING, _FIT, _TIME, _FAULT]] = [
            ring.start,
            fit.start,
            time.start,
            fault.start,
        ]
        return np.concatenate([header, weights.reshape(-1)])

    # ----------------------------------------------------------------- accessors

    def num_signals(self) -> int:
        return self._num_signals

    def window(self) -> int:
        """The span: the longest window (unless given), the ring buffer's length."""
        return self._window

    def windows(self) -> tuple[int, ...]:
        """The window of each signal."""
        return self._windows

    def order(self) -> int:
        return self._order

    def period(self) -> float:
        """Sampling period (s)."""
        return self._period

    def evaluation(self) -> str:
        return self._evaluation

    def delay(self) -> float:
        """Seconds the outputs lag the newest sample: (N - 1) / 2 * period for "centre"
        (N the span), 0 for "end"."""
        return self._delay

    def output_names(self) -> tuple[str, ...]:
        """The named state arrays that are outputs, in the filter's port order."""
        return (*_ESTIMATES[: self._order + 1], "evaluation_time", "input_fault")

    def is_ready(self) -> bool:
        """True once the window holds N real samples."""
        return bool(self.ring[_NUM_SAMPLES] >= self._window)

    def bad_sample_count(self) -> int:
        """How many samples had NaN or infinite entries (held)."""
        return int(self.ring[_TOTAL_BAD])

    # ----------------------------------------------------------------- per tick

    def initialize(self, t: float, signal: np.ndarray) -> None:
        """Fills the window with `signal` (k) taken at t (s), then forgets it was a
        sample: the first `step` (usually at the same time) fills it again."""
        self.step(t, signal)
        ring = self.ring
        ring[_NEWEST_ROW] = ring[_NUM_SAMPLES] = 0.0

    def step(self, t: float, signal: np.ndarray) -> None:
        """Takes the sample `signal` (k floats, signal units: a float64 array) taken
        at t (s) and updates the estimates, in place (`savgol_step`)."""
        savgol_step(t, signal, self._state, self._constants)

    def warm_up(self) -> None:
        """Compiles (or loads) `savgol_step` for a tick's types: t a float, the signal
        and the state C-contiguous float64 vectors (a step's state, bound or not, and
        the fused controller's signals are), on copies."""
        savgol_step(
            0.0, np.zeros(self._num_signals), self._state.copy(), self._constants
        )


class SavitzkyGolayFilter(StepSystem):
    """Causal Savitzky-Golay estimation of k signals and their derivatives.

    ```
                  ┌─────────────────────┐
                  │                     ├──► value
      signal ────►│ SavitzkyGolayFilter ├──► derivative
                  │                     ├──► second_derivative (order 2 only)
                  │                     ├──► evaluation_time
                  └─────────────────────┘
    ```

    - signal (k): the sampled signals (any units).
    - value, derivative, second_derivative (k each): the fitted polynomial and its first
      and second time derivatives (units, units/s, units/s²) at the evaluation point.
    - evaluation_time (1): the time (s) the three outputs refer to: the time of the
      newest sample minus delay(). Align downstream signals with it.

    A tick stores the sample `signal` holds in a ring buffer of the last N samples and
    computes the outputs with precomputed weights (savgol_coefficients) read in the
    window's order from the ring's position, so a step neither refits nor shifts nor
    allocates the buffer. The outputs (and `input_fault`) are the tick of the sample
    now held (direct feedthrough), committed at the next sampling instant
    (`hrp2_drake.step.StepSystem`: one tick from sample to command). The arithmetic is
    `SavitzkyGolayFilterStep`'s (its `initialize` and `step`), which this system runs
    on its context's state.

    Start-up: at the first sample the whole window is filled with that sample, so
    value = first sample and derivatives = 0. An initialization event does the same with
    the input at initialization, so the outputs are meaningful from the simulator's
    first step (a bare default context, never initialized, fills its window with the
    sample it is given at its first tick). Until N
    samples have arrived the window holds copies of the first sample: estimates are
    finite and continuous but biased towards that constant (derivatives ramp up from 0);
    is_ready(context) is False. From the N-th sample on, the estimates are exact for
    polynomials of degree <= order.

    A bad sample (NaN or infinite entries) never takes the diagram down: each bad entry
    holds the previous sample's value (0 before any), the estimates stay finite, and
    the output `input_fault` counts the consecutive bad samples (0 once a good one
    arrives; the window then flushes the held values within N samples).
    `bad_sample_count(context)` is the total. A consumer decides what a fault means (the
    torque controller falls back to position control).
    """

    def __init__(
        self,
        num_signals: int,
        window: int | Sequence[int] = 80,
        order: int = 2,
        period: float = 1e-3,
        evaluation: str = "centre",
        span: int | None = None,
        lead: float = 0.0,
    ):
        """
        Args:
            num_signals: k, the size of `signal`.
            window: N, number of samples fitted (>= order + 1); or one window per
                signal (k values), every one centred on the longest one's centre
                (module docstring; "centre" evaluation only, and each of the same
                parity as the longest, so that the centres coincide).
            order: polynomial order p, 1 or 2.
            period: sampling period (s) of the periodic update.
            evaluation: "centre" or "end" (see savgol_coefficients).
            span: the window whose centre every window shares (default: the
                longest; >= every window, same parity): give two filters the same span
                to align them, e.g. the encoders' and the other sensors'.
            lead: the samples arrive this long (s) before each multiple of `period`
                (`StepSystem`: the commits follow the sampler).
        """
        super().__init__()
        step = SavitzkyGolayFilterStep(
            num_signals, window, order, period, evaluation, span
        )
        self._signal = self.DeclareVectorInputPort("signal", step.num_signals())
        self._declare_step_state(step)
        for name in step.output_names():
            self._declare_step_output(name)
        self._declare_commit(step.period(), lead)
        self.DeclareInitializationDiscreteUpdateEvent(self._initialize)

    @classmethod
    def from_config(
        cls, num_signals: int, config: SavitzkyGolayConfig, period: float = 1e-3
    ) -> "SavitzkyGolayFilter":
        """Builds the filter from a (possibly YAML-loaded) config, validating it."""
        config.validate()
        return cls(num_signals, config.window, config.order, period, config.evaluation)

    def num_signals(self) -> int:
        return self._step.num_signals()

    def window(self) -> int:
        """The span: the longest window (unless given), the ring buffer's length."""
        return self._step.window()

    def windows(self) -> tuple[int, ...]:
        """The window of each signal."""
        return self._step.windows()

    def order(self) -> int:
        return self._step.order()

    def period(self) -> float:
        """Sampling period (s)."""
        return self._step.period()

    def evaluation(self) -> str:
        return self._step.evaluation()

    def delay(self) -> float:
        """Seconds the outputs lag the newest sample: (N - 1) / 2 * period for "centre"
        (N the longest window), 0 for "end"; a consumer reads them in the same
        tick."""
        return self._step.delay()

    def is_ready(self, context) -> bool:
        """True once the window holds N real samples (see the class docstring)."""
        self._load_context(context)
        return self._step.is_ready()

    def evaluation_time(self, context) -> float:
        """The time (s) the committed outputs refer to: the evaluation_time port's
        of the previous tick (the accessors read the committed state)."""
        group = self.step_group("evaluation_time")
        return context.get_discrete_state(group).get_value()[0]

    def bad_sample_count(self, context) -> int:
        """How many samples had NaN or infinite entries (held, see the class
        docstring)."""
        self._load_context(context)
        return self._step.bad_sample_count()

    def _initialize(self, context, discrete_state):
        self._load(discrete_state)
        self._step.initialize(context.get_time(), self._signal.Eval(context))
        self._store(discrete_state)

    def _tick(self, context, t):
        # The hot path of every control period (scripts/bench.py --only tick).
        self._step.step(t, self._signal.Eval(context))


def savgol_filter_offline(
    x: np.ndarray, dt: float, window: int, order: int, axis: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Non-causal Savitzky-Golay estimates over whole arrays (paper Sec. 3.4.3).

    Each sample n gets the fit of the window centred on it (no delay), with the weights
    of savgol_coefficients(window, order, dt, "centre"). Near the ends, where no centred
    window fits, the first (last) N samples are fitted and the polynomial is evaluated
    at the sample's own position, like scipy.signal.savgol_filter(mode="interp").

    Args:
        x: samples, uniformly spaced along `axis` (any other shape).
        dt: sampling period (s).
        window: N, odd (so that the centre is a sample) and <= x.shape[axis].
        order: polynomial order p, 1 or 2.
        axis: the time axis of x.

    Returns:
        (value, derivative, second_derivative), each shaped like x (units, units/s,
        units/s²); second_derivative is None for order 1.

    Raises:
        ValueError: bad window/order/dt, an even window, too few samples, or a
            non-finite x (with the first bad index).
    """
    where = "savgol_filter_offline"
    _check_parameters(window, order, "centre", where)
    _check_period(dt, "dt", where)
    if window % 2 == 0:
        raise ValueError(
            f"{where}: window={window} must be odd so that its centre is a sample "
            f"(use {window - 1} or {window + 1})"
        )
    x = np.asarray(x, dtype=float)
    if x.ndim == 0:
        raise ValueError(f"{where}: x must be an array of samples, got a scalar")
    length = x.shape[axis]
    if length < window:
        raise ValueError(
            f"{where}: x has {length} samples along axis {axis}, fewer than "
            f"window={window}"
        )
    if not np.all(np.isfinite(x)):
        bad = np.argwhere(~np.isfinite(x))[0].tolist()
        raise ValueError(f"{where}: x is not finite at index {bad}")

    half = (window - 1) // 2
    x_time_first = np.moveaxis(x, axis, 0)
    head = x_time_first[:window].reshape(window, -1)
    tail = x_time_first[-window:].reshape(window, -1)
    centre = savgol_coefficients(window, order, dt, "centre")
    edges = _fit_weights(window, order, np.arange(window))
    estimates = []
    for d in range(order + 1):
        # Interior: y[n] = sum_j w[j] x[n - half + j], the centred window of sample n.
        y = correlate1d(x_time_first, centre[d], axis=0, mode="constant")
        scale = dt**d
        y[:half] = (edges[d, :half] @ head).reshape(y[:half].shape) / scale
        y[-half:] = (edges[d, -half:] @ tail).reshape(y[-half:].shape) / scale
        estimates.append(np.moveaxis(y, 0, axis))
    if order < 2:
        estimates.append(None)
    return tuple(estimates)
