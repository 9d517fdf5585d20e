import contextlib
import math

import numpy as np
import pytest
import scipy.signal
from pydrake.common.yaml import yaml_load_typed
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import BasicVector, DiagramBuilder, LeafSystem
from pydrake.systems.primitives import ConstantVectorSource, TrajectorySource
from ticks import commit, run_ticks

from hrp2_drake.estimation.savitzky_golay import (
    SavitzkyGolayConfig,
    SavitzkyGolayFilter,
    SavitzkyGolayFilterStep,
    savgol_coefficients,
    savgol_filter_offline,
)
from hrp2_drake.simulation import SampleHold

PERIOD = 1e-3  # s
_RING = 4  # SavitzkyGolayFilterStep.ring's bookkeeping entries


def _polynomial(degree: int, num_signals: int, seed: int = 0) -> np.ndarray:
    """Coefficients (num_signals, degree + 1), highest power first (np.polyval)."""
    return np.random.default_rng(seed).uniform(-2.0, 2.0, (num_signals, degree + 1))


def _derivatives(coefficients: np.ndarray, t: float) -> list[np.ndarray]:
    """[p(t), p'(t), p''(t)] for each row of coefficients."""
    rows = [np.poly1d(c) for c in coefficients]
    return [
        np.array([row.deriv(d)(t) if d else row(t) for row in rows]) for d in range(3)
    ]


class _PolynomialSource(LeafSystem):
    """Outputs p(t), one polynomial per signal."""

    def __init__(self, coefficients: np.ndarray):
        super().__init__()
        self._coefficients = coefficients
        self.DeclareVectorOutputPort("y", len(coefficients), self._calc)

    def _calc(self, context, output: BasicVector):
        t = context.get_time()
        output.SetFromVector([np.polyval(c, t) for c in self._coefficients])


def _sampled(builder: DiagramBuilder, port, size: int, initial) -> object:
    """`port` (a signal of time) as the station's sampler holds it: sample k from k
    periods on (and `initial` before, what the initialization reads)."""
    hold = builder.AddSystem(SampleHold(size, PERIOD, 0.0, np.asarray(initial, float)))
    builder.Connect(port, hold.get_input_port())
    return hold.get_output_port()


def _outputs(system: SavitzkyGolayFilter, context) -> list[np.ndarray]:
    names = ["value", "derivative", "second_derivative"][: system.order() + 1]
    return [system.GetOutputPort(name).Eval(context) for name in names]


@pytest.mark.parametrize("dt", [1e-3, 0.02])
@pytest.mark.parametrize(
    "window, order, evaluation",
    [
        (80, 2, "centre"),
        (80, 1, "centre"),
        (80, 2, "end"),
        (81, 1, "end"),
        (7, 2, "centre"),
        (4, 1, "centre"),
        (3, 2, "end"),
        (2, 1, "end"),
    ],
)
def test_coefficients_match_scipy(window, order, evaluation, dt):
    weights = savgol_coefficients(window, order, dt, evaluation)
    assert weights.shape == (order + 1, window)
    pos = (window - 1) / 2 if evaluation == "centre" else window - 1
    for d in range(order + 1):
        expected = scipy.signal.savgol_coeffs(
            window, order, deriv=d, delta=dt, pos=pos, use="dot"
        )
        scale = np.max(np.abs(expected))
        np.testing.assert_allclose(weights[d], expected, rtol=0, atol=1e-11 * scale)


@pytest.mark.parametrize("order", [1, 2])
@pytest.mark.parametrize("evaluation", ["centre", "end"])
def test_coefficients_exact_on_polynomials(order, evaluation):
    window, t_newest = 80, 0.3
    times = t_newest - PERIOD * np.arange(window)[::-1]  # oldest..newest
    t_eval = t_newest - ((window - 1) / 2 * PERIOD if evaluation == "centre" else 0.0)
    weights = savgol_coefficients(window, order, PERIOD, evaluation)
    for degree in range(order + 1):
        coefficients = _polynomial(degree, 4, seed=degree)
        samples = np.array([np.polyval(c, times) for c in coefficients]).T
        expected = _derivatives(coefficients, t_eval)
        for d in range(order + 1):
            np.testing.assert_allclose(
                weights[d] @ samples, expected[d], rtol=1e-7, atol=1e-7
            )


