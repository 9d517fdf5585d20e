"""The estimation chain of paper Sec. 2 (the Savitzky-Golay filters of Sec. 5.1 and
the `FloatingBaseTorqueEstimator`) as rows of a chain (`estimation_rows`,
`hrp2_drake.chain`), and `add_estimator`, which adds them to a robot diagram wired
to its sensor ports; `EstimationChain`, the systems it adds.
"""

from dataclasses import dataclass

from pydrake.multibody.plant import MultibodyPlant
from pydrake.systems.framework import DiagramBuilder, OutputPort, System

from hrp2_drake.chain import (
    Arg,
    Chain,
    Row,
    Sum,
    add_chain,
    args,
    concatenated,
    entries,
    whole,
)
from hrp2_drake.estimation.estimator_config import (
    TorqueEstimatorConfig,
    estimation_delay,
    filter_windows,
)
from hrp2_drake.estimation.estimator_step import FloatingBaseTorqueEstimatorStep
from hrp2_drake.estimation.savitzky_golay import (
    SavitzkyGolayFilter,
    SavitzkyGolayFilterStep,
)
from hrp2_drake.estimation.torque_estimator import FloatingBaseTorqueEstimator


@dataclass
class EstimationChain:
    """The systems add_estimator adds.

    Attributes:
        estimator: the FloatingBaseTorqueEstimator.
        encoder_filter: Savitzky-Golay filter of the encoders (order 2): q, v, vdot.
        sensor_filter: one Savitzky-Golay filter (order 1) of [accelerometer (3); gyro
            (3); F/T sensors (6 each, config.sensors order)]: values, and the gyro's
            derivative as the angular acceleration. Without IMU it holds the F/T
            sensors only; None without IMU and F/T sensors.
        input_fault: the sum of the filters' `input_fault` (consecutive NaN or
            infinite samples they held): > 0 means the estimates rest on held data.
    """

    estimator: FloatingBaseTorqueEstimator
    encoder_filter: SavitzkyGolayFilter
    sensor_filter: SavitzkyGolayFilter | None
    input_fault: OutputPort  # (1,) consecutive bad samples held by either filter

    def delay(self) -> float:
        """Seconds between the robot state an output of the estimator describes and the
        time it is output (`estimation_delay`). For the paper's N = 80 at 1 kHz:
        39.5 ms."""
        return estimation_delay(self.estimator.config())


def add_estimator(
    builder: DiagramBuilder,
    station: System,
    plant: MultibodyPlant,
    config: TorqueEstimatorConfig,
    *,
    encoders: str = "q_measured",
    accelerometer: str = "imu_linear_acceleration",
    gyroscope: str = "imu_angular_velocity",
    wrench_prefix: str = "wrench_",
    name: str = "torque_estimator",
    lead: float = 0.0,
) -> EstimationChain:
    """Adds the whole estimation chain of paper Sec. 2 to `builder` and connects it to
    the output ports of `station` (a robot diagram, simulated or real, already added to
    `builder`), with the paper's filters (Sec. 5.1): Savitzky-Golay of order 2 on the
    encoders (q, v, vdot), of order 1 on the IMU and the F/T sensors (values; the gyro's
    derivative is the angular acceleration), one window for all (config.window) or one
    per signal (config.windows), every filter evaluated at config.window's point (one
    delay everywhere). The systems and their wiring are `estimation_rows`'.

    .. code-block:: text

        q_measured ──────────► SG order 2 ─► value, derivative, second_derivative
                                             = q, v, vdot ──────────────────┐
        imu_linear_acceleration ─┐                                          ▼
        imu_angular_velocity ────┼─► SG order 1 ─► value (entries) ──────► estimator
        wrench_<s> (each) ───────┘             └─► derivative (the gyro's) ─┘
                                     (imu_angular_acceleration)

    Without IMU (config.imu_frame empty, a fixed base) the two imu ports are neither
    read nor needed: the order-1 filter carries the F/T sensors only; without F/T
    sensors either, there is no order-1 filter at all (EstimationChain.sensor_filter
    is None).

    Args:
        builder: the builder that holds `station`.
        station: the system whose outputs are the robot's sensors.
        plant: the estimator's model of the robot (see FloatingBaseTorqueEstimator: a
            floating base, or welded to the world; not the station's plant, which may
            be welded or carry contact and strings).
        config: names and options; config.joints must be the order of the encoder port.
        encoders, accelerometer, gyroscope: names of the station's output ports
            (accelerometer and gyroscope only with an IMU).
        wrench_prefix: the F/T port of sensor s is wrench_prefix + s.
        name: name of the estimator; the other systems' names start with it (give
            another to add a second chain to the same builder).
        lead: the station samples this long (s) before each multiple of the period
            (`hrp2_drake.step.StepSystem`: the systems commit at its samples).

    Returns:
        The added systems (their outputs are the estimator's ports).

    Raises:
        KeyError: a port the station lacks (named), an unknown frame/joint.
    """
    config.validate()
    ports = StationPorts(encoders, accelerometer, gyroscope, wrench_prefix)
    _check_station_ports(station, config, encoders, ports.sensors(config))
    rows = estimation_rows(plant, config, lead=lead, ports=ports, name=name)
    signals = {
        f"station/{port}": station.GetOutputPort(port)
        for port in [encoders, *ports.sensors(config)]
    }
    added = add_chain(builder, Chain(tuple(rows), None, {}), signals)
    systems = added.systems
    return EstimationChain(
        systems["estimator"],
        systems["encoder_filter"],
        systems.get("sensor_filter"),
        added.logged["sensor_fault"],
    )


