#!/usr/bin/env python3
"""Benchmarks of hrp2_drake, in one run so that ratios between rows are meaningful.

Sections (all by default; pick with --only):
  sim        real-time factor of the simulated HRP-2 per scenario (goal: >= 3x for
             fixed_base, >= 1x for standing, one core), and of the bare plant without
             servo and sensors (baseline: what our Python systems cost on top).
  sg         per-tick cost of the Savitzky-Golay filters
             (scripts/bench_savitzky_golay.py).
  estimator  per-tick cost of the floating-base torque estimator
             (scripts/bench_estimator.py).
  control    per-tick cost of the controller stack and real-time factor of the motion
             experiment's diagrams (scripts/bench_control.py).
  fit        fit_asymmetric from 10^3 to 10^6 samples, Newton and QP
             (scripts/bench_fitting.py).
  tick       one 1 kHz tick of estimation plus control for HRP-2, part by part
             (bench_tick): the two Savitzky-Golay filters, the floating-base estimator,
             the inverse dynamics and the Δq controller of the right leg, their sum,
             the safety supervisor apart, and a no-op Python LeafSystem tick with the
             estimator's ports; PASS/FAIL against the budget (<= 100 us and <= 10
             no-op ticks).
  closed_loop  real-time factor of the motion experiment's closed loop, the unit of
             cost of a tuner (goal: >= 3x for torque control): torque control K6 = 0.1
             and position control, every port logged and only a tuner's, the bare
             plant, and where the time goes per system (scripts/bench_closed_loop.py;
             --closed-loop-duration, default the whole motion; --closed-loop-profile,
             simulated s of the per-system run, default 4).
  fused      the fused controller's tick on HRP-2 in closed loop (30 joints, IMU, 4 F/T,
             right leg, observer, supervisor), p50/p99, and its ratio to Drake's
             CalcInverseDynamics on the full HRP-2 in the same run (goal <= 6;
             scripts/bench_fused.py).
  balance    the fused controller with the balance front end (issue 29) on the
             standing HRP-2 in closed loop (both legs, BalanceControlConfig's
             defaults, supervisor, the CoM on the authors' sinusoid): the QP's solve
             (update + solve), the base from the soles and the whole tick (tick +
             command), p50/p99 in µs and as ratios to Drake's CalcInverseDynamics on
             the full HRP-2 in the same run, for daqp (the default) and pydrake's
             OSQP, and what they mean at 1 kHz (1 ms a tick)
             (scripts/bench_balance.py --closed-loop; --balance-duration, default
             2 s simulated, torque control from 0.5 s).
  lcm        the controller over LCM in real time (fused controller, message-driven
             loop) against `hrp2-drake sim-robot` in another process, through the tcpq
             hub on 127.0.0.1 (scripts/bench_lcm.py; --lcm-duration, default 60 s):
             receive-to-publish latency p50/p99/p99.9/max (goal p99 <= 250 us),
             overruns of the 1 ms period, torque-control share, fallbacks; in real
             time and with the robot in lock step (the controller without a late robot).
  bus        the bus loop through the emulated servos (`sim-servo`), back to back:
             cycle p50/p99 and the achieved rate for 1, 6 and 12 XL330s at 1, 2 and
             4 Mbit/s (Dynamixel) and 1, 6 and 12 STS3215s at 0.5 and 1 Mbit/s
             (Feetech), beside the wire-time budget and what a USB adapter's 1 ms
             latency timer leaves (scripts/bench_bus.py; --bus-cycles, default 2000).

Figures vary from run to run (2 cores, shared): compare rows of the same run.

    python scripts/bench.py [--only sim,sg] [--duration 3] [--json out/bench.json]
    python scripts/bench.py --only tick [--rounds 41]
    python scripts/bench.py --only fused
    python scripts/bench.py --only balance [--balance-duration 2]
    python scripts/bench.py --only lcm [--lcm-duration 60]
    python scripts/bench.py --only closed_loop [--closed-loop-duration 5]
    python scripts/bench.py --only bus [--bus-cycles 2000]
"""

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, LeafSystem
from pydrake.systems.primitives import ConstantVectorSource