@pytest.mark.parametrize(
    "window, order, evaluation, field",
    [
        (2, 2, "centre", "window=2"),
        (1, 1, "end", "window=1"),
        (80, 3, "centre", "order=3"),
        (80, 0, "centre", "order=0"),
        (80, 2, "middle", "evaluation='middle'"),
        (80.5, 2, "centre", "window=80.5"),
        ("80", 2, "centre", "window='80'"),
        (80, 2.0, "centre", "order=2.0"),
    ],
)
def test_bad_parameters_raise(window, order, evaluation, field):
    with pytest.raises(ValueError, match=f"SavitzkyGolayConfig: {field}"):
        SavitzkyGolayConfig(window=window, order=order, evaluation=evaluation)
    with pytest.raises(ValueError, match=f"SavitzkyGolayFilter: {field}"):
        SavitzkyGolayFilter(3, window, order, PERIOD, evaluation)
    with pytest.raises(ValueError, match=f"savgol_coefficients: {field}"):
        savgol_coefficients(window, order, PERIOD, evaluation)


def test_bad_filter_arguments_raise():
    with pytest.raises(ValueError, match="period=0.0"):
        SavitzkyGolayFilter(3, 10, 2, period=0.0)
    with pytest.raises(ValueError, match="num_signals=0"):
        SavitzkyGolayFilter(0, 10, 2)
    with pytest.raises(ValueError, match="dt=nan"):
        savgol_coefficients(10, 2, math.nan)


def test_config_from_yaml():
    config = yaml_load_typed(
        schema=SavitzkyGolayConfig, data="window: 21\norder: 1\nevaluation: end\n"
    )
    system = SavitzkyGolayFilter.from_config(5, config, period=2e-3)
    assert (system.window(), system.order(), system.evaluation()) == (21, 1, "end")
    assert system.period() == 2e-3 and system.delay() == 0.0
    # yaml_load_typed sets fields after __post_init__: from_config validates.
    bad = yaml_load_typed(schema=SavitzkyGolayConfig, data="window: 1\n")
    with pytest.raises(ValueError, match="window=1"):
        SavitzkyGolayFilter.from_config(5, bad)
    with pytest.raises(RuntimeError, match="windw"):
        yaml_load_typed(schema=SavitzkyGolayConfig, data="windw: 21\n")


def test_ports_and_delay():
    system = SavitzkyGolayFilter(4, window=80, order=2, period=PERIOD)
    names = [system.get_output_port(i).get_name() for i in range(5)]
    assert names == [
        "value",
        "derivative",
        "second_derivative",
        "evaluation_time",
        "input_fault",
    ]
    assert system.get_input_port().get_name() == "signal"
    assert system.get_input_port().size() == 4
    assert system.delay() == pytest.approx(0.0395)  # (80 - 1) / 2 ms
    # One tick from sample to estimate: every output is the tick of the sample now
    # held (direct feedthrough); the delay is the window's evaluation point alone.
    for i in range(system.num_output_ports()):
        assert system.HasDirectFeedthrough(0, i)
    first_order = SavitzkyGolayFilter(4, window=80, order=1, evaluation="end")
    assert first_order.num_output_ports() == 4
    assert not first_order.HasOutputPort("second_derivative")
    assert first_order.delay() == 0.0


@pytest.mark.parametrize(
    "window, order, evaluation",
    [(80, 2, "centre"), (80, 2, "end"), (21, 1, "centre"), (21, 1, "end")],
)
def test_filter_in_diagram_exact_on_polynomial(window, order, evaluation):
    coefficients = _polynomial(order, 3, seed=window)
    builder = DiagramBuilder()
    source = builder.AddSystem(_PolynomialSource(coefficients))
    system = builder.AddSystem(
        SavitzkyGolayFilter(3, window, order, PERIOD, evaluation)
    )
    initial = [np.polyval(c, 0.0) for c in coefficients]
    builder.Connect(
        _sampled(builder, source.get_output_port(), 3, initial),
        system.get_input_port(),
    )
    simulator = Simulator(builder.Build())
    # Events at the final time are not handled: the last sample is at t = 0.150 s.
    simulator.AdvanceTo(0.1505)
    context = system.GetMyContextFromRoot(simulator.get_context())

    assert system.is_ready(context)
    # The outputs: the tick of the sample held, the one taken at 0.150 s.
    t_eval = system.GetOutputPort("evaluation_time").Eval(context)[0]
    assert t_eval == pytest.approx(0.150 - system.delay(), abs=1e-12)
    # The accessor reads the committed state: the previous sample's tick.
    assert system.evaluation_time(context) == pytest.approx(t_eval - PERIOD, abs=1e-12)
    expected = _derivatives(coefficients, t_eval)
    for d, output in enumerate(_outputs(system, context)):
        np.testing.assert_allclose(output, expected[d], rtol=1e-7, atol=1e-7)


