"""DelayPredictor on synthetic joints that obey the motor model (eq. 6) with a known
inertia and rest torque, seen through an estimator delay: exact model, exact present;
a model error, still closer to the present than the delayed estimates."""

import math

import numpy as np
import pytest
from pydrake.common.yaml import yaml_load_typed
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource, MatrixGain
from scipy.integrate import solve_ivp
from ticks import commit

from hrp2_drake import kernels
from hrp2_drake.control import predictor
from hrp2_drake.control.predictor import (
    DelayPredictor,
    DelayPredictorConfig,
    DelayPredictorStep,
)
from hrp2_drake.identification.motor_model import MotorModel

JOINTS = ["hip", "knee", "ankle"]
K_TAU = np.array([2e-4, 5e-5, 1e-4])  # rad/(N·m)
K_V = np.array([0.013, 0.0066, 0.01])  # s
INERTIA = np.array([1.5, 0.8, 0.3])  # kg·m²; time constants 23, 6 and 3 ms
TAU_REST = np.array([30.0, -10.0, 5.0])  # N·m
MODEL = MotorModel(JOINTS, K_TAU, K_V)
PERIOD = 0.001
OFFSET = 100  # the plant runs this many periods before the predictor's first tick


class Joints:
    """n joints obeying K_v q̇ + K_τ m q̈ = Δq − K_τ τ_rest exactly, with Δq (and
    τ_rest) held over each period: u[j] acts over [j, j + 1) periods."""

    def __init__(self, u, tau_rest, k_tau=K_TAU, k_v=K_V, inertia=INERTIA):
        self.u = u
        self.tau_rest = np.broadcast_to(tau_rest, u.shape)
        self.k_tau, self.k_v, self.inertia = k_tau, k_v, inertia
        self.a = k_v / (k_tau * inertia)
        self.v = np.zeros((len(u) + 1, u.shape[1]))
        for j in range(len(u)):
            self.v[j + 1] = self.velocity(j, 1.0)

    def forcing(self, j):
        """g in q̈ = g − a q̇ over period j."""
        return (self.u[j] - self.k_tau * self.tau_rest[j]) / (self.k_tau * self.inertia)

    def velocity(self, j, fraction):
        h = fraction * PERIOD
        phi = np.exp(-self.a * h)
        return phi * self.v[j] + (1 - phi) / self.a * self.forcing(j)

    def at(self, s):
        """q̇, q̈, τ at s periods (q̈ and τ just after s)."""
        j = math.floor(s + 1e-9)
        v = self.velocity(j, s - j)
        vdot = self.forcing(j) - self.a * v
        return v, vdot, self.tau_rest[j] + self.inertia * vdot

    def just_before(self, j):
        """q̇ and τ at j periods, τ under u[j − 1]."""
        v = self.v[j]
        vdot = self.forcing(j - 1) - self.a * v
        return v, self.tau_rest[j - 1] + self.inertia * vdot


def _excitation(steps):
    """Δq holding the rest torque plus sums of sinusoids (rad)."""
    t = np.arange(steps) * PERIOD
    wave = np.column_stack(
        [
            2e-3 * np.sin(2 * np.pi * 1.3 * t) + 1e-3 * np.sin(2 * np.pi * 7.1 * t),
            1.5e-3 * np.cos(2 * np.pi * 2.9 * t) + 5e-4 * np.sin(2 * np.pi * 17 * t),
            1e-3 * np.sin(2 * np.pi * 4.3 * t + 1) + 1e-3 * np.sin(2 * np.pi * 11 * t),
        ]
    )
    return K_TAU * TAU_REST + wave