sys.path.insert(0, str(Path(__file__).resolve().parent))

from hrp2_drake.paper import hrp2  # noqa: E402
from hrp2_drake.robot.station import (  # noqa: E402
    StationConfig,
    initial_joint_positions,
    make_station,
)


def _real_time_factor(diagram, duration: float) -> float:
    simulator = Simulator(diagram)
    simulator.Initialize()
    start = time.perf_counter()
    simulator.AdvanceTo(duration)
    return duration / (time.perf_counter() - start)


def bench_simulation(duration: float) -> list[dict]:
    rows = []
    for scenario in ("fixed_base", "hanging", "standing", "standing_on_block"):
        config = StationConfig(scenario=scenario)
        builder = DiagramBuilder()
        station = builder.AddSystem(make_station(config))
        source = builder.AddSystem(
            ConstantVectorSource(initial_joint_positions(config))
        )
        builder.Connect(source.get_output_port(), station.GetInputPort("q_cmd"))
        rtf = _real_time_factor(builder.Build(), duration)
        rows.append({"name": f"simulate {scenario}", "real_time_factor": rtf})
        print(f"  simulate {scenario:18s} {rtf:6.2f}x real time", file=sys.stderr)
    # Baseline: the same plant (fixed base), constant actuation, no servo, no sensors.
    from pydrake.multibody.plant import AddMultibodyPlant, MultibodyPlantConfig

    builder = DiagramBuilder()
    plant, _ = AddMultibodyPlant(
        MultibodyPlantConfig(time_step=1e-3, discrete_contact_approximation="sap"),
        builder,
    )
    hrp2.add_hrp2(plant)
    plant.WeldFrames(plant.world_frame(), plant.GetFrameByName(hrp2.BASE_BODY))
    plant.Finalize()
    torque = builder.AddSystem(ConstantVectorSource(np.zeros(plant.num_actuators())))
    builder.Connect(torque.get_output_port(), plant.get_actuation_input_port())
    rtf = _real_time_factor(builder.Build(), duration)
    rows.append({"name": "baseline: bare fixed-base plant", "real_time_factor": rtf})
    print(f"  bare fixed-base plant     {rtf:6.2f}x real time", file=sys.stderr)
    return rows


# ------------------------------------------------------------------ one tick

TICK_BUDGET_US = 100.0  # issue "Run it on a robot": estimation plus control per tick
TICK_BUDGET_NOOPS = 10.0  # ... and at most this many no-op Python system ticks
PERIOD = 1e-3  # s


class _NoopTick(LeafSystem):
    """The FloatingBaseTorqueEstimator's ports (inputs, discrete state, state outputs,
    periodic update) with an update that does nothing: what the framework alone costs
    per tick of a Python LeafSystem (the baseline of the tick budget)."""

    def __init__(self, n: int, sensors: list[str]):
        super().__init__()
        for name in ("q", "v", "vdot"):
            self.DeclareVectorInputPort(name, n)
        for name in (
            "imu_linear_acceleration",
            "imu_angular_velocity",
            "imu_angular_acceleration",
        ):
            self.DeclareVectorInputPort(name, 3)
        for name in sensors:
            self.DeclareVectorInputPort(f"wrench_{name}", 6)
        self.DeclareStateOutputPort("tau", self.DeclareDiscreteState(n))
        self.DeclareStateOutputPort("unknown_wrench", self.DeclareDiscreteState(6))
        for name in sensors:
            self.DeclareStateOutputPort(
                f"external_wrench_{name}", self.DeclareDiscreteState(6)
            )
        self.DeclareDiscreteState(6 * len(sensors) + 1)
        self.DeclarePeriodicDiscreteUpdateEvent(PERIOD, 0.0, self._update)

    def _update(self, context, discrete_state):
        pass