def test_start_up_behaviour():
    window = 10
    system = SavitzkyGolayFilter(2, window, order=2, period=PERIOD)
    context = system.CreateDefaultContext()

    def ramp(t):
        return np.array([1.0 + 3.0 * t, -2.0 + 50.0 * t])

    # A bare default context: a committed state of zeros, not ready; its outputs
    # are already the tick of the sample held, whose first sample fills the window.
    assert not system.is_ready(context)
    assert system.evaluation_time(context) == 0.0
    system.get_input_port().FixValue(context, ramp(0.0))
    value, derivative, second_derivative = _outputs(system, context)
    np.testing.assert_array_equal(value, ramp(0.0))
    np.testing.assert_array_equal(derivative, [0.0, 0.0])

    # Initialization fills the window with the input: the estimate of a constant.
    context = system.CreateDefaultContext()
    context.SetTime(0.0)
    system.get_input_port().FixValue(context, ramp(0.0))
    Simulator(system, context).Initialize()
    value, derivative, second_derivative = _outputs(system, context)
    np.testing.assert_array_equal(value, ramp(0.0))
    np.testing.assert_array_equal(derivative, [0.0, 0.0])
    np.testing.assert_array_equal(second_derivative, [0.0, 0.0])
    assert system.evaluation_time(context) == pytest.approx(-system.delay())
    assert not system.is_ready(context)

    # Then each sample replaces one copy of the first: a fit of the padded window,
    # in the outputs of the tick of that sample; the commit at the next sampling
    # instant makes it the state (what the accessors read).
    weights = savgol_coefficients(window, 2, PERIOD, "centre")
    for m in range(1, window + 1):  # m samples received
        t_newest = (m - 1) * PERIOD
        context.SetTime(t_newest)
        system.get_input_port().FixValue(context, ramp(t_newest))
        received = [ramp(i * PERIOD) for i in range(m)]
        padded = np.array([received[0]] * (window - m) + received)
        outputs = _outputs(system, context)
        for d, output in enumerate(outputs):
            np.testing.assert_allclose(output, weights[d] @ padded, atol=1e-9)
        t_port = system.GetOutputPort("evaluation_time").Eval(context)[0]
        assert t_port == pytest.approx(t_newest - system.delay())
        commit(system, context, m * PERIOD)
        assert system.is_ready(context) == (m == window)
        assert system.evaluation_time(context) == t_port
    # Ready: exact on the ramp, at the window's centre.
    t_eval = system.evaluation_time(context)
    value, derivative, second_derivative = outputs
    np.testing.assert_allclose(value, ramp(t_eval), atol=1e-12)
    np.testing.assert_allclose(derivative, [3.0, 50.0], rtol=1e-9)
    np.testing.assert_allclose(second_derivative, [0.0, 0.0], atol=1e-6)


def test_each_sample_enters_once_in_a_simulator():
    """Behind a sampler (offset 0, the station's with no lead), the filter commits at
    the same float instants as the sampler latches: each sample k is the tick at
    [k, k + 1) periods and enters the window once (a commit a rounding later than the
    latch would take sample k + 1 as tick k's, then see it twice). A ramp of one per
    sample: the last two samples' slope is 1/period at every tick, over 2 s."""
    from pydrake.trajectories import PiecewisePolynomial

    count = 2000
    times = PERIOD * (np.arange(count + 1) - 0.5)
    ramp = np.arange(count + 1, dtype=float)[None, :]
    builder = DiagramBuilder()
    source = builder.AddSystem(
        TrajectorySource(PiecewisePolynomial.ZeroOrderHold(times, ramp))
    )
    system = builder.AddSystem(SavitzkyGolayFilter(1, 2, 1, PERIOD, "end"))
    builder.Connect(
        _sampled(builder, source.get_output_port(), 1, [0.0]), system.get_input_port()
    )
    simulator = Simulator(builder.Build())
    context = system.GetMyContextFromRoot(simulator.get_context())
    value, slope = [], []
    for k in range(1, count - 1):
        simulator.AdvanceTo((k + 0.5) * PERIOD)
        value.append(system.GetOutputPort("value").Eval(context)[0])
        slope.append(system.GetOutputPort("derivative").Eval(context)[0])
    np.testing.assert_allclose(value, np.arange(1, count - 1), rtol=0, atol=1e-9)
    np.testing.assert_allclose(slope, 1 / PERIOD, rtol=1e-9)


