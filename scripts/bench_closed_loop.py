"""Real-time factor of the closed-loop motion experiment (the unit of cost of a tuner),
and where its time goes, system by system.

Rows (one run, so that ratios between rows are meaningful; 2 cores, shared):
- "torque control K6=0.1, all ports logged": the hanging HRP-2 tracking the climbing
  motion with the paper's torque control on the right leg (`build_torque_control`,
  supervised, the identified motor model of `hrp2-drake reproduce` if there is one),
  every output port of the control diagram logged at 1 kHz (as
  `motion.run_controller` does it).
- "torque control K6=0.1, tuner's ports": the same run logging only what a tuner reads
  (`TUNER_PORTS`: q_ref, q_measured, delta_q, fallback_active, and the supervisor's
  outputs).
- "torque control K6=0.1 fused, ...": the same chain as one FusedTorqueController
  (`build_torque_control(fused=True)`, the same signals): what `tune` runs (goal of
  issue 21: >= 4x real time).
- "torque control K6=0.1 unsupervised, ...": the paper's stack alone (the Δq
  controller's own latched fallback, no SafetySupervisor): what the supervisor costs.
- "position control, ...": the robot's own servo on the same reference (the baseline).
- "bare hanging plant": the station's MultibodyPlant alone (strings, no servo, no
  sensors; zero actuation: the robot hangs limp), a reference for the plant's step.
  An upper bound: limp, the legs rest on their joint limits, so SAP solves limit
  constraints at every step, which the servo-held robot of the other rows never
  does (there the plant's own step costs about 60% of this row, callgrind).
  Columns: real_time_factor (simulated s per wall-clock s), cpu_real_time_factor (per
  CPU s of this process: less sensitive to other processes on the machine),
  us_per_step (wall clock, per 1 ms step).
- "breakdown: ...": one more torque-control run (tuner's ports) with the callbacks
  (output calcs, event handlers) of every Python LeafSystem timed (`_SystemTimer`):
  each system's time per step, exclusive of the Python systems it pulls through its
  inputs (but with the C++ work its Evals trigger), its share of the run and its
  callbacks per step; the rest is Drake's C++ (the plant's step, C++ systems such as
  the IMU, MatrixGain selectors and loggers, event dispatch, the pybind11 calls into
  the callbacks). The timers add about 1 us per callback.

Run: .venv/bin/python scripts/bench_closed_loop.py [duration]   (or bench.py --only
closed_loop)
"""

import functools
import sys
import time
import types
from collections import defaultdict
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

import numpy as np
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, LeafSystem
from pydrake.systems.primitives import ConstantVectorSource

from hrp2_drake.assembly.builders import (
    build_position_control,
    build_torque_control,
    simulated_station,
)
from hrp2_drake.identification.motor_model import MotorModel
from hrp2_drake.paper import hrp2, motion
from hrp2_drake.robot.station import (
    StationConfig,
    add_scenario_plant,
    initial_joint_positions,
)
from hrp2_drake.simulation import add_loggers

#: What a tuner logs of a torque-control run (those the diagram has).
TUNER_PORTS = (
    "q_ref",
    "q_measured",
    "delta_q",
    "fallback_active",
    "supervisor_mode",
    "supervisor_fault",
    "supervisor_transition",
)
K6 = 0.1
MOTOR_MODEL = (
    Path(__file__).resolve().parents[1] / "out/reproduce/identify/motor_model.yaml"
)
PERIOD = 1e-3  # s, the plant's and the controllers' step


def _motor_model() -> tuple[MotorModel, str]:
    """The identified motor model of `hrp2-drake reproduce` if there is one (what the
    motion experiment uses), else the servo's true one."""
    if MOTOR_MODEL.is_file():
        return MotorModel.load(MOTOR_MODEL), "out/reproduce/identify/motor_model.yaml"
    return hrp2.true_motor_model(), "the servo's true motor model"