class _Ticker:
    """One system on one context, ticked the way the Simulator does it at a periodic
    update: EvalUniquePeriodicDiscreteUpdate, then SetDiscreteState (plus the Eval of
    `output`, for a system whose output is computed from live inputs). `prepare(tick)`
    runs before each tick, outside the timing (fresh sensor samples)."""

    def __init__(self, system, context, output=None, prepare=None):
        self.system = system
        self.context = context
        self.output = output
        self.prepare = prepare
        self.tick = 0

    def us_per_tick(self, num_ticks: int) -> float:
        system, context, output = self.system, self.context, self.output
        elapsed = 0.0
        for _ in range(num_ticks):
            context.SetTime(self.tick * PERIOD)
            if self.prepare is not None:
                self.prepare(self.tick)
            self.tick += 1
            start = time.perf_counter()
            context.SetDiscreteState(system.EvalUniquePeriodicDiscreteUpdate(context))
            if output is not None:
                output.Eval(context)
            elapsed += time.perf_counter() - start
        return elapsed / num_ticks * 1e6


def _tick_systems() -> dict[str, _Ticker]:
    """HRP-2's estimation and control systems as build_torque_control configures them
    (estimator_config: window 80, unknown wrench on the torso; inverse dynamics and Δq
    controller of the right leg on the upright fixed-base model, every port of the
    diagram connected), each on its own context with healthy, plausible inputs
    (half-sitting, small velocities, standing wrenches), initialized."""
    from bench_estimator import _fix, _inputs

    from hrp2_drake.paper import hrp2

    config = hrp2.estimator_config()
    sensors = list(config.sensors)
    inputs = _inputs(len(sensors))
    systems = _estimation_tickers(config, inputs)
    systems |= _control_tickers()
    systems["safety supervisor (update + q_cmd)"] = _supervisor_ticker(sensors)
    noop = _NoopTick(hrp2.NUM_JOINTS, sensors)
    context = noop.CreateDefaultContext()
    _fix(noop, context, inputs, sensors)
    systems["no-op LeafSystem (the estimator's ports)"] = _Ticker(noop, context)
    return systems


def _estimation_tickers(config, inputs: dict) -> dict[str, _Ticker]:
    """The SG filters of the encoders and of the sensors, and the estimator, with
    `config` (HRP-2's `estimator_config`) on `inputs` (bench_estimator's)."""
    from bench_estimator import _fix

    from hrp2_drake.estimation.savitzky_golay import SavitzkyGolayFilter
    from hrp2_drake.estimation.torque_estimator import FloatingBaseTorqueEstimator
    from hrp2_drake.paper import hrp2

    def filter_ticker(system, signal):
        context = system.CreateDefaultContext()
        system.get_input_port().FixValue(context, signal)
        system.ExecuteInitializationEvents(context)
        return _Ticker(system, context)

    systems = {}
    systems["SG encoder filter (30, order 2)"] = filter_ticker(
        SavitzkyGolayFilter(
            hrp2.NUM_JOINTS, config.window, 2, config.period, config.evaluation
        ),
        inputs["q"],
    )
    sensor_signal = np.concatenate(
        [
            inputs["imu_linear_acceleration"],
            inputs["imu_angular_velocity"],
            *inputs["wrenches"],
        ]
    )
    systems["SG sensor filter (30, order 1)"] = filter_ticker(
        SavitzkyGolayFilter(
            sensor_signal.size, config.window, 1, config.period, config.evaluation
        ),
        sensor_signal,
    )
    estimator = FloatingBaseTorqueEstimator(hrp2.estimator_plant(), config)
    context = estimator.CreateDefaultContext()
    _fix(estimator, context, inputs, list(config.sensors))
    systems["estimator (30 joints, IMU, 4 F/T)"] = _Ticker(estimator, context)
    return systems


