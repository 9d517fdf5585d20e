"""DisturbanceObserver on synthetic signals with a known disturbance: a joint that
obeys the motor model exactly plus a torque d(t), seen through an estimator delay."""

import math

import numpy as np
import pytest
from ticks import commit

from hrp2_drake import kernels
from hrp2_drake.control import disturbance_observer
from hrp2_drake.control.disturbance_observer import (
    DisturbanceObserver,
    DisturbanceObserverConfig,
    DisturbanceObserverStep,
)
from hrp2_drake.identification.motor_model import MotorModel

JOINTS = ["hip", "knee"]
MODEL = MotorModel(JOINTS, [2e-4, 5e-5], [0.013, 0.0066], [0.0, 1e-4])
PERIOD, DELAY = 0.001, 0.041


def _signals(disturbance, steps: int, nan_at=()):
    """Per step: Δq as sent, q̂̇ and τ̂ delayed by DELAY (a NaN τ̂ at `nan_at`); and
    the disturbance d per step."""
    lag = round(DELAY / PERIOD)
    t = np.arange(steps + lag) * PERIOD
    delta_q = np.column_stack([3e-3 * np.sin(7 * t), 2e-3 * np.cos(5 * t)])
    v = np.column_stack([0.8 * np.cos(3 * t), -1.1 * np.sin(4 * t)])
    d = np.array([disturbance(x) for x in t])
    # The joint obeys eq. 6 plus the disturbance: τ = (Δq − K_v q̇ − K_c sign q̇)/K_τ + d.
    tau = (delta_q - MODEL.k_v * v - MODEL.k_c * np.sign(v)) / MODEL.k_tau + d
    old = np.maximum(np.arange(steps) - lag, 0)
    tau_old = tau[old]
    tau_old[list(nan_at)] = np.nan
    return delta_q[:steps], v[old], tau_old, d


def _run(disturbance, config: DisturbanceObserverConfig, steps: int = 800, nan_at=()):
    """Feeds the observer τ̂ and q̂̇ delayed by DELAY, Δq as sent, one sample a tick
    (tests/ticks.commit); returns d̂ per step."""
    observer = DisturbanceObserver(MODEL, config)
    context = observer.CreateDefaultContext()
    delta_q, v, tau, d = _signals(disturbance, steps, nan_at)
    out = []
    for k in range(steps):
        observer.get_input_port(0).FixValue(context, delta_q[k])
        observer.get_input_port(1).FixValue(context, v[k])
        observer.get_input_port(2).FixValue(context, tau[k])
        # Tick k committed at the next sampling instant: its d̂ is the held output.
        commit(observer, context, (k + 1) * PERIOD)
        out.append(observer.get_output_port().Eval(context).copy())
    return np.array(out), d


def test_a_step_disturbance_is_a_first_order_response():
    bandwidth = 20.0
    config = DisturbanceObserverConfig(
        JOINTS, bandwidth=bandwidth, delay=DELAY, period=PERIOD
    )
    step = 0.3
    estimate, _ = _run(lambda t: np.array([5.0, -2.0]) * (t >= step), config)
    alpha = 1 - math.exp(-bandwidth * PERIOD)
    lag = round(DELAY / PERIOD)
    # The observer sees the step lag periods after it happened, then filters it.
    k = np.arange(len(estimate))
    seen = np.clip(k - (round(step / PERIOD) + lag) + 1, 0, None)
    expected = np.outer(1 - (1 - alpha) ** seen, [5.0, -2.0])
    np.testing.assert_allclose(estimate, expected, atol=1e-9)
    # Time constant 1/bandwidth: 63% after 50 ms.
    settled = estimate[round(step / PERIOD) + lag + 49, 0]
    assert settled == pytest.approx(5 * (1 - 1 / math.e), rel=0.02)


def test_no_disturbance_reads_zero_only_with_the_right_delay():
    config = DisturbanceObserverConfig(
        JOINTS, bandwidth=20.0, delay=DELAY, period=PERIOD
    )
    estimate, _ = _run(lambda t: np.zeros(2), config)
    assert np.abs(estimate).max() < 1e-9
    # Δq taken 10 ms too fresh: the model's torque no longer matches τ̂.
    wrong = DisturbanceObserverConfig(
        JOINTS, bandwidth=20.0, delay=DELAY - 0.010, period=PERIOD
    )
    estimate, _ = _run(lambda t: np.zeros(2), wrong)
    assert np.abs(estimate[200:]).max() > 0.5  # measured 1.9 N·m


def test_nan_input_holds_the_estimate_and_limit_clips():
    config = DisturbanceObserverConfig(
        JOINTS, bandwidth=50.0, delay=DELAY, limit=[3.0, 10.0], period=PERIOD
    )
    estimate, _ = _run(
        lambda t: np.array([5.0, -2.0]), config, steps=400, nan_at=range(300, 320)
    )
    np.testing.assert_array_equal(estimate[300:320], np.tile(estimate[299], (20, 1)))
    assert estimate[-1, 0] == pytest.approx(3.0)  # clipped
    assert estimate[-1, 1] == pytest.approx(-2.0, abs=1e-6)
    # Nothing before Δq is that old.
    assert not np.any(estimate[: round(DELAY / PERIOD)])


@pytest.mark.parametrize(
    "changes, message",
    [
        (dict(joints=[]), "joints is empty"),
        (dict(bandwidth=0.0), "bandwidth"),
        (dict(delay=-1.0), "delay"),
        (dict(limit=[1.0, 2.0, 3.0]), "limit"),
    ],
)
def test_bad_config(changes, message):
    config = DisturbanceObserverConfig(
        **{"joints": JOINTS, "period": PERIOD, **changes}
    )
    with pytest.raises(ValueError, match=message):
        DisturbanceObserver(MODEL, config)
    with pytest.raises(KeyError, match="ankle"):
        DisturbanceObserver(MODEL, DisturbanceObserverConfig(["ankle"], period=PERIOD))


