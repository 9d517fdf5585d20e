"""Per-tick cost of FloatingBaseTorqueEstimator's periodic update for the 30-joint HRP-2
(microseconds), plus a baseline in the same run.

Rows:
- "estimator update ...": the discrete update alone (EvalUniquePeriodicDiscreteUpdate,
  then SetDiscreteState, as the simulator does it), inputs fixed on the context at
  plausible values (half-sitting, small velocities and accelerations, standing
  wrenches); variants: unknown wrench on the base (default) or on the torso, rotor
  inertia off, during the F/T offset calibration.
- "estimate() ...": the context-free `estimate` method (offline use).
- "baseline noop update": a Python LeafSystem with the same inputs whose periodic update
  only reads them: the framework's own per-tick cost (use it for ratios).
- "net allocated blocks per tick": Python heap blocks still allocated after the ticks,
  per tick (0: nothing accumulates).
- "estimation stage ...": what add_estimator adds for HRP-2 as the experiments configure
  it (hrp2.estimator_config: window 80, unknown wrench on the torso): the encoder
  filter (k = 30, order 2), the sensor filter (k = 30, order 1) and the estimator, each
  update alone, their sum (goal: < 100 us), and the whole chain simulated on constant
  sensor signals (multiplexer and demultiplexers included).

Run: .venv/bin/python scripts/bench_estimator.py
"""

import dataclasses
import sys
import time

import numpy as np
from pydrake.multibody.plant import MultibodyPlant
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, LeafSystem
from pydrake.systems.primitives import ConstantVectorSource

from hrp2_drake.estimation.estimation_chain import add_estimator
from hrp2_drake.estimation.estimator_config import (
    ForceTorqueSensorConfig,
    TorqueEstimatorConfig,
)
from hrp2_drake.estimation.savitzky_golay import SavitzkyGolayFilter
from hrp2_drake.estimation.torque_estimator import FloatingBaseTorqueEstimator
from hrp2_drake.paper import hrp2

PERIOD = 1e-3  # s


def hrp2_estimator_config(plant: MultibodyPlant) -> TorqueEstimatorConfig:
    """The HRP-2 estimator config from the robot model's names."""
    sensors = {
        name: ForceTorqueSensorConfig(
            frame=plant.GetJointByName(joint).frame_on_child().name(),
            body=hrp2.FT_SENSOR_BODIES[name],
        )
        for name, joint in hrp2.FT_SENSORS.items()
    }
    return TorqueEstimatorConfig(
        joints=list(hrp2.JOINT_NAMES), imu_frame=hrp2.IMU_FRAME, sensors=sensors
    )


def _inputs(num_sensors: int) -> dict:
    rng = np.random.default_rng(0)
    n = hrp2.NUM_JOINTS
    standing = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 280.0])
    return {
        "q": hrp2.half_sitting(),
        "v": rng.normal(0.0, 0.1, n),
        "vdot": rng.normal(0.0, 1.0, n),
        "imu_linear_acceleration": np.array([0.1, -0.2, 9.81]),
        "imu_angular_velocity": np.array([0.01, -0.02, 0.005]),
        "imu_angular_acceleration": np.array([0.1, 0.05, -0.02]),
        "wrenches": [standing] * 2 + [np.zeros(6)] * (num_sensors - 2),
    }


def _fix(system: LeafSystem, context, inputs: dict, sensors: list[str]) -> None:
    for name, value in inputs.items():
        if name != "wrenches":
            system.GetInputPort(name).FixValue(context, value)
    for name, value in zip(sensors, inputs["wrenches"]):
        system.GetInputPort(f"wrench_{name}").FixValue(context, value)


def _us_per_update(system: LeafSystem, context, num_ticks: int) -> float:
    start = time.perf_counter()
    for tick in range(num_ticks):
        context.SetTime(tick * PERIOD)
        context.SetDiscreteState(system.EvalUniquePeriodicDiscreteUpdate(context))
    return (time.perf_counter() - start) / num_ticks * 1e6


class _NoopEstimator(LeafSystem):
    """The estimator's ports and states, with an update that only reads the inputs."""

    def __init__(self, n: int, sensors: list[str]):
        super().__init__()
        self._inputs = [self.DeclareVectorInputPort(p, n) for p in ("q", "v", "vdot")]
        for p in (
            "imu_linear_acceleration",
            "imu_angular_velocity",
            "imu_angular_acceleration",
        ):
            self._inputs.append(self.DeclareVectorInputPort(p, 3))
        for s in sensors:
            self._inputs.append(self.DeclareVectorInputPort(f"wrench_{s}", 6))
        self._tau = self.DeclareDiscreteState(n)
        self.DeclareStateOutputPort("tau", self._tau)
        self.DeclarePeriodicDiscreteUpdateEvent(PERIOD, 0.0, self._update)

    def _update(self, context, discrete_state):
        for port in self._inputs:
            port.Eval(context)