def _control_tickers() -> dict[str, _Ticker]:
    """Inverse dynamics and the Δq torque controller of the right leg."""
    from hrp2_drake.control.inverse_dynamics import (
        TORQUE_COMPONENTS,
        InverseDynamicsConfig,
        InverseDynamicsController,
        make_fixed_base_plant,
    )
    from hrp2_drake.control.torque_controller import (
        DeltaQTorqueController,
        TorqueControllerConfig,
    )
    from hrp2_drake.description import load_robot_description
    from hrp2_drake.paper import hrp2

    joints = list(hrp2.RIGHT_LEG)
    n = len(joints)
    leg = [list(hrp2.JOINT_NAMES).index(j) for j in joints]
    q = hrp2.half_sitting()[leg]
    period = load_robot_description().sensors.period
    inverse_dynamics = InverseDynamicsController(
        make_fixed_base_plant(hrp2.add_hrp2, hrp2.BASE_BODY),
        InverseDynamicsConfig(joints=joints, ks=[3000.0], kd=[50.0], period=period),
    )
    context = inverse_dynamics.CreateDefaultContext()
    id_inputs = {
        "q_ref": q,
        "v_ref": np.full(n, 0.3),
        "vdot_ref": np.ones(n),
        "q": q + 1e-3,
        "v": np.full(n, 0.25),
    }
    for name, value in id_inputs.items():
        inverse_dynamics.GetInputPort(name).FixValue(context, value)
    systems = {"inverse dynamics (right leg)": _Ticker(inverse_dynamics, context)}

    torque = DeltaQTorqueController(
        hrp2.true_motor_model(joints),
        TorqueControllerConfig(joints=joints, period=period),
    )
    context = torque.CreateDefaultContext()
    terms = inverse_dynamics.compute(*id_inputs.values())
    fixed = {
        "tau_desired": terms.tau_desired,
        "tau_estimated": terms.tau_desired - 1.0,
        "v": np.full(n, 0.2),
        "q_measured": q,
        "q_ref": q,
        "sensor_fault": np.zeros(1),
    }
    fixed |= dict(zip(TORQUE_COMPONENTS, terms[1:]))
    for name, value in fixed.items():
        torque.GetInputPort(name).FixValue(context, value)
    torque.ExecuteInitializationEvents(context)
    systems["Δq torque controller (right leg)"] = _Ticker(torque, context)
    return systems


def _supervisor_ticker(sensors: list[str]) -> _Ticker:
    """The safety supervisor (30 joints, IMU + 4 F/T, stamps) as bench_control
    measures it: update + q_cmd, fresh noisy samples and stamps every tick (a noisy
    sensor that repeats its sample is stale)."""
    from hrp2_drake.control.safety import (
        SafetyConfig,
        SafetySupervisor,
        supervisor_sensors,
        with_sensor_ranges,
    )
    from hrp2_drake.description import load_robot_description
    from hrp2_drake.paper import hrp2

    monitored = supervisor_sensors(sensors)
    robot = load_robot_description()
    config = with_sensor_ranges(
        SafetyConfig(start_time=0.0), monitored, robot.sensor_ranges
    )
    supervisor = SafetySupervisor(
        hrp2.NUM_JOINTS, monitored, config, robot.sensors.period, num_sensor_stamps=7
    )
    context = supervisor.CreateDefaultContext()
    q30 = hrp2.half_sitting()
    for name, value in (
        ("q_torque", q30 + 1e-3),
        ("q_position", q30),
        ("q_measured", q30),
    ):
        supervisor.GetInputPort(name).FixValue(context, value)
    rng = np.random.default_rng(0)
    sizes = {name: 6 if kind == "wrench" else 3 for name, kind in monitored.items()}
    ports = {name: supervisor.GetInputPort(name) for name in (*sizes, "sensor_time")}

    def fresh_samples(tick, context=context):
        ports["sensor_time"].FixValue(context, np.full(7, (tick - 1) * PERIOD))
        for name, size in sizes.items():
            ports[name].FixValue(context, rng.normal(0, 1, size))

    fresh_samples(0)
    supervisor.ExecuteInitializationEvents(context)
    return _Ticker(
        supervisor, context, supervisor.GetOutputPort("q_cmd"), fresh_samples
    )