def _drive(predictor, ticks, inputs):
    """Fixes the inputs of each tick k (a dict of name -> (ticks, size) arrays) at
    k periods, commits the tick at the next sampling instant (`tests.ticks`) and
    reads its outputs there: they are held (the committed state), what the Δq
    controller reads at tick k + 1. Returns each output per tick."""
    context = predictor.CreateDefaultContext()
    ports = [predictor.get_output_port(i) for i in range(predictor.num_output_ports())]
    names = [port.get_name() for port in ports]
    out = {name: [] for name in names}
    for k in range(ticks):
        context.SetTime(k * PERIOD)
        for name, values in inputs.items():
            predictor.GetInputPort(name).FixValue(context, values[k])
        commit(predictor, context, (k + 1) * PERIOD)
        for name in names:
            out[name].append(predictor.GetOutputPort(name).Eval(context).copy())
    return {name: np.array(values) for name, values in out.items()}, context


def _scenario(joints, delay, latency, ticks):
    """The inputs of each tick and the present (t + latency) of the joints."""
    L = round(latency / PERIOD)
    ahead = [joints.at(k + OFFSET - delay / PERIOD) for k in range(ticks)]
    present = [joints.just_before(k + OFFSET + L) for k in range(ticks)]
    inputs = {
        "v_estimated": np.array([x[0] for x in ahead]),
        "vdot_estimated": np.array([x[1] for x in ahead]),
        "tau_estimated": np.array([x[2] for x in ahead]),
        "delta_q": joints.u[OFFSET - 1 + L : OFFSET - 1 + L + ticks],
    }
    return inputs, np.array([x[0] for x in present]), np.array([x[1] for x in present])


def _config(delay, latency, **changes):
    return DelayPredictorConfig(
        joints=JOINTS,
        delay=delay,
        inertia=INERTIA.tolist(),
        command_latency=latency,
        **{"period": PERIOD, **changes},
    )


def test_the_joint_generator_solves_the_ode():
    """The test's plant against an ODE solver (another way to the same velocities)."""
    u = _excitation(60)
    joints = Joints(u, TAU_REST)

    def rhs(t, v):
        j = min(int(t / PERIOD), len(u) - 1)
        return joints.forcing(j) - joints.a * v

    v = np.zeros(3)
    for j in range(len(u)):
        v = solve_ivp(
            rhs,
            ((j + 1e-12) * PERIOD, (j + 1 - 1e-12) * PERIOD),
            v,
            rtol=1e-12,
            atol=1e-14,
        ).y[:, -1]
    np.testing.assert_allclose(v, joints.v[-1], rtol=1e-7, atol=1e-12)


@pytest.mark.parametrize(
    "delay, latency",
    [(0.041, 0.0), (0.041, 0.001), (0.0415, 0.001), (0.0, 0.001), (0.0025, 0.002)],
)
def test_exact_model_predicts_the_present(delay, latency):
    ticks = 400
    joints = Joints(_excitation(ticks + OFFSET + 5), TAU_REST)
    inputs, v_now, tau_now = _scenario(joints, delay, latency, ticks)
    predictor = DelayPredictor(MODEL, _config(delay, latency))
    assert predictor.num_buffered() == math.ceil(round((delay + latency) / PERIOD, 6))
    assert not predictor.HasAnyDirectFeedthrough()
    out, context = _drive(predictor, ticks, inputs)
    M = predictor.num_buffered()
    assert predictor.is_ready(context)
    # Start-up: the delayed estimates pass through until M Δq have been read.
    v, tau = out["v_predicted"], out["tau_predicted"]
    np.testing.assert_array_equal(v[: M - 1], inputs["v_estimated"][: M - 1])
    np.testing.assert_allclose(v[M - 1 :], v_now[M - 1 :], rtol=0, atol=1e-9)
    np.testing.assert_allclose(tau[M - 1 :], tau_now[M - 1 :], rtol=0, atol=1e-9)
    # Not the trivial case: the estimates are far from the present.
    assert np.abs(inputs["v_estimated"] - v_now)[M:].max() > 1e-3
    assert np.abs(inputs["tau_estimated"] - tau_now)[M:].max() > 1e-2