@dataclass(frozen=True)
class StationPorts:
    """The station's sensor ports the estimation chain reads, by role."""

    encoders: str = "q_measured"
    accelerometer: str = "imu_linear_acceleration"
    gyroscope: str = "imu_angular_velocity"
    wrench_prefix: str = "wrench_"

    def sensors(self, config: TorqueEstimatorConfig) -> list[str]:
        """The ports the order-1 filter reads, in its order: the IMU's, then each
        F/T sensor's."""
        imu = [self.accelerometer, self.gyroscope] if config.imu_frame else []
        return imu + [self.wrench_prefix + s for s in config.sensors]


def estimation_rows(
    plant: MultibodyPlant,
    config: TorqueEstimatorConfig,
    *,
    lead: float = 0.0,
    ports: StationPorts = StationPorts(),
    name: str = "torque_estimator",
) -> list[Row]:
    """The estimation chain's rows (`hrp2_drake.chain`): the encoders' filter
    ("encoder_filter"), the IMU's and F/T sensors' ("sensor_filter", if any) and the
    estimator ("estimator"), reading the station's signals (`ports`). The last row
    logs tau_estimated, every external_wrench_<s> and sensor_fault (the sum of the
    filters' input_fault: consecutive NaN or infinite samples held)."""
    encoder_windows, sensor_windows = filter_windows(config)
    period, evaluation, span = config.period, config.evaluation, config.span()
    N = len(config.joints)

    def sg(size, windows, order):
        return dict(
            make_step=lambda: SavitzkyGolayFilterStep(
                size, windows, order, period, evaluation, span=span
            ),
            make_system=lambda: SavitzkyGolayFilter(
                size, windows, order, period, evaluation, span=span, lead=lead
            ),
        )

    estimates = ("value", "derivative", "second_derivative")
    rows = [
        Row(
            name="encoder_filter",
            system_name=f"{name}_encoder_filter",
            inputs={"signal": whole(f"station/{ports.encoders}")},
            arguments=args("signal"),
            outputs=(*estimates, "input_fault"),
            initialize=args("signal"),
            **sg(N, encoder_windows, 2),
        )
    ]
    sensor_ports = ports.sensors(config)
    imu = bool(config.imu_frame)
    names = list(config.sensors)
    faults = ["encoder_filter/input_fault"]
    if sensor_ports:
        size = 3 * (2 if imu else 0) + 6 * len(names)
        rows.append(
            Row(
                name="sensor_filter",
                system_name=f"{name}_sensor_filter",
                inputs={
                    "signal": concatenated(
                        *(f"station/{p}" for p in sensor_ports),
                        name=f"{name}_sensor_signals",
                    )
                },
                arguments=args("signal"),
                outputs=(*estimates[:2], "input_fault"),
                initialize=args("signal"),
                **sg(size, sensor_windows, 1),
            )
        )
        faults.append("sensor_filter/input_fault")
    rows.append(_estimator_row(plant, config, lead, name, imu, names, faults))
    return rows


def _estimator_row(plant, config, lead, name, imu, names, faults) -> Row:
    """The estimator's row: q, v, vdot from the encoders' filter; the IMU's and the
    F/T sensors' filtered values (and the gyro's derivative) as entries of the
    sensor filter's outputs."""
    inputs = {
        port: whole(f"encoder_filter/{source}")
        for port, source in (
            ("q", "value"),
            ("v", "derivative"),
            ("vdot", "second_derivative"),
        )
    }
    start = 0
    if imu:
        for port, source, rows in (
            ("imu_linear_acceleration", "value", range(0, 3)),
            ("imu_angular_velocity", "value", range(3, 6)),
            ("imu_angular_acceleration", "derivative", range(3, 6)),
        ):
            inputs[port] = entries(
                f"sensor_filter/{source}", rows, name=f"{name}_{port}"
            )
        start = 6
    wrenches = tuple(f"wrench_{s}" for s in names)
    for k, port in enumerate(wrenches):
        rows = range(start + 6 * k, start + 6 * k + 6)
        inputs[port] = entries("sensor_filter/value", rows, name=f"{name}_{port}")
    imu_args = (
        args(
            "imu_linear_acceleration",
            "imu_angular_velocity",
            "imu_angular_acceleration",
        )
        if imu
        else (Arg(), Arg(), Arg())
    )
    wrench_arg = Arg(wrenches, (len(names), 6)) if names else Arg()
    externals = [f"external_wrench_{s}" for s in names]
    fault = Sum(tuple(faults), name=f"{name}_input_fault")
    return Row(
        name="estimator",
        system_name=name,
        make_step=lambda: FloatingBaseTorqueEstimatorStep(plant, config),
        make_system=lambda: FloatingBaseTorqueEstimator(plant, config, lead=lead),
        inputs=inputs,
        arguments=(*args("q", "v", "vdot"), *imu_args, wrench_arg),
        outputs=("tau", *externals),
        logged={
            "tau_estimated": whole("estimator/tau"),
            "sensor_fault": fault,
            **{e: whole(f"estimator/{e}") for e in externals},
        },
    )


def _check_station_ports(
    station: System,
    config: TorqueEstimatorConfig,
    encoders: str,
    sensor_ports: list[str],
) -> None:
    """add_estimator's first step: `station` has the encoder port, of one entry per
    joint, and every sensor port (a KeyError, a ValueError naming them otherwise)."""
    ports = [encoders] + sensor_ports
    missing = [p for p in ports if not station.HasOutputPort(p)]
    if missing:
        raise KeyError(
            f"add_estimator: station '{station.get_name()}' has no output ports "
            f"{missing}"
        )
    n = len(config.joints)
    if station.GetOutputPort(encoders).size() != n:
        raise ValueError(
            f"add_estimator: port '{encoders}' has "
            f"{station.GetOutputPort(encoders).size()} entries, config.joints has {n}"
        )