ESTIMATION_AND_CONTROL = (
    "SG encoder filter (30, order 2)",
    "SG sensor filter (30, order 1)",
    "estimator (30 joints, IMU, 4 F/T)",
    "inverse dynamics (right leg)",
    "Δq torque controller (right leg)",
)


def bench_tick(rounds: int = 41, ticks_per_round: int = 250) -> list[dict]:
    """Per-tick cost (us) of each part of HRP-2's 1 kHz estimation and control, and of
    a no-op Python LeafSystem tick, in one run: `rounds` rounds, each ticking every
    system `ticks_per_round` times in turn, in a shuffled order (so that a busy spell
    of the shared machine hits every row alike); each row is the median over the
    rounds of the round's mean.
    The sum "estimation plus control" is that of the five parts of
    ESTIMATION_AND_CONTROL (the supervisor is reported apart); the verdict is PASS
    when it is <= TICK_BUDGET_US and <= TICK_BUDGET_NOOPS no-op ticks."""
    systems = _tick_systems()
    for ticker in systems.values():  # warm up; fill the filters' windows
        ticker.us_per_tick(100)
    samples = {name: [] for name in systems}
    order = list(systems)
    shuffle = np.random.default_rng(0).shuffle
    for _ in range(rounds):
        shuffle(order)
        for name in order:
            samples[name].append(systems[name].us_per_tick(ticks_per_round))
    # Still healthy after every tick (the inputs are those of a robot at work).
    supervisor = systems["safety supervisor (update + q_cmd)"]
    assert supervisor.system.GetOutputPort("fault").Eval(supervisor.context)[0] == 0
    torque = systems["Δq torque controller (right leg)"]
    assert torque.system.GetOutputPort("fallback_active").Eval(torque.context)[0] == 0
    median = {name: float(np.median(values)) for name, values in samples.items()}
    noop = median["no-op LeafSystem (the estimator's ports)"]
    total = sum(median[name] for name in ESTIMATION_AND_CONTROL)
    ratio = total / noop
    verdict = (
        "PASS" if total <= TICK_BUDGET_US and ratio <= TICK_BUDGET_NOOPS else "FAIL"
    )
    rows = [
        {"name": name, "us_per_tick": us, "noop_ticks": us / noop}
        for name, us in median.items()
    ]
    rows.append(
        {
            "name": "estimation plus control (sum of the five parts)",
            "us_per_tick": total,
            "noop_ticks": ratio,
        }
    )
    rows.append(
        {
            "name": (
                f"verdict: {verdict} (budget <= {TICK_BUDGET_US:g} us and <= "
                f"{TICK_BUDGET_NOOPS:g} no-op ticks; median of {rounds} rounds of "
                f"{ticks_per_round} ticks)"
            )
        }
    )
    for row in rows:
        if "us_per_tick" in row:
            print(
                f"  {row['name']:<52s} {row['us_per_tick']:7.1f} us  "
                f"{row['noop_ticks']:5.2f} no-op ticks",
                file=sys.stderr,
            )
        else:
            print(f"  {row['name']}", file=sys.stderr)
    return rows


def _sim(args) -> list[dict]:
    print("simulation", file=sys.stderr)
    return bench_simulation(args.duration)


def _sg(args) -> list[dict]:
    from bench_savitzky_golay import bench_savitzky_golay

    print("savitzky-golay", file=sys.stderr)
    return bench_savitzky_golay()


def _estimator(args) -> list[dict]:
    from bench_estimator import bench_estimator

    print("estimator", file=sys.stderr)
    return bench_estimator()


def _control(args) -> list[dict]:
    from bench_control import bench_controller_stack, bench_motion_experiment

    print("control", file=sys.stderr)
    return bench_controller_stack() + bench_motion_experiment()


