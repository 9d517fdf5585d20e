"""Drake Diagrams over LCM, for the tests: the station's ports as LCM messages
(`make_lcm_station`, the controller's side) and the simulated station behind them
(`make_sim_robot`, the robot's side), built from Drake's `LcmInterfaceSystem`,
`LcmSubscriberSystem` and `LcmPublisherSystem` (Drake's hardware-station idiom:
`MakeHardwareStation(scenario, hardware=True|False)` in RussTedrake/manipulation).

The package's own path to a robot over LCM is not a Diagram: the controller's loop
(`hrp2_drake.hardware.control_loop.ControlLoop` with `lcm_link.LcmLink`) and the
robot's bridge (`hrp2_drake.hardware.robot_bridge.RobotBridge`, `hrp2-drake
sim-robot`). These Diagrams check that the same channels and messages carry the
station's ports, so that a Diagram controller (`build_torque_control`) runs on them
unchanged (tests/test_lcm.py). Moved here from `hrp2_drake.hardware.lcm_station`
(issue 28): only the tests used them.

.. code-block:: text

                ┌───────────────────────────────────────────┐
   q_cmd ──────►│ encode ─► LcmPublisherSystem <P>_Q_CMD    │
                │                                           ├──► q_measured
                │ LcmSubscriberSystem <P>_Q_MEASURED ─┐     ├──► imu_linear_acceleration
                │ LcmSubscriberSystem <P>_IMU ────────┼► decode ► imu_angular_velocity
                │ LcmSubscriberSystem <P>_WRENCH_<S> ─┘     ├──► wrench_<s> (each)
                │ LcmInterfaceSystem                        ├──► sensor_time
                └───────────────────────────────────────────┘

Messages cross the diagram as their bytes (`BytesSerializer`: pydrake's
`PySerializer` hands Python message objects through the diagram, and the framework
deep-copies them whenever it stores or caches one). `sensor_time` is the controller's
time at which each channel's latest new sample (a new timestamp) arrived, so that a
silent or frozen sensor goes stale there.
"""

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.lcm import DrakeLcmInterface
from pydrake.systems.framework import (
    Context,
    Diagram,
    DiagramBuilder,
    DiscreteValues,
    LeafSystem,
)
from pydrake.systems.lcm import (
    LcmInterfaceSystem,
    LcmPublisherSystem,
    LcmSubscriberSystem,
    SerializerInterface,
)

from hrp2_drake.description import RobotDescription
from hrp2_drake.hardware.lcm_station import LcmChannels
from hrp2_drake.hardware.messages import SignalCodec


class BytesSerializer(SerializerInterface):
    """An LCM serializer whose AbstractValue is the message's bytes (empty: none
    yet)."""

    def __init__(self):
        SerializerInterface.__init__(self)

    def __repr__(self) -> str:
        return "BytesSerializer()"

    def CreateDefaultValue(self) -> AbstractValue:
        return AbstractValue.Make(b"")

    def Deserialize(self, buffer, abstract_value: AbstractValue) -> None:
        abstract_value.set_value(bytes(buffer))

    def Serialize(self, abstract_value: AbstractValue) -> bytes:
        return abstract_value.get_value()


def _bytes_port(system: LeafSystem, name: str):
    return system.DeclareAbstractInputPort(name, AbstractValue.Make(b""))