def test_causal_centre_equals_offline_on_noise():
    """The ring buffer and the offline function use the same weights: the centre
    estimate after sample m is the offline estimate at sample m - (N - 1) / 2."""
    window, num_samples = 21, 120
    x = np.random.default_rng(1).normal(size=(num_samples, 3))
    offline = savgol_filter_offline(x, PERIOD, window, 2)
    system = SavitzkyGolayFilter(3, window, 2, PERIOD, "centre")
    half = (window - 1) // 2
    checked = []

    def check(m, context):
        if m >= window - 1:
            t_eval = system.GetOutputPort("evaluation_time").Eval(context)[0]
            assert t_eval == pytest.approx((m - half) * PERIOD)
            for d, output in enumerate(_outputs(system, context)):
                np.testing.assert_allclose(
                    output, offline[d][m - half], rtol=1e-9, atol=1e-9
                )
            checked.append(m)

    run_ticks(
        system,
        system.CreateDefaultContext(),
        {system.get_input_port(): x},
        PERIOD,
        check,
    )
    assert len(checked) == num_samples - window + 1


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_non_finite_samples_are_held_and_flagged(bad):
    """A 3-sample burst of bad entries: the filter holds each bad entry's previous
    value, its estimates stay finite (here: exactly the constant), input_fault counts
    the consecutive bad samples and returns to 0 at the next good one."""
    from pydrake.trajectories import PiecewisePolynomial

    good = np.array([1.0, -2.0, 2.0, 0.5])
    burst = good.copy()
    burst[[1, 3]] = bad
    # Samples at 1 ms ticks: good, then bad at 10, 11, 12 ms, then good again.
    values = np.column_stack([good, burst, good, good])
    source = PiecewisePolynomial.ZeroOrderHold([0.0, 0.0095, 0.0125, 1.0], values)
    builder = DiagramBuilder()
    src = builder.AddSystem(TrajectorySource(source))
    system = builder.AddNamedSystem("q_filter", SavitzkyGolayFilter(4, 10, 2))
    builder.Connect(
        _sampled(builder, src.get_output_port(), 4, good), system.get_input_port()
    )
    simulator = Simulator(builder.Build())
    context = system.GetMyContextFromRoot(simulator.get_context())
    faults = []
    for t in (np.arange(1, 30) + 0.5) * 1e-3:
        simulator.AdvanceTo(t)
        value = system.GetOutputPort("value").Eval(context)
        np.testing.assert_allclose(value, good, atol=1e-12)
        assert np.all(np.isfinite(system.GetOutputPort("derivative").Eval(context)))
        faults.append(system.GetOutputPort("input_fault").Eval(context)[0])
    assert faults[8:14] == [0.0, 1.0, 2.0, 3.0, 0.0, 0.0]
    assert system.bad_sample_count(context) == 3


def test_wrong_size_input_raises():
    system = SavitzkyGolayFilter(4, 10, 2)
    context = system.CreateDefaultContext()
    with pytest.raises(RuntimeError, match="size=4 for input port 'signal'"):
        system.get_input_port().FixValue(context, np.zeros(3))
    builder = DiagramBuilder()
    source = builder.AddSystem(ConstantVectorSource(np.zeros(3)))
    builder.AddSystem(system)
    with pytest.raises(RuntimeError, match="size"):
        builder.Connect(source.get_output_port(), system.get_input_port())