def bench_estimator(num_ticks: int = 2000) -> list[dict]:
    """Measures the HRP-2 estimator's update, then the estimation stage
    (bench_estimation_stage). Returns rows {"name", "us_per_tick"} (and {"name",
    "blocks_per_tick"} for the allocation row)."""
    plant = MultibodyPlant(0.0)
    hrp2.add_hrp2(plant)
    plant.Finalize()
    base_config = hrp2_estimator_config(plant)
    sensors = list(base_config.sensors)
    inputs = _inputs(len(sensors))
    rows = []
    variants = {
        "estimator update (unknown wrench on the base)": {},
        "estimator update (unknown wrench on the torso)": {
            "unknown_wrench_body": "CHEST_LINK1"
        },
        "estimator update (rotor inertia off)": {"include_rotor_inertia": False},
        "estimator update (calibrating F/T offsets)": {"offset_calibration_time": 1e9},
    }
    for name, changes in variants.items():
        estimator = FloatingBaseTorqueEstimator(
            plant, dataclasses.replace(base_config, **changes)
        )
        context = estimator.CreateDefaultContext()
        _fix(estimator, context, inputs, sensors)
        _us_per_update(estimator, context, 50)  # warm up
        rows.append(
            {"name": name, "us_per_tick": _us_per_update(estimator, context, num_ticks)}
        )

    estimator = FloatingBaseTorqueEstimator(plant, base_config)
    args = [
        inputs[k]
        for k in (
            "q",
            "v",
            "vdot",
            "imu_linear_acceleration",
            "imu_angular_velocity",
            "imu_angular_acceleration",
        )
    ]
    wrenches = np.array(inputs["wrenches"])
    start = time.perf_counter()
    for _ in range(num_ticks):
        estimator.estimate(*args, wrenches)
    rows.append(
        {
            "name": "estimate() without a context",
            "us_per_tick": (time.perf_counter() - start) / num_ticks * 1e6,
        }
    )

    noop = _NoopEstimator(hrp2.NUM_JOINTS, sensors)
    context = noop.CreateDefaultContext()
    _fix(noop, context, inputs, sensors)
    rows.append(
        {
            "name": "baseline noop update (same ports)",
            "us_per_tick": _us_per_update(noop, context, num_ticks),
        }
    )

    estimator = FloatingBaseTorqueEstimator(plant, base_config)
    context = estimator.CreateDefaultContext()
    _fix(estimator, context, inputs, sensors)
    _us_per_update(estimator, context, 50)
    before = sys.getallocatedblocks()
    _us_per_update(estimator, context, num_ticks)
    rows.append(
        {
            "name": "net allocated blocks per tick",
            "blocks_per_tick": (sys.getallocatedblocks() - before) / num_ticks,
        }
    )
    return rows + bench_estimation_stage(num_ticks)


def _sensor_signals() -> dict[str, np.ndarray]:
    """Constant station-like outputs: half-sitting, at rest, standing wrenches."""
    standing = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 280.0])
    signals = {
        "q_measured": hrp2.half_sitting(),
        "imu_linear_acceleration": np.array([0.1, -0.2, 9.81]),
        "imu_angular_velocity": np.array([0.01, -0.02, 0.005]),
    }
    for name in hrp2.FT_SENSORS:
        signals[f"wrench_{name}"] = standing if "foot" in name else np.zeros(6)
    return signals


def _filter_us_per_update(system: SavitzkyGolayFilter, num_ticks: int) -> float:
    context = system.CreateDefaultContext()
    rng = np.random.default_rng(1)
    system.get_input_port().FixValue(context, rng.normal(size=system.num_signals()))
    _us_per_update(system, context, 50)
    return _us_per_update(system, context, num_ticks)


def bench_estimation_stage(num_ticks: int = 2000) -> list[dict]:
    """The per-tick cost of the SG stage and the estimator for the 30-joint HRP-2 as
    add_estimator wires them (module docstring). Rows {"name", "us_per_tick"}."""
    config = hrp2.estimator_config()
    n, k = hrp2.NUM_JOINTS, 3 + 3 + 6 * len(config.sensors)
    encoder = _filter_us_per_update(
        SavitzkyGolayFilter(n, config.window, 2, config.period), num_ticks
    )
    sensor = _filter_us_per_update(
        SavitzkyGolayFilter(k, config.window, 1, config.period), num_ticks
    )
    estimator = FloatingBaseTorqueEstimator(hrp2.estimator_plant(), config)
    context = estimator.CreateDefaultContext()
    _fix(estimator, context, _inputs(len(config.sensors)), list(config.sensors))
    _us_per_update(estimator, context, 50)
    update = _us_per_update(estimator, context, num_ticks)

    # The whole chain in a simulation, on constant signals from a station look-alike.
    station_builder = DiagramBuilder()
    for name, value in _sensor_signals().items():
        source = station_builder.AddNamedSystem(name, ConstantVectorSource(value))
        station_builder.ExportOutput(source.get_output_port(), name)
    builder = DiagramBuilder()
    station = builder.AddNamedSystem("station", station_builder.Build())
    add_estimator(builder, station, hrp2.estimator_plant(), config)
    simulator = Simulator(builder.Build())
    simulator.Initialize()
    simulator.AdvanceTo(50 * config.period)
    start = time.perf_counter()
    simulator.AdvanceTo((50 + num_ticks) * config.period)
    simulated = (time.perf_counter() - start) / num_ticks * 1e6
    label = f"window {config.window}, unknown wrench on the torso"
    return [
        {
            "name": f"estimation stage: encoder SG filter k={n} order 2",
            "us_per_tick": encoder,
        },
        {
            "name": f"estimation stage: sensor SG filter k={k} order 1",
            "us_per_tick": sensor,
        },
        {"name": f"estimation stage: estimator ({label})", "us_per_tick": update},
        {
            "name": "estimation stage: SG filters + estimator (sum of updates)",
            "us_per_tick": encoder + sensor + update,
        },
        {
            "name": "estimation stage: add_estimator chain simulated on constant "
            "signals",
            "us_per_tick": simulated,
        },
    ]


if __name__ == "__main__":
    for row in bench_estimator():
        if "us_per_tick" in row:
            print(f"{row['name']:<72s} {row['us_per_tick']:8.1f} us/tick")
        else:
            print(f"{row['name']:<72s} {row['blocks_per_tick']:8.3f}")
