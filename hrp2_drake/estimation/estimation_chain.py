"""`add_estimator`: the whole estimation chain of paper Sec. 2 (the Savitzky-Golay
filters of Sec. 5.1 and the `FloatingBaseTorqueEstimator`) wired to a robot diagram's
sensor ports, and `EstimationChain`, the systems it adds.
"""

from dataclasses import dataclass

from pydrake.multibody.plant import MultibodyPlant
from pydrake.systems.framework import DiagramBuilder, OutputPort, System
from pydrake.systems.primitives import Adder, Demultiplexer, Multiplexer

from hrp2_drake.estimation.estimator_config import (
    TorqueEstimatorConfig,
    estimation_delay,
    filter_windows,
)
from hrp2_drake.estimation.savitzky_golay import SavitzkyGolayFilter
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
    delay everywhere).

    .. code-block:: text

        q_measured ──────────► SG order 2 ─► value, derivative, second_derivative
                                             = q, v, vdot ──────────────────┐
        imu_linear_acceleration ─┐                                          ▼
        imu_angular_velocity ────┼─► Mux ─► SG order 1 ─► value ─► Demux ─► estimator
        wrench_<s> (each) ───────┘                    └─► derivative ─► Demux ─┘
                                     (the gyro's derivative: imu_angular_acceleration)

    Without IMU (config.imu_frame empty, a fixed base) the two imu ports are neither
    read nor needed: the Mux, the order-1 filter and the value Demux carry the F/T
    sensors only, and there is no derivative Demux; without F/T sensors either, there
    is no order-1 filter at all (EstimationChain.sensor_filter is None).

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
    imu_ports = [accelerometer, gyroscope] if config.imu_frame else []
    sensor_ports = imu_ports + [wrench_prefix + s for s in config.sensors]
    _check_station_ports(station, config, encoders, sensor_ports)
    estimator = builder.AddNamedSystem(
        name, FloatingBaseTorqueEstimator(plant, config, lead=lead)
    )
    encoder_filter = _add_encoder_filter(
        builder, station, estimator, config, encoders, name, lead
    )
    faults = [encoder_filter.GetOutputPort("input_fault")]
    sensor_filter = _add_sensor_filter(
        builder, station, estimator, config, sensor_ports, name, lead
    )
    if sensor_filter is not None:
        faults.append(sensor_filter.GetOutputPort("input_fault"))
    fault = builder.AddNamedSystem(f"{name}_input_fault", Adder(len(faults), 1))
    for k, port in enumerate(faults):
        builder.Connect(port, fault.get_input_port(k))
    return EstimationChain(
        estimator, encoder_filter, sensor_filter, fault.get_output_port()
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


def _add_encoder_filter(
    builder: DiagramBuilder,
    station: System,
    estimator: FloatingBaseTorqueEstimator,
    config: TorqueEstimatorConfig,
    encoders: str,
    name: str,
    lead: float,
) -> SavitzkyGolayFilter:
    """Adds the encoders' Savitzky-Golay filter (order 2) between the station's port
    `encoders` and the estimator's q, v and vdot inputs; returns it."""
    encoder_windows, _ = filter_windows(config)
    encoder_filter = builder.AddNamedSystem(
        f"{name}_encoder_filter",
        SavitzkyGolayFilter(
            len(config.joints),
            encoder_windows,
            2,
            config.period,
            config.evaluation,
            span=config.span(),
            lead=lead,
        ),
    )
    builder.Connect(station.GetOutputPort(encoders), encoder_filter.get_input_port())
    for source, target in (
        ("value", "q"),
        ("derivative", "v"),
        ("second_derivative", "vdot"),
    ):
        builder.Connect(
            encoder_filter.GetOutputPort(source), estimator.GetInputPort(target)
        )
    return encoder_filter


def _add_sensor_filter(
    builder: DiagramBuilder,
    station: System,
    estimator: FloatingBaseTorqueEstimator,
    config: TorqueEstimatorConfig,
    sensor_ports: list[str],
    name: str,
    lead: float,
) -> SavitzkyGolayFilter | None:
    """Adds the IMU's and F/T sensors' Savitzky-Golay filter (order 1) between the
    station's `sensor_ports` (accelerometer and gyroscope with an IMU, then each F/T
    sensor's) and the estimator: a Mux, the filter, a Demux of its values, and with an
    IMU a Demux of its derivatives for the gyro's (imu_angular_acceleration). Returns
    the filter, or None (and adds nothing) without any of these sensors."""
    names = list(config.sensors)
    num_imu_ports = len(sensor_ports) - len(names)
    sizes = [3] * num_imu_ports + [6] * len(names)
    if not sizes:
        return None
    _, sensor_windows = filter_windows(config)
    mux = builder.AddNamedSystem(f"{name}_sensor_mux", Multiplexer(sizes))
    for k, port in enumerate(sensor_ports):
        builder.Connect(station.GetOutputPort(port), mux.get_input_port(k))
    sensor_filter = builder.AddNamedSystem(
        f"{name}_sensor_filter",
        SavitzkyGolayFilter(
            sum(sizes),
            sensor_windows,
            1,
            config.period,
            config.evaluation,
            span=config.span(),
            lead=lead,
        ),
    )
    builder.Connect(mux.get_output_port(), sensor_filter.get_input_port())
    values = builder.AddNamedSystem(f"{name}_sensor_values", Demultiplexer(sizes))
    builder.Connect(sensor_filter.GetOutputPort("value"), values.get_input_port())
    imu_targets = ["imu_linear_acceleration", "imu_angular_velocity"]
    targets = imu_targets[:num_imu_ports] + [f"wrench_{n}" for n in names]
    for k, target in enumerate(targets):
        builder.Connect(values.get_output_port(k), estimator.GetInputPort(target))
    if num_imu_ports:
        rates = builder.AddNamedSystem(
            f"{name}_sensor_derivatives", Demultiplexer(sizes)
        )
        builder.Connect(
            sensor_filter.GetOutputPort("derivative"), rates.get_input_port()
        )
        builder.Connect(
            rates.get_output_port(1),
            estimator.GetInputPort("imu_angular_acceleration"),
        )
    return sensor_filter