@pytest.mark.parametrize("window", [5, 81])
@pytest.mark.parametrize("order", [1, 2])
@pytest.mark.parametrize("axis", [0, 1])
def test_offline_matches_scipy(window, order, axis):
    x = np.random.default_rng(2).normal(size=(300, 4))
    x = x if axis == 0 else x.T
    dt = 2e-3
    estimates = savgol_filter_offline(x, dt, window, order, axis=axis)
    assert len(estimates) == 3
    if order == 1:
        assert estimates[2] is None
    for d in range(order + 1):
        expected = scipy.signal.savgol_filter(
            x, window, order, deriv=d, delta=dt, axis=axis, mode="interp"
        )
        assert estimates[d].shape == x.shape
        scale = np.max(np.abs(expected))
        np.testing.assert_allclose(estimates[d], expected, rtol=0, atol=1e-10 * scale)


def test_offline_exact_on_polynomial_including_edges():
    t = np.arange(200) * PERIOD
    coefficients = _polynomial(2, 3, seed=3)
    x = np.array([np.polyval(c, t) for c in coefficients]).T
    estimates = savgol_filter_offline(x, PERIOD, 81, 2)
    for d in range(3):
        expected = np.array([_derivatives(coefficients, ti)[d] for ti in t])
        np.testing.assert_allclose(estimates[d], expected, rtol=1e-7, atol=1e-7)


def test_offline_bad_inputs_raise():
    x = np.zeros((100, 2))
    with pytest.raises(ValueError, match="window=80 must be odd"):
        savgol_filter_offline(x, PERIOD, 80, 2)
    with pytest.raises(ValueError, match="100 samples along axis 0.*window=101"):
        savgol_filter_offline(x, PERIOD, 101, 2)
    with pytest.raises(ValueError, match="window=2 must be an integer >= order"):
        savgol_filter_offline(x, PERIOD, 2, 2)
    x[42, 1] = math.nan
    with pytest.raises(ValueError, match=r"not finite at index \[42, 1\]"):
        savgol_filter_offline(x, PERIOD, 21, 2)


def _run_on_noise(system: SavitzkyGolayFilter, samples: np.ndarray) -> list[np.ndarray]:
    """Feeds `samples` (T, k) one per period; returns the outputs of the last tick."""
    last = []

    def keep(k, context):
        if k == len(samples) - 1:
            last.extend(output.copy() for output in _outputs(system, context))

    _feed(system, samples, keep)
    return last


def _feed(system: SavitzkyGolayFilter, samples: np.ndarray, each=None):
    """Runs the filter tick by tick as the sampler does (`tests.ticks`): sample k
    held at tick k, after the initialization on sample 0; calls each(k, context) with
    the outputs of tick k; returns the context."""
    context = system.CreateDefaultContext()
    return run_ticks(system, context, {system.get_input_port(): samples}, PERIOD, each)


def test_per_signal_windows_are_centred_on_one_instant():
    """Each signal is the fit of its own window, every window centred on the longest
    one's centre: signal i equals a filter of its window alone, (N_max − N_i) / 2
    updates earlier (its own, shorter delay)."""
    windows = [21, 41, 81]
    samples = np.random.default_rng(3).normal(size=(200, 3))
    system = SavitzkyGolayFilter(3, windows, 2, PERIOD)
    assert system.windows() == (21, 41, 81) and system.window() == 81
    assert system.delay() == pytest.approx(40 * PERIOD)
    together = _run_on_noise(system, samples)
    for i, window in enumerate(windows):
        earlier = (81 - window) // 2
        alone = _run_on_noise(
            SavitzkyGolayFilter(1, window, 2, PERIOD), samples[: 200 - earlier, [i]]
        )
        for d in range(3):
            assert together[d][i] == pytest.approx(alone[d][0], rel=1e-12, abs=1e-9)