def test_the_step_on_plain_arrays_is_the_system():
    """The step driven by plain arrays (no Context) gives the LeafSystem's d̂ bit for
    bit (a NaN τ̂ included), and raw_disturbance into a buffer equals the new-array
    form."""
    config = DisturbanceObserverConfig(
        JOINTS, bandwidth=50.0, delay=DELAY, limit=[3.0, 10.0], period=PERIOD
    )
    disturbance = lambda t: np.array([5.0, -2.0]) * (t >= 0.1)  # noqa: E731
    nan_at = range(150, 160)
    expected, _ = _run(disturbance, config, steps=300, nan_at=nan_at)
    delta_q, v, tau, _ = _signals(disturbance, 300, nan_at)
    step = DisturbanceObserverStep(MODEL, config)
    assert step.delay_periods() == 41
    out = []
    for k in range(300):
        step.step(k * PERIOD, delta_q[k], v[k], tau[k])
        out.append(step.disturbance.copy())
    np.testing.assert_array_equal(out, expected)
    # The step's d̂ after 300 ms: 159 periods of the filter on the step seen at
    # 141 ms, minus the 10 held ones; joint 0 clipped at 3 N·m.
    alpha = 1 - math.exp(-50.0 * PERIOD)
    assert out[-1][0] == 3.0
    assert out[-1][1] == pytest.approx(-2.0 * (1 - (1 - alpha) ** 149), abs=1e-9)
    # Aligned samples (Δq sent 41 periods before): d itself.
    buffer = np.zeros(2)
    raw = step.raw_disturbance(delta_q[159], v[200], tau[200], out=buffer)
    assert raw is buffer
    np.testing.assert_allclose(raw, [5.0, -2.0], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(
        raw, step.raw_disturbance(delta_q[159], v[200], tau[200])
    )


# --------------------------------------------------------------------- the kernels


def _kernel_run(config: DisturbanceObserverConfig) -> tuple[np.ndarray, np.ndarray]:
    """The observer's state after each of 200 periods (a step disturbance, NaN τ̂
    and a NaN Δq on the way, d̂ clipped), and raw_disturbance on (50, n) rows."""
    disturbance = lambda t: np.array([5.0, -2.0]) * (t >= 0.05)  # noqa: E731
    delta_q, v, tau, _ = _signals(disturbance, 200, nan_at=range(120, 125))
    delta_q[100, 0] = np.nan
    step = DisturbanceObserverStep(MODEL, config)
    states = []
    for k in range(200):
        step.step(k * PERIOD, delta_q[k], v[k], tau[k])
        states.append(step.state.copy())
    return np.array(states), step.raw_disturbance(delta_q[:50], v[:50], tau[:50])


@pytest.mark.skipif(not kernels.jit_enabled(), reason="NUMBA_DISABLE_JIT: no kernels")
@pytest.mark.parametrize("delay", [DELAY, 0.0])
def test_kernel_compiled_equals_interpreted(delay):
    """The kernels compiled and as their Python source (`kernels.interpreted`) on
    the same periods (K_c sign(q̂̇) on the knee, the clip, bad input, with and
    without the Δq delay): the same states and raw d bit for bit."""
    config = DisturbanceObserverConfig(
        JOINTS, bandwidth=50.0, delay=delay, limit=[3.0, 10.0], period=PERIOD
    )
    compiled = _kernel_run(config)
    with kernels.interpreted():
        assert not hasattr(disturbance_observer._observer_step, "py_func")  # Python
        interpreted = _kernel_run(config)
    for a, b in zip(compiled, interpreted):
        np.testing.assert_array_equal(a, b)
    assert compiled[0][-1, 0] == 3.0  # clipped
    assert np.all(np.isfinite(compiled[0]))


def test_warm_up_then_frozen():
    """warm_up compiles the kernels for a tick's arrays without touching the state;
    frozen, a real tick on a step bound into a larger state (as in the fused
    controller) runs, and arrays of another type raise instead of compiling."""
    config = DisturbanceObserverConfig(
        JOINTS, bandwidth=50.0, delay=DELAY, period=PERIOD
    )
    step = DisturbanceObserverStep(MODEL, config)
    buffer = np.zeros(step.state_size + 5)
    step.bind(buffer[2 : 2 + step.state_size])
    delta_q, v, tau, _ = _signals(lambda t: np.array([5.0, -2.0]), 60)
    for k in range(45):
        step.step(k * PERIOD, delta_q[k], v[k], tau[k])
    before = buffer.copy()
    step.warm_up()
    np.testing.assert_array_equal(buffer, before)
    if kernels.jit_enabled():  # every kernel of the module compiled
        mine = [
            k
            for k in kernels.kernels()
            if k.py_func.__module__ == disturbance_observer.__name__
        ]
        assert mine and all(k.signatures for k in mine)
    try:
        kernels.freeze()
        step.step(45 * PERIOD, delta_q[45], v[45], tau[45])
        assert step.disturbance[0] > 0.0 and step.counters[1] == 46
        raw = step.raw_disturbance(delta_q[4], v[45], tau[45], out=np.zeros(2))
        np.testing.assert_allclose(raw, [5.0, -2.0], atol=1e-9)
        if kernels.jit_enabled():
            with pytest.raises(TypeError):
                step.step(0.0, delta_q[46].astype(np.float32), v[46], tau[46])
    finally:
        kernels.thaw()
    state = step.state.copy()
    with pytest.raises(ValueError, match="2 entries"):
        step.step(0.0, delta_q[46][:1], v[46], tau[46])
    np.testing.assert_array_equal(step.state, state)