def test_model_error_still_beats_the_delayed_estimates():
    ticks, delay, latency = 1500, 0.0415, 0.001
    steps = ticks + OFFSET + 5
    t = np.arange(steps) * PERIOD
    # The truth: K_τ 20 % below the model's, K_v 10 % above, a slowly varying τ_rest.
    tau_rest = TAU_REST + np.outer(np.sin(2 * np.pi * 0.5 * t), [5.0, 2.0, 1.0])
    joints = Joints(_excitation(steps), tau_rest, k_tau=K_TAU / 1.2, k_v=1.1 * K_V)
    inputs, v_now, tau_now = _scenario(joints, delay, latency, ticks)
    predictor = DelayPredictor(MODEL, _config(delay, latency))
    out, _ = _drive(predictor, ticks, inputs)
    M = predictor.num_buffered()
    for name, estimated, now in (
        ("v", inputs["v_estimated"], v_now),
        ("tau", inputs["tau_estimated"], tau_now),
    ):
        predicted = out[f"{name}_predicted"]
        rms_pred = np.sqrt(np.mean((predicted[M:] - now[M:]) ** 2, axis=0))
        rms_delayed = np.sqrt(np.mean((estimated[M:] - now[M:]) ** 2, axis=0))
        ratio = rms_pred / rms_delayed
        assert np.all(ratio < 0.5), f"{name}: RMS error predicted / delayed = {ratio}"


def test_wrench_extrapolation_is_exact_for_a_ramp():
    ticks, delay, latency = 100, 0.0415, 0.001
    f0 = np.array([1.0, -2.0, 300.0, 0.1, -0.2, 0.3])
    rate = np.array([10.0, 0.0, -50.0, 1.0, 2.0, -3.0])
    t = np.arange(ticks) * PERIOD
    joints = Joints(_excitation(ticks + OFFSET + 5), TAU_REST)
    inputs, _, _ = _scenario(joints, delay, latency, ticks)
    inputs["wrench_estimated"] = f0 + np.outer(t - delay, rate)
    inputs["wrench_rate"] = np.tile(rate, (ticks, 1))
    predictor = DelayPredictor(MODEL, _config(delay, latency, wrench_size=6))
    out, _ = _drive(predictor, ticks, inputs)
    expected = f0 + np.outer(t + latency, rate)
    np.testing.assert_allclose(out["wrench_predicted"], expected, rtol=0, atol=1e-9)
    # Without wrench_size the ports are absent.
    plain = DelayPredictor(MODEL, _config(delay, latency))
    assert not plain.HasInputPort("wrench_estimated")
    assert not plain.HasOutputPort("wrench_predicted")


def test_nan_input_holds_then_recovers():
    ticks, delay, latency = 700, 0.0415, 0.001
    joints = Joints(_excitation(ticks + OFFSET + 5), TAU_REST)
    inputs, v_now, _ = _scenario(joints, delay, latency, ticks)
    inputs["wrench_estimated"] = np.ones((ticks, 6))
    inputs["wrench_rate"] = np.zeros((ticks, 6))
    config = _config(delay, latency, wrench_size=6)
    clean, _ = _drive(DelayPredictor(MODEL, config), ticks, inputs)
    dirty = {name: values.copy() for name, values in inputs.items()}
    dirty["tau_estimated"][300:310] = np.nan
    dirty["v_estimated"][305, 1] = np.inf
    dirty["delta_q"][400, 2] = np.nan
    dirty["wrench_rate"][500, 0] = np.nan
    predictor = DelayPredictor(MODEL, config)
    out, context = _drive(predictor, ticks, dirty)  # must not raise
    for values in out.values():
        assert np.all(np.isfinite(values))
    # Bad estimates hold the prediction; the next good tick is the clean one again.
    for name in ("v_predicted", "tau_predicted"):
        held = np.tile(out[name][299], (10, 1))
        np.testing.assert_array_equal(out[name][300:310], held)
        np.testing.assert_allclose(out[name][310:400], clean[name][310:400], atol=1e-12)
    np.testing.assert_array_equal(out["input_fault"][299:311, 0], [0, *range(1, 11), 0])
    # A bad Δq holds that joint's previous Δq: approximate for M ticks, then exact.
    M = predictor.num_buffered()
    assert np.abs(out["v_predicted"][400 : 400 + M] - v_now[400 : 400 + M]).max() < 0.05
    np.testing.assert_allclose(
        out["v_predicted"][400 + M :], clean["v_predicted"][400 + M :], atol=1e-12
    )
    # A bad wrench holds the wrench only.
    wrench = out["wrench_predicted"]
    np.testing.assert_array_equal(wrench[500], wrench[499])
    np.testing.assert_array_equal(out["v_predicted"][500], clean["v_predicted"][500])
    assert predictor.bad_input_count(context) == 12