def _diagrams(duration: float | None):
    """(reference duration, {label: factory of a ControlDiagram}) of the motion
    experiment: the whole climbing motion (1 s settle), or its first `duration` s."""
    config = motion.MotionConfig()
    reference = motion.motion_reference(config)
    end = (
        reference.end_time()
        if duration is None
        else min(duration, reference.end_time())
    )
    motor_model, _ = _motor_model()
    base = config.torque_control
    torque = replace(base, controller=replace(base.controller, k6=K6))

    def torque_control(torque_config, fused: bool = False):
        robot, station, period = simulated_station(config.station)
        return build_torque_control(
            robot,
            station,
            reference,
            motor_model,
            torque_config,
            control_period=period,
            fused=fused,
        )

    def position_control():
        robot, station, _ = simulated_station(config.station)
        return build_position_control(robot, station, reference)

    return end, {
        "torque control K6=0.1": lambda: torque_control(torque),
        # The same chain as one FusedTorqueController (the same signals; what `tune`
        # and the hardware loop run).
        "torque control K6=0.1 fused": lambda: torque_control(torque, fused=True),
        # The paper's stack alone: the Δq controller's own latched fallback, no
        # SafetySupervisor (ours, beyond the paper).
        "torque control K6=0.1 unsupervised": lambda: torque_control(
            replace(torque, supervised=False)
        ),
        "position control": position_control,
    }


def _simulator(control, ports: tuple[str, ...] | None) -> Simulator:
    """A simulator of `control` with a 1 kHz logger on the given exported ports (all
    vector ports if None), as `motion.run_controller` builds it."""
    builder = DiagramBuilder()
    builder.AddNamedSystem("control", control.diagram)
    names = control.output_names()
    if ports is not None:
        names = [name for name in names if name in ports]
    add_loggers(builder, {n: control.diagram.GetOutputPort(n) for n in names}, PERIOD)
    return Simulator(builder.Build())


def _timed(simulator: Simulator, duration: float, reset=None) -> tuple[float, float]:
    """(wall-clock, CPU) seconds of this process to simulate `duration` seconds after
    Initialize (`reset()` called between the two)."""
    simulator.Initialize()
    if reset is not None:
        reset()
    wall, cpu = time.perf_counter(), time.process_time()
    simulator.AdvanceTo(duration)
    return time.perf_counter() - wall, time.process_time() - cpu


def _bare_hanging_plant() -> Simulator:
    """The hanging station's MultibodyPlant (`station.add_scenario_plant`: the same
    config, model and strings) with zero actuation and nothing else."""
    config = StationConfig(scenario="hanging")
    builder = DiagramBuilder()
    plant, _ = add_scenario_plant(
        builder, config, config.description(), initial_joint_positions(config)
    )
    zero = builder.AddSystem(ConstantVectorSource(np.zeros(plant.num_actuators())))
    builder.Connect(zero.get_output_port(), plant.get_actuation_input_port())
    return Simulator(builder.Build())


#: The LeafSystem methods that take a callback (output calc, event handler).
_DECLARE_WITH_CALLBACK = (
    "DeclareVectorOutputPort",
    "DeclareAbstractOutputPort",
    "DeclareCacheEntry",
    "DeclarePeriodicDiscreteUpdateEvent",
    "DeclarePeriodicPublishEvent",
    "DeclarePeriodicUnrestrictedUpdateEvent",
    "DeclarePerStepDiscreteUpdateEvent",
    "DeclarePerStepPublishEvent",
    "DeclarePerStepUnrestrictedUpdateEvent",
    "DeclareInitializationDiscreteUpdateEvent",
    "DeclareInitializationPublishEvent",
    "DeclareInitializationUnrestrictedUpdateEvent",
    "DeclareForcedDiscreteUpdateEvent",
    "DeclareForcedPublishEvent",
    "DeclareForcedUnrestrictedUpdateEvent",
)


class _SystemTimer:
    """Times the callbacks (output calcs, event handlers) of every Python LeafSystem,
    per system, exclusive of nested callbacks of other systems: a system that Evals an
    input computed by another Python system is not charged for that system's calc (it
    is charged for the C++ work its Evals trigger, e.g. the plant's outputs).

    Drake binds a system's callbacks when its constructor declares them, so the
    Declare* methods of LeafSystem are wrapped (`patched`) while the diagram is built:
    they time the callbacks they are given; they are restored after."""

    def __init__(self):
        self._stack: list[list] = []  # [start, time spent in nested callbacks]
        self.reset()

    def reset(self) -> None:
        """Forgets the times and calls so far (e.g. those of Initialize)."""
        self.seconds: dict[str, float] = defaultdict(float)
        self.calls: dict[str, int] = defaultdict(int)

    def _timed(self, system: LeafSystem, callback):
        """`callback`, timed under its system's name (known once the system is in a
        builder, so read at the first call)."""
        label = None

        @functools.wraps(callback)
        def timed(*args):
            nonlocal label
            if label is None:
                label = f"{type(system).__name__} {system.get_name()}"
            frame = [time.perf_counter(), 0.0]
            self._stack.append(frame)
            try:
                return callback(*args)
            finally:
                self._stack.pop()
                elapsed = time.perf_counter() - frame[0]
                self.seconds[label] += elapsed - frame[1]
                self.calls[label] += 1
                if self._stack:
                    self._stack[-1][1] += elapsed

        return timed

    @contextmanager
    def patched(self):
        originals = {name: getattr(LeafSystem, name) for name in _DECLARE_WITH_CALLBACK}

        def declare(original):
            def wrapper(system, *args, **kwargs):
                args = [self._timed(system, a) if _is_callback(a) else a for a in args]
                kwargs = {
                    k: self._timed(system, a) if _is_callback(a) else a
                    for k, a in kwargs.items()
                }
                return original(system, *args, **kwargs)

            return wrapper

        for name, original in originals.items():
            setattr(LeafSystem, name, declare(original))
        try:
            yield
        finally:
            for name, original in originals.items():
                setattr(LeafSystem, name, original)