@pytest.mark.parametrize("span", [None, 61])
def test_per_signal_windows_exact_on_polynomials_at_the_common_time(span):
    coefficients = _polynomial(2, 3, seed=5)
    builder = DiagramBuilder()
    source = builder.AddSystem(_PolynomialSource(coefficients))
    system = builder.AddSystem(
        SavitzkyGolayFilter(3, [11, 31, 41], 2, PERIOD, span=span)
    )
    initial = [np.polyval(c, 0.0) for c in coefficients]
    builder.Connect(
        _sampled(builder, source.get_output_port(), 3, initial),
        system.get_input_port(),
    )
    simulator = Simulator(builder.Build())
    simulator.AdvanceTo(0.1005)
    context = system.GetMyContextFromRoot(simulator.get_context())
    assert system.delay() == pytest.approx(((span or 41) - 1) / 2 * PERIOD)
    t_eval = system.GetOutputPort("evaluation_time").Eval(context)[0]
    assert t_eval == pytest.approx(0.100 - system.delay(), abs=1e-12)
    expected = _derivatives(coefficients, t_eval)
    for d, output in enumerate(_outputs(system, context)):
        np.testing.assert_allclose(output, expected[d], rtol=1e-7, atol=1e-7)


def test_a_shorter_window_centred_in_the_past_keeps_its_derivatives_aligned():
    """A parabola's fitted q̈ describes the window's centre: centring every window on
    one instant keeps q̈ aligned on a cubic, where evaluating a short window at that
    instant from its newest end would not."""
    coefficients = np.array([[40.0, -3.0, 1.0, 0.5]])  # a cubic: q̈ changes
    samples = np.array([[np.polyval(coefficients[0], k * PERIOD)] for k in range(300)])
    short_centred = _run_on_noise(
        SavitzkyGolayFilter(1, [21], 2, PERIOD, span=81), samples
    )
    long = _run_on_noise(SavitzkyGolayFilter(1, 81, 2, PERIOD), samples)
    t = 299 * PERIOD - 40 * PERIOD
    truth = np.poly1d(coefficients[0]).deriv(2)(t)
    assert short_centred[2][0] == pytest.approx(truth, rel=1e-9)
    assert long[2][0] == pytest.approx(truth, rel=1e-9)


@pytest.mark.parametrize(
    "window, evaluation, span, match",
    [
        ([21, 41], "centre", None, "window has 2 values for 3 signals"),
        ([21, 41, 2], "centre", None, "window=2"),
        (
            [21, 40, 81],
            "centre",
            None,
            r"windows \[40\] differ in parity from the span, 81",
        ),
        ([21, 41, 81], "end", None, "need evaluation='centre'"),
        (21, "centre", 11, "span=11 must be an integer >= the longest window, 21"),
    ],
)
def test_per_signal_window_errors(window, evaluation, span, match):
    with pytest.raises(ValueError, match=match):
        SavitzkyGolayFilter(3, window, 2, PERIOD, evaluation, span=span)


# ------------------------------------------------------------------ the step alone


@pytest.mark.parametrize(
    "window, order, span",
    [(21, 2, None), (21, 1, None), ([11, 5, 21, 21], 2, None), ([7, 3, 9, 9], 1, 13)],
)
def test_step_on_plain_arrays_equals_the_filter(window, order, span):
    """SavitzkyGolayFilterStep driven by arrays (no Drake) gives the filter's outputs to
    the bit, tick by tick, through start-up and a burst of bad samples."""
    samples = np.random.default_rng(7).normal(size=(60, 4))
    samples[30:33, [0, 2]] = math.nan
    system = SavitzkyGolayFilter(4, window, order, PERIOD, span=span)
    step = SavitzkyGolayFilterStep(4, window, order, PERIOD, "centre", span)
    names = step.output_names()
    assert names == tuple(
        system.get_output_port(i).get_name() for i in range(system.num_output_ports())
    )
    assert step.state_size == _RING + step.window() * 4 + (order + 1) * 4 + 2
    filtered = []
    _feed(
        system,
        samples,
        lambda k, context: filtered.append(
            [system.GetOutputPort(name).Eval(context).copy() for name in names]
        ),
    )
    step.initialize(0.0, samples[0])
    for k, sample in enumerate(samples):
        step.step(k * PERIOD, sample)
        for name, expected in zip(names, filtered[k]):
            np.testing.assert_array_equal(getattr(step, name), expected)
    assert step.input_fault[0] == 0.0 and step.bad_sample_count() == 3
    assert step.is_ready()