def _fit(args) -> list[dict]:
    from bench_fitting import bench_fitting

    print("fitting", file=sys.stderr)
    return bench_fitting()


def _tick(args) -> list[dict]:
    print("tick", file=sys.stderr)
    return bench_tick(args.rounds)


def _fused(args) -> list[dict]:
    from bench_fused import bench_fused_tick

    print("fused", file=sys.stderr)
    return bench_fused_tick()


def _balance(args) -> list[dict]:
    from bench_balance import closed_loop_rows

    print("balance", file=sys.stderr)
    return closed_loop_rows(args.balance_duration)


def _closed_loop(args) -> list[dict]:
    from bench_closed_loop import bench_closed_loop

    print("closed loop", file=sys.stderr)
    return bench_closed_loop(args.closed_loop_duration, args.closed_loop_profile)


def _lcm(args) -> list[dict]:
    from bench_lcm import bench_lcm

    print("lcm", file=sys.stderr)
    return [
        bench_lcm(
            robot,
            args.lcm_duration,
            Path("out/bench_lcm") / (robot + ("_lockstep" if lockstep else "")),
            lockstep=lockstep,
        )
        for robot in ("hrp2", "iiwa14")
        for lockstep in (False, True)
    ]


def _bus(args) -> list[dict]:
    import tempfile

    from bench_bus import KIND_BAUDS, bench_bus, bus_grid

    print("bus", file=sys.stderr)
    servo = {"dynamixel": "XL330", "feetech": "STS3215"}
    with tempfile.TemporaryDirectory() as folder:
        return [
            {"name": f"{n} x {servo[kind]} at {baud / 1e6:g} Mbit/s"}
            | bench_bus(n, baud, args.bus_cycles, Path(folder), kind)
            for kind in KIND_BAUDS
            for n, baud in bus_grid(kind)
        ]


#: The sections (`--only`), in the order they run: each prints its name and returns
#: its rows.
SECTIONS = {
    "sim": _sim,
    "sg": _sg,
    "estimator": _estimator,
    "control": _control,
    "fit": _fit,
    "tick": _tick,
    "fused": _fused,
    "balance": _balance,
    "closed_loop": _closed_loop,
    "lcm": _lcm,
    "bus": _bus,
}


def _arguments() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", default=",".join(SECTIONS))
    parser.add_argument("--duration", type=float, default=3.0, help="simulated s")
    parser.add_argument("--json", type=Path, help="also write the rows here")
    parser.add_argument("--rounds", type=int, default=41, help="tick: rounds (median)")
    parser.add_argument("--lcm-duration", type=float, default=60.0, help="lcm: seconds")
    parser.add_argument(
        "--balance-duration", type=float, default=2.0, help="balance: simulated s"
    )
    parser.add_argument(
        "--bus-cycles", type=int, default=2000, help="bus: cycles per bus"
    )
    parser.add_argument(
        "--closed-loop-duration",
        type=float,
        help="closed_loop: simulated s per run (default: the whole motion)",
    )
    parser.add_argument(
        "--closed-loop-profile",
        type=float,
        default=4.0,
        help="closed_loop: simulated s of the per-system breakdown",
    )
    return parser.parse_args()


def _print_tables(results: dict[str, list[dict]]) -> None:
    """Each section's rows as a markdown table, on stdout."""
    for section, rows in results.items():
        print(f"\n## {section}")
        keys = sorted({k for row in rows for k in row if k != "name"})
        print("| name | " + " | ".join(keys) + " |")
        print("| --- |" + " --- |" * len(keys))
        for row in rows:
            cells = [
                (
                    f"{row[k]:.4g}"
                    if isinstance(row.get(k), float)
                    else str(row.get(k, ""))
                )
                for k in keys
            ]
            print(f"| {row['name']} | " + " | ".join(cells) + " |")


def main() -> int:
    args = _arguments()
    sections = set(args.only.split(","))
    results = {name: run(args) for name, run in SECTIONS.items() if name in sections}
    _print_tables(results)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