class SensorDecoder(LeafSystem):
    """The robot's sensor messages as the station's vector ports (controller side).

    .. code-block:: text

                                  ┌───────────────┐
        q_measured_message ──────►│               ├──► q_measured
        imu_message (if IMU) ────►│ SensorDecoder ├──► imu_linear_acceleration,
                                  │               │    imu_angular_velocity
        wrench_<s>_message ──────►│               ├──► wrench_<s>
                                  │               ├──► sensor_time
                                  └───────────────┘

    Inputs are the messages' bytes (`BytesSerializer`). Each value output is the
    latest message (NaN before the first: the station waits for it). `sensor_time`
    holds, per sensor signal (`station.sensor_sizes` order), the context time at which
    its channel's latest new sample (a new timestamp) was seen: discrete state,
    updated every `period` (0 until then). A
    message of the wrong type, size or joint names raises a ValueError naming the
    channel.
    """

    def __init__(
        self, robot: RobotDescription, channels: LcmChannels, period: float = 0.001
    ):
        super().__init__()
        self._codecs = channels.codecs(robot)
        n = len(robot.joints)
        self._inputs = [_bytes_port(self, "q_measured_message")]
        self.DeclareVectorOutputPort(
            "q_measured", n, lambda c, o: o.SetFromVector(self._values(c, 0, n))
        )
        if robot.has_imu():
            self._inputs.append(_bytes_port(self, "imu_message"))
            self.DeclareVectorOutputPort(
                "imu_linear_acceleration",
                3,
                lambda c, o: o.SetFromVector(self._values(c, 1, 6)[:3]),
            )
            self.DeclareVectorOutputPort(
                "imu_angular_velocity",
                3,
                lambda c, o: o.SetFromVector(self._values(c, 1, 6)[3:]),
            )
        for name in robot.sensor_names():
            k = len(self._inputs)
            self._inputs.append(_bytes_port(self, f"wrench_{name}_message"))
            self.DeclareVectorOutputPort(
                f"wrench_{name}",
                6,
                lambda c, o, k=k: o.SetFromVector(self._values(c, k, 6)),
            )
        k = len(self._inputs)
        # [arrival time of the latest new sample (k); its timestamp (k)].
        state = self.DeclareDiscreteState(
            np.concatenate([np.zeros(k), np.full(k, -1.0)])
        )
        self._stamps = int(state)
        self.DeclarePeriodicDiscreteUpdateEvent(period, 0.0, self._update)
        # sensor_time follows the simulated station's order (`sensor_sizes`), where
        # the IMU is two signals: both carry the IMU channel's stamp.
        rows = (
            [0]
            + ([1, 1] if robot.has_imu() else [])
            + list(range(k - len(robot.sensor_names()), k))
        )
        self._rows = np.array(rows)
        self.DeclareVectorOutputPort(
            "sensor_time",
            len(rows),
            lambda c, o: o.SetFromVector(
                c.get_discrete_state(self._stamps).get_value()[self._rows]
            ),
        )

    def _values(self, context: Context, channel: int, size: int) -> np.ndarray:
        data = self._inputs[channel].Eval(context)
        if not data:
            return np.full(size, np.nan)
        return self._codecs[channel].values(data)

    def _update(self, context: Context, discrete_state: DiscreteValues) -> None:
        x = discrete_state.get_mutable_value(self._stamps)
        k = len(self._inputs)
        now = context.get_time()
        for c, (port, codec) in enumerate(zip(self._inputs, self._codecs)):
            stamp = codec.timestamp(port.Eval(context))
            if stamp != x[k + c]:
                x[c], x[k + c] = now, stamp


class CommandEncoder(LeafSystem):
    """q_cmd (rad, the robot's joint order) as an lcmt_drake_signal's bytes
    (controller side).

    .. code-block:: text

                 ┌────────────────┐
        q_cmd ──►│ CommandEncoder ├──► q_cmd_message
                 └────────────────┘
    """

    def __init__(self, joints, channel: str):
        super().__init__()
        self._codec = SignalCodec(joints, channel)
        self._q = self.DeclareVectorInputPort("q_cmd", len(joints))
        self.DeclareAbstractOutputPort(
            "q_cmd_message",
            lambda: AbstractValue.Make(b""),
            lambda c, o: o.set_value(self._codec.encode(self._q.Eval(c), c.get_time())),
        )


def make_lcm_station(
    robot: RobotDescription,
    lcm: DrakeLcmInterface,
    channels: LcmChannels | None = None,
    period: float = 0.001,
    wait_timeout: float = 10.0,
) -> Diagram:
    """The hardware station: the simulated station's port names over LCM (module
    docstring). Every sensor subscriber waits up to `wait_timeout` s (wall clock) for
    its first message when the simulator initializes, and raises a RuntimeError that
    names the channel and the LCM URL if none comes."""
    channels = (channels or LcmChannels()).resolved(robot)
    builder = DiagramBuilder()
    interface = builder.AddNamedSystem("lcm", LcmInterfaceSystem(lcm))
    decoder = builder.AddNamedSystem(
        "sensor_decoder", SensorDecoder(robot, channels, period)
    )
    for k, channel in enumerate(channels.sensors(robot)):
        subscriber = builder.AddNamedSystem(
            f"subscribe_{channel}",
            LcmSubscriberSystem(channel, BytesSerializer(), interface, wait_timeout),
        )
        builder.Connect(subscriber.get_output_port(), decoder.get_input_port(k))
    for i in range(decoder.num_output_ports()):
        port = decoder.get_output_port(i)
        builder.ExportOutput(port, port.get_name())
    encoder = builder.AddNamedSystem(
        "command_encoder", CommandEncoder(robot.joints, channels.q_cmd)
    )
    publisher = builder.AddNamedSystem(
        "publish_q_cmd",
        LcmPublisherSystem(
            channels.q_cmd, BytesSerializer(), interface, publish_period=period
        ),
    )
    builder.Connect(encoder.get_output_port(), publisher.get_input_port())
    builder.ExportInput(encoder.get_input_port(), "q_cmd")
    diagram = builder.Build()
    diagram.set_name(f"{robot.name}_lcm_station")
    return diagram


# ------------------------------------------------------------------ the robot's side