def test_in_a_loop_with_a_feedthrough_controller():
    """Its outputs are state: a controller whose Δq depends directly on v_predicted
    closes the loop without an algebraic loop, under the Simulator."""
    builder = DiagramBuilder()
    config = _config(0.0415, 0.001)
    predictor = builder.AddSystem(DelayPredictor(MODEL, config))
    for name, value in (
        ("v_estimated", [0.1, -0.2, 0.0]),
        ("vdot_estimated", [0.0, 0.0, 0.0]),
        ("tau_estimated", TAU_REST),
    ):
        source = builder.AddSystem(ConstantVectorSource(np.asarray(value, float)))
        builder.Connect(source.get_output_port(), predictor.GetInputPort(name))
    gain = builder.AddSystem(MatrixGain(np.diag(K_V)))  # Δq = K_v q̇_pred
    builder.Connect(predictor.GetOutputPort("v_predicted"), gain.get_input_port())
    builder.Connect(gain.get_output_port(), predictor.GetInputPort("delta_q"))
    assert not predictor.HasAnyDirectFeedthrough()
    simulator = Simulator(builder.Build())
    # Ticks at 0, 1, ..., 199 ms, each committed at the next sampling instant (the
    # last at 200 ms: an update at the final time waits for the next step).
    simulator.AdvanceTo(0.2005)
    context = predictor.GetMyContextFromRoot(simulator.get_context())
    assert predictor.is_ready(context)
    # The same loop by hand: the Δq read at tick k is K_v times the v_predicted of
    # tick k − 1 (zero at tick 0), one period late, as the docstring says.
    manual = DelayPredictor(MODEL, config)
    manual_context = manual.CreateDefaultContext()
    manual.GetInputPort("v_estimated").FixValue(manual_context, [0.1, -0.2, 0.0])
    manual.GetInputPort("vdot_estimated").FixValue(manual_context, np.zeros(3))
    manual.GetInputPort("tau_estimated").FixValue(manual_context, TAU_REST)
    for k in range(200):
        v = manual.GetOutputPort("v_predicted").Eval(manual_context)
        manual.GetInputPort("delta_q").FixValue(manual_context, K_V * v)
        commit(manual, manual_context, (k + 1) * PERIOD)
    for name in ("v_predicted", "tau_predicted"):
        value = predictor.GetOutputPort(name).Eval(context)
        assert np.all(np.isfinite(value))
        expected = manual.GetOutputPort(name).Eval(manual_context)
        np.testing.assert_array_equal(value, expected)


def test_config_loads_from_yaml():
    # The period is the code's (the control period), never the file's.
    defaults = DelayPredictorConfig(period=PERIOD)
    config = yaml_load_typed(
        schema=DelayPredictorConfig,
        data="joints: [hip, knee, ankle]\ninertia: [1.5, 0.8, 0.3]\nwrench_size: 12\n",
        defaults=defaults,
    )
    config.validate()
    # The default delay: the torque chain's loop_delay at N = 80, 1 kHz (the
    # estimation delay, 39.5 ms, plus the one tick of the loop).
    assert config.delay == 0.0405 and config.command_latency == 0.001
    with pytest.raises(RuntimeError, match="horizon"):
        yaml_load_typed(
            schema=DelayPredictorConfig,
            data="joints: [hip]\nhorizon: 1\n",
            defaults=defaults,
        )