def test_step_exact_on_a_ramp_and_bound_to_a_buffer():
    """The step's numbers: a ramp's value and slope at the window's centre once ready;
    bound to a slice of a larger vector (as a fused controller does) it goes on
    identically, its named arrays views on that vector."""
    window = 9
    step = SavitzkyGolayFilterStep(2, window, 2, PERIOD, "centre")
    assert step.delay() == pytest.approx(4e-3)

    def ramp(t):
        return np.array([1.0 + 3.0 * t, -2.0 + 50.0 * t])

    step.initialize(0.0, ramp(0.0))
    np.testing.assert_array_equal(step.value, [1.0, -2.0])
    np.testing.assert_array_equal(step.derivative, [0.0, 0.0])
    assert not step.is_ready()
    for m in range(window):
        step.step(m * PERIOD, ramp(m * PERIOD))
    assert step.is_ready() and step.bad_sample_count() == 0
    assert step.evaluation_time[0] == pytest.approx(4e-3)
    np.testing.assert_allclose(step.value, [1.012, -1.8], rtol=0, atol=1e-12)
    np.testing.assert_allclose(step.derivative, [3.0, 50.0], rtol=1e-9)
    np.testing.assert_allclose(step.second_derivative, [0.0, 0.0], atol=1e-6)

    alone = SavitzkyGolayFilterStep(2, window, 2, PERIOD, "centre")
    alone.state[:] = step.state
    fused = np.full(step.state_size + 3, -1.0)
    step.bind(fused[2:-1])
    assert np.shares_memory(step.value, fused)
    for m in range(window, 2 * window):  # a parabola on signal 1 fills the window
        sample = ramp(m * PERIOD) + [0.0, 1e-3 * m**2]
        step.step(m * PERIOD, sample)
        alone.step(m * PERIOD, sample)
    np.testing.assert_array_equal(fused[2:-1], alone.state)
    np.testing.assert_array_equal(fused[[0, 1, -1]], [-1.0, -1.0, -1.0])
    np.testing.assert_array_equal(step.second_derivative, alone.second_derivative)
    assert step.second_derivative[1] == pytest.approx(2e-3 / PERIOD**2, rel=1e-9)


# ------------------------------------------------------------------ the numba kernel


def _kernel_samples(num_signals: int, ticks: int, seed: int) -> np.ndarray:
    """Smooth signals of different scales with noise, a burst of NaN and inf entries,
    and a bad entry in the very first sample (held at 0)."""
    rng = np.random.default_rng(seed)
    t = np.arange(ticks) * PERIOD
    scales = np.logspace(-2, 3, num_signals)
    samples = scales * (
        np.sin(2 * np.pi * np.outer(t, rng.uniform(0.5, 3.0, num_signals)))
        + 1e-3 * rng.normal(size=(ticks, num_signals))
    )
    samples[0, 1] = math.nan
    samples[30:33, [0, 2]] = math.nan
    samples[31, 3] = -math.inf
    return samples


def _run_step(step: SavitzkyGolayFilterStep, samples: np.ndarray) -> np.ndarray:
    """initialize, then one step per sample; the whole state after each."""
    step.initialize(0.0, samples[0])
    states = []
    for m, sample in enumerate(samples):
        step.step(m * PERIOD, sample)
        states.append(step.state.copy())
    return np.array(states)


_KERNEL_CASES = [
    (21, 2, None),
    (9, 1, None),
    ([11, 5, 21, 21, 7], 2, None),
    ([7, 3, 9, 9, 3], 1, 13),
]


@pytest.mark.parametrize("window, order, span", _KERNEL_CASES)
def test_kernel_compiled_equals_interpreted(window, order, span):
    """The compiled kernel and its Python source give the same states, to the bit
    (elementwise code, and the same sums in the same order, no fma), through
    start-up, bad samples and a bound state."""
    from hrp2_drake import kernels

    samples = _kernel_samples(5, 70, seed=11)

    def make():
        return SavitzkyGolayFilterStep(5, window, order, PERIOD, "centre", span)

    compiled = _run_step(make(), samples)
    # (With NUMBA_DISABLE_JIT both are the Python source.)
    with kernels.interpreted() if kernels.jit_enabled() else contextlib.nullcontext():
        interpreted = _run_step(make(), samples)
        bound = make()
        buffer = np.full(bound.state_size + 7, -3.0)
        bound.bind(buffer[4:-3])
        interpreted_bound = _run_step(bound, samples)
    np.testing.assert_array_equal(compiled, interpreted)
    np.testing.assert_array_equal(compiled, interpreted_bound)
    np.testing.assert_array_equal(buffer[[0, 1, 2, 3, -3, -2, -1]], -3.0)
    assert np.all(np.isfinite(compiled))