class CommandDecoder(LeafSystem):
    """The controller's q_cmd messages as the servo's command (robot side): the
    latest message's positions, or `initial` (the home pose) before the first.

    .. code-block:: text

                         ┌────────────────┐
        q_cmd_message ──►│ CommandDecoder ├──► q_cmd
                         └────────────────┘

    A message with the wrong joints raises a ValueError naming the channel.
    """

    def __init__(self, joints, initial: np.ndarray, channel: str):
        super().__init__()
        self._codec = SignalCodec(joints, channel)
        self._message = _bytes_port(self, "q_cmd_message")
        self._initial = np.asarray(initial, float)
        self.DeclareVectorOutputPort("q_cmd", len(joints), self._calc)

    def _calc(self, context: Context, output) -> None:
        data = self._message.Eval(context)
        output.SetFromVector(self._codec.values(data) if data else self._initial)


class SensorEncoder(LeafSystem):
    """The station's sensor ports as messages' bytes (robot side), one output per
    channel (`LcmChannels.sensors` order).

    .. code-block:: text

                                   ┌───────────────┐
        q_measured ───────────────►│               ├──► q_measured_message
        imu_linear_acceleration ──►│ SensorEncoder ├──► imu_message (if IMU)
        imu_angular_velocity ─────►│               ├──► wrench_<s>_message (each)
        wrench_<s> ───────────────►│               │
                                   └───────────────┘
    """

    def __init__(self, robot: RobotDescription, channels: LcmChannels):
        super().__init__()
        codecs = channels.codecs(robot)
        q = self.DeclareVectorInputPort("q_measured", len(robot.joints))
        self.DeclareAbstractOutputPort(
            "q_measured_message",
            lambda: AbstractValue.Make(b""),
            lambda c, o: o.set_value(codecs[0].encode(q.Eval(c), c.get_time())),
        )
        k = 1
        if robot.has_imu():
            acc = self.DeclareVectorInputPort("imu_linear_acceleration", 3)
            gyro = self.DeclareVectorInputPort("imu_angular_velocity", 3)
            self.DeclareAbstractOutputPort(
                "imu_message",
                lambda: AbstractValue.Make(b""),
                lambda c, o, imu=codecs[1]: o.set_value(
                    imu.encode(
                        np.concatenate([acc.Eval(c), gyro.Eval(c)]), c.get_time()
                    )
                ),
            )
            k = 2
        for name, codec in zip(robot.sensor_names(), codecs[k:]):
            port = self.DeclareVectorInputPort(f"wrench_{name}", 6)
            self.DeclareAbstractOutputPort(
                f"wrench_{name}_message",
                lambda: AbstractValue.Make(b""),
                lambda c, o, p=port, w=codec: o.set_value(
                    w.encode(p.Eval(c), c.get_time())
                ),
            )


def make_sim_robot(
    config, lcm: DrakeLcmInterface, channels: LcmChannels | None = None, meshcat=None
) -> Diagram:
    """The simulated robot behind the LCM channels (`hrp2-drake sim-robot`): the
    station of `config` (a StationConfig), its command from P_Q_CMD (the home pose
    until the first message), its sensors published every sensor period. Ground truth
    stays exported (`state_true`, `joint_torque_true`), for evaluation only."""
    from hrp2_drake.robot.station import initial_joint_positions, make_station

    robot = config.description()
    channels = (channels or LcmChannels()).resolved(robot)
    period = config.sensors_config().period
    builder = DiagramBuilder()
    interface = builder.AddNamedSystem("lcm", LcmInterfaceSystem(lcm))
    station = builder.AddNamedSystem("station", make_station(config, meshcat))
    subscriber = builder.AddNamedSystem(
        "subscribe_q_cmd",
        LcmSubscriberSystem(channels.q_cmd, BytesSerializer(), interface),
    )
    decoder = builder.AddNamedSystem(
        "command_decoder",
        CommandDecoder(robot.joints, initial_joint_positions(config), channels.q_cmd),
    )
    builder.Connect(subscriber.get_output_port(), decoder.get_input_port())
    builder.Connect(decoder.get_output_port(), station.GetInputPort("q_cmd"))
    encoder = builder.AddNamedSystem("sensor_encoder", SensorEncoder(robot, channels))
    for i in range(encoder.num_input_ports()):
        port = encoder.get_input_port(i)
        builder.Connect(station.GetOutputPort(port.get_name()), port)
    for i, channel in enumerate(channels.sensors(robot)):
        publisher = builder.AddNamedSystem(
            f"publish_{channel}",
            LcmPublisherSystem(
                channel, BytesSerializer(), interface, publish_period=period
            ),
        )
        builder.Connect(encoder.get_output_port(i), publisher.get_input_port())
    for name in ("state_true", "joint_torque_true", "q_measured"):
        builder.ExportOutput(station.GetOutputPort(name), name)
    builder.ExportOutput(decoder.get_output_port(), "q_cmd")
    diagram = builder.Build()
    diagram.set_name(f"{robot.name}_sim_robot")
    return diagram