@pytest.mark.parametrize(
    "changes, message",
    [
        (dict(joints=[]), "joints is empty"),
        (dict(joints=["hip", "hip", "knee"]), "duplicated joints"),
        (dict(delay=-0.001), "delay"),
        (dict(delay=math.nan), "delay"),
        (dict(inertia=[1.0, 2.0]), "inertia"),
        (dict(inertia=[1.0, 0.0, 2.0]), "inertia"),
        (dict(command_latency=-1.0), "command_latency"),
        (dict(wrench_size=-6), "wrench_size"),
        (dict(wrench_size=1.5), "wrench_size"),
        (dict(max_velocity_correction=[1.0, 2.0]), "max_velocity_correction"),
        (dict(max_torque_correction=[0.0]), "max_torque_correction"),
        (dict(period=0.0), "period"),
    ],
)
def test_bad_config(changes, message):
    fields = dict(joints=JOINTS, inertia=INERTIA.tolist(), period=PERIOD)
    config = DelayPredictorConfig(**{**fields, **changes})
    with pytest.raises(ValueError, match=message) as error:
        DelayPredictor(MODEL, config)
    assert "\n" not in str(error.value)


def test_bad_model():
    with pytest.raises(KeyError, match="DelayPredictor.*toe"):
        DelayPredictor(
            MODEL,
            DelayPredictorConfig(["hip", "toe"], inertia=[1.0, 1.0], period=PERIOD),
        )
    bad = MotorModel(JOINTS, [2e-4, 0.0, 1e-4], K_V)
    with pytest.raises(ValueError, match=r"k_tau must be > 0 for joints \['knee'\]"):
        DelayPredictor(bad, _config(0.0415, 0.001))


def test_the_step_on_plain_arrays_is_the_system():
    """The step driven by plain arrays (no Context) gives the LeafSystem's outputs
    bit for bit, bad input included, and predicts the present of the exact joints."""
    ticks, delay, latency = 300, 0.0415, 0.001
    joints = Joints(_excitation(ticks + OFFSET + 5), TAU_REST)
    inputs, v_now, tau_now = _scenario(joints, delay, latency, ticks)
    inputs["wrench_estimated"] = np.ones((ticks, 6))
    inputs["wrench_rate"] = np.tile(np.arange(6.0), (ticks, 1))
    inputs["tau_estimated"][100:103] = np.nan
    inputs["delta_q"][150, 1] = np.inf
    config = _config(delay, latency, wrench_size=6)
    expected, context = _drive(DelayPredictor(MODEL, config), ticks, inputs)
    step = DelayPredictorStep(MODEL, config)
    assert step.num_buffered() == 43 and step.horizon() == pytest.approx(0.0425)
    names = list(expected)
    out = {name: [] for name in names}
    for k in range(ticks):
        step.step(
            k * PERIOD,
            inputs["v_estimated"][k],
            inputs["vdot_estimated"][k],
            inputs["tau_estimated"][k],
            inputs["delta_q"][k],
            inputs["wrench_estimated"][k],
            inputs["wrench_rate"][k],
        )
        for name in names:
            out[name].append(getattr(step, name).copy())
    for name in names:
        np.testing.assert_array_equal(out[name], expected[name], err_msg=name)
    assert step.is_ready() and step.bad_input_count() == 4
    # Numbers: 3 bad ticks in a row, then good; the present before the bad Δq.
    fault = np.array(out["input_fault"])[:, 0]
    np.testing.assert_array_equal(fault[99:104], [0, 1, 2, 3, 0])
    v = np.array(out["v_predicted"])
    np.testing.assert_allclose(v[50:100], v_now[50:100], rtol=0, atol=1e-9)
    np.testing.assert_allclose(step.wrench_predicted, 1.0 + 0.0425 * np.arange(6.0))