@pytest.mark.parametrize("window, order, span", _KERNEL_CASES)
def test_kernel_equals_the_weighted_window(window, order, span):
    """Each estimate is savgol_coefficients' weights times the signal's own window
    (centred on the span's centre), as numpy's products computed it before the
    kernel: equal up to rounding, 1e-14 of the sum of the terms' magnitudes (the
    difference is rounding in the sum, where weights ~1/dt² cancel)."""
    k = 5
    samples = _kernel_samples(k, 70, seed=12)
    samples[0, 1] = 0.0  # no bad samples here: the window is the samples themselves
    samples[30:33] = samples[29]
    step = SavitzkyGolayFilterStep(k, window, order, PERIOD, "centre", span)
    states = _run_step(step, samples)
    N, windows = step.window(), step.windows()
    fit = step.rows("value").start
    for m in range(N - 1, len(samples)):
        estimates = states[m, fit : fit + (order + 1) * k].reshape(order + 1, k)
        for i, n in enumerate(windows):
            weights = savgol_coefficients(n, order, PERIOD, "centre")
            newest = m - (N - n) // 2
            window_samples = samples[newest - n + 1 : newest + 1, i]
            expected = weights @ window_samples
            magnitude = np.abs(weights) @ np.abs(window_samples)
            np.testing.assert_array_less(
                np.abs(estimates[:, i] - expected), 1e-14 * magnitude + 1e-300
            )


def test_warm_up_then_frozen_a_tick_runs_and_a_new_signature_raises():
    """warm_up compiles (or loads) the kernel for a tick's types without changing the
    state; frozen, a step (alone or bound to a larger vector, as the fused controller
    binds it) runs, a float32 signal raises instead of compiling."""
    from hrp2_drake import kernels
    from hrp2_drake.estimation.savitzky_golay import savgol_step

    if not kernels.jit_enabled():
        pytest.skip("NUMBA_DISABLE_JIT: nothing compiles")
    step = SavitzkyGolayFilterStep(4, [11, 5, 11, 7], 2, PERIOD, "centre")
    bound = SavitzkyGolayFilterStep(4, 9, 1, PERIOD, "centre")
    buffer = np.zeros(bound.state_size + 2)
    bound.bind(buffer[1:-1])
    step.initialize(0.0, np.arange(4.0))
    before = step.state.copy()
    step.warm_up()
    bound.warm_up()
    np.testing.assert_array_equal(step.state, before)
    kernels.freeze()
    try:
        for m in range(12):
            step.step(m * PERIOD, np.arange(4.0) + m)
            bound.step(m * PERIOD, np.arange(4.0) - m)
        np.testing.assert_allclose(step.derivative, [1000.0] * 4, rtol=1e-9)
        np.testing.assert_allclose(bound.derivative, [-1000.0] * 4, rtol=1e-9)
        with pytest.raises(TypeError, match="float32"):
            step.step(0.1, np.zeros(4, dtype=np.float32))
        with pytest.raises(TypeError):
            savgol_step(
                0.1, np.zeros(4), step.state.astype(np.float32), step._constants
            )
    finally:
        kernels.thaw()


def test_a_signal_of_the_wrong_size_raises():
    step = SavitzkyGolayFilterStep(4, 9, 2, PERIOD, "centre")
    with pytest.raises(ValueError, match="signal's size"):
        step.step(0.0, np.zeros(5))


def test_every_config_taking_an_evaluation_point_refuses_another_by_its_field():
    """One check (`check_evaluation`) for the filter's and both configs' field."""
    from hrp2_drake.assembly.torque_control import EstimatorSettings
    from hrp2_drake.estimation.estimator_config import TorqueEstimatorConfig

    field = r"\.evaluation='middle' must be one of \('centre', 'end'\)"
    with pytest.raises(ValueError, match=f"TorqueControlConfig.estimator{field}"):
        EstimatorSettings(evaluation="middle").validate()
    with pytest.raises(ValueError, match=f"TorqueEstimatorConfig{field}"):
        TorqueEstimatorConfig(joints=["j"], evaluation="middle").validate()