def _is_callback(value) -> bool:
    return isinstance(value, (types.FunctionType, types.MethodType))


def _row(name: str, duration: float, wall: float, cpu: float) -> dict:
    return {
        "name": name,
        "real_time_factor": duration / wall,
        "cpu_real_time_factor": duration / cpu,
        "us_per_step": wall / duration * PERIOD * 1e6,
    }


def bench_closed_loop(
    duration: float | None = None, profile: float = 4.0
) -> list[dict]:
    """The rows of the module docstring. `duration`: simulated seconds of each timed
    run (None: the whole motion, its 1 s settle included); `profile`: of the
    breakdown run."""
    end, factories = _diagrams(duration)
    _, source = _motor_model()
    print(f"  {end:.2f} s simulated per run; motor model: {source}", file=sys.stderr)
    rows = []
    for label, factory in factories.items():
        for logged, ports in (
            ("all ports logged", None),
            ("tuner's ports", TUNER_PORTS),
        ):
            wall, cpu = _timed(_simulator(factory(), ports), end)
            rows.append(_row(f"{label}, {logged}", end, wall, cpu))
    wall, cpu = _timed(_bare_hanging_plant(), end)
    rows.append(_row("bare hanging plant (limp: no servo, no sensors)", end, wall, cpu))
    for row in rows:
        print(
            f"  {row['name']:<58s} {row['real_time_factor']:5.2f}x real time "
            f"({row['cpu_real_time_factor']:5.2f}x CPU time) "
            f"{row['us_per_step']:6.0f} us/step",
            file=sys.stderr,
        )
    return rows + breakdown(factories["torque control K6=0.1"], min(profile, end))


def breakdown(factory, duration: float) -> list[dict]:
    """Per-system time (`_SystemTimer`) of `duration` simulated seconds of
    `factory()`'s diagram, the tuner's ports logged; the rest is Drake's C++."""
    timer = _SystemTimer()
    with timer.patched():
        simulator = _simulator(factory(), TUNER_PORTS)
    total, _ = _timed(simulator, duration, reset=timer.reset)
    steps = duration / PERIOD
    rows = []
    for label, seconds in sorted(timer.seconds.items(), key=lambda item: -item[1]):
        rows.append(
            {
                "name": f"breakdown: {label}",
                "us_per_step": seconds / steps * 1e6,
                "share": seconds / total,
                "calls_per_step": timer.calls[label] / steps,
            }
        )
    rest = total - sum(timer.seconds.values())
    rows.append(
        {
            "name": "breakdown: Drake C++ (plant step, C++ systems, loggers, events)",
            "us_per_step": rest / steps * 1e6,
            "share": rest / total,
        }
    )
    rows.append(
        {
            "name": f"breakdown: total ({duration:g} s simulated, timers on)",
            "us_per_step": total / steps * 1e6,
            "share": 1.0,
        }
    )
    for row in rows:
        calls = (
            f" {row['calls_per_step']:4.1f} calls" if "calls_per_step" in row else ""
        )
        print(
            f"  {row['name']:<72s} {row['us_per_step']:6.1f} us/step "
            f"{row['share'] * 100:5.1f}%{calls}",
            file=sys.stderr,
        )
    return rows


if __name__ == "__main__":
    for row in bench_closed_loop(float(sys.argv[1]) if len(sys.argv) > 1 else None):
        print(row)