# --------------------------------------------------------------------- the kernels


def _kernel_run(config: DelayPredictorConfig, ticks: int = 200) -> np.ndarray:
    """The predictor's state after each tick on the exact joints, bad input on the
    way (NaN τ̂, an infinite Δq entry, a NaN wrench rate)."""
    joints = Joints(_excitation(ticks + OFFSET + 5), TAU_REST)
    inputs, _, _ = _scenario(joints, config.delay, config.command_latency, ticks)
    inputs["tau_estimated"][100:103] = np.nan
    inputs["delta_q"][150, 1] = np.inf
    wrench = np.tile(np.arange(6.0), (ticks, 1))
    rate = np.ones((ticks, 6))
    rate[170, 2] = np.nan
    step = DelayPredictorStep(MODEL, config)
    states = []
    for k in range(ticks):
        extra = (wrench[k], rate[k]) if config.wrench_size else ()
        step.step(
            k * PERIOD,
            *(inputs[name][k] for name in ("v_estimated", "vdot_estimated")),
            inputs["tau_estimated"][k],
            inputs["delta_q"][k],
            *extra,
        )
        states.append(step.state.copy())
    return np.array(states)


@pytest.mark.skipif(not kernels.jit_enabled(), reason="NUMBA_DISABLE_JIT: no kernels")
@pytest.mark.parametrize(
    "changes",
    [
        dict(
            wrench_size=6, max_velocity_correction=[0.05], max_torque_correction=[5.0]
        ),
        dict(delay=0.0, latency=0.0),  # M = 0: the estimates pass through
    ],
)
def test_kernel_compiled_equals_interpreted(changes):
    """The kernel compiled and as its Python source (`kernels.interpreted`) on the
    same ticks: the same states bit for bit (the weighted sum over the window in
    the same order)."""
    config = _config(**{"delay": 0.0415, "latency": 0.001, **changes})
    compiled = _kernel_run(config)
    with kernels.interpreted():
        assert not hasattr(predictor._predictor_step, "py_func")  # Python
        interpreted = _kernel_run(config)
    np.testing.assert_array_equal(compiled, interpreted)
    assert np.all(np.isfinite(compiled))


def test_warm_up_then_frozen():
    """warm_up compiles the kernel for a tick's arrays without touching the state;
    frozen, a real tick on a step bound into a larger state (as in the fused
    controller) runs, and arrays of another type raise instead of compiling."""
    config = _config(0.0415, 0.001, wrench_size=6)
    step = DelayPredictorStep(MODEL, config)
    buffer = np.zeros(step.state_size + 4)
    step.bind(buffer[1 : 1 + step.state_size])
    v, wrench, hold = np.array([0.1, -0.2, 0.3]), np.ones(6), K_TAU * TAU_REST
    for k in range(50):
        step.step(k * PERIOD, v, np.zeros(3), TAU_REST, hold, wrench, wrench)
    before = buffer.copy()
    step.warm_up()
    np.testing.assert_array_equal(buffer, before)
    if kernels.jit_enabled():  # every kernel of the module compiled
        mine = [
            k for k in kernels.kernels() if k.py_func.__module__ == predictor.__name__
        ]
        assert mine and all(k.signatures for k in mine)
    try:
        kernels.freeze()
        step.step(0.05, v, np.zeros(3), TAU_REST, hold, wrench, 2 * wrench)
        assert step.is_ready() and step.bad_input_count() == 0
        np.testing.assert_allclose(step.wrench_predicted, 1.0 + 2 * step.horizon())
        if kernels.jit_enabled():
            with pytest.raises(TypeError):
                step.step(0.051, v.astype(np.float32), v, v, v, wrench, wrench)
    finally:
        kernels.thaw()
    state = step.state.copy()
    with pytest.raises(ValueError, match="wrench_estimated and wrench_rate 6"):
        step.step(0.051, v, v, v, v)  # no wrench with wrench_size 6
    np.testing.assert_array_equal(step.state, state)
