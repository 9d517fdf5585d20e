"""The identification of any robot (paper Sec. 3, 5.2), as `hrp2-drake identify`
runs it without logs and as the paper's reproduction and the balance experiment run
it for a motor model: its config (`IdentifyConfig`: the fit's, `FitConfig`, and the
simulated robot's data collection), the collection on the simulated station, the
fit (`identification.joint_fits.identify_logs`) and the report
(`identification.report.write_report`, with the emulated servo's parameters as
ground truth for a simulated log).

In the assembly, not in identification/: it drives the simulated robot (the
station, `robot/`), which the algorithms' layer does not import; every step it
calls is in identification/.
"""

from dataclasses import dataclass, field
from pathlib import Path

from hrp2_drake.config import check_finite
from hrp2_drake.description import RobotDescription, load_robot_description
from hrp2_drake.description.excitation import CollectionConfig
from hrp2_drake.identification.excitation import collect, make_plan
from hrp2_drake.identification.joint_fits import (
    FitConfig,
    IdentificationResult,
    identify_logs,
)
from hrp2_drake.identification.logs import RobotLog, save_log, window_samples
from hrp2_drake.identification.report import write_report
from hrp2_drake.robot.ground_truth import true_motor_model
from hrp2_drake.robot.station import (
    StationConfig,
    initial_joint_positions,
    make_station,
)

#: The period of the collection's log (s): `excitation.collect`'s.
COLLECTION_LOG_PERIOD = 0.001


@dataclass
class IdentifyConfig(FitConfig):
    """Configuration of `hrp2-drake identify`: how the model is fitted (`FitConfig`:
    joints, window, stride, fit, saturation_margin, w, w_sweep,
    zero_velocity_threshold, held_out_block, held_out_every) and, without --log, the
    data collection on the simulated robot.

    Args:
        station: the robot (`station.robot`) and, without --log, the simulated robot
            during data collection (the paper's: hanging). With --log only its robot
            is read: a real robot's logs need its description, not a simulator.
        collection: pushes and sinusoids; empty sinusoids and push body: the robot
            description's `identification` (HRP-2: pushes on the right foot, one
            sinusoid per right-leg joint).
        duration_scale: shortens the default collection (1 = about 90 s of data).
    """

    station: StationConfig = field(
        default_factory=lambda: StationConfig(scenario="hanging")
    )
    collection: CollectionConfig = field(default_factory=CollectionConfig)
    duration_scale: float = 1.0

    def validate(self) -> None:
        """Raises ValueError naming the bad field (yaml_load_typed does not call it).
        The station is a simulation's (validated where one is collected)."""
        super().validate()
        self.collection.validate()
        check_finite(self.duration_scale, "IdentifyConfig.duration_scale", 0.0)
        self.check_joints(self.robot())

    def robot(self) -> RobotDescription:
        """The robot's description (`station.robot`): what its logs need."""
        return load_robot_description(self.station.robot or None)

    def collection_or_default(self) -> CollectionConfig:
        if self.collection.sinusoids or self.collection.pushes.body:
            return self.collection
        return self.robot().identification.scaled(
            self.duration_scale, self.station.sensors_config().seed
        )


def collect_log(
    config: IdentifyConfig, progress: bool = True
) -> tuple[dict, list[str]]:
    """Runs the data collection on the simulated robot."""
    robot = config.station.description()
    station = make_station(config.station)
    plant = station.GetSubsystemByName("plant")
    collection = config.collection_or_default()
    if collection.is_empty():
        raise ValueError(
            f"IdentifyConfig.collection: empty, and robot '{robot.name}' describes no "
            "identification excitation"
        )
    plan = make_plan(collection, robot.joints, initial_joint_positions(config.station))
    body = (
        plant.GetBodyByName(collection.pushes.body).index()
        if collection.pushes.body
        else None
    )
    log = collect(station, plan, body, collection.pushes.point, progress=progress)
    return log, list(robot.joints)


def identify_collection(config: IdentifyConfig, out: Path) -> dict:
    """The identification on a collection: collect on the simulated robot (its log
    saved as identification_log.npz), identify (`identify_logs`), report; the
    results as a dict. `config` is validated by the caller
    (`IdentifyConfig.validate`)."""
    out.mkdir(parents=True, exist_ok=True)
    robot = config.robot()
    # Refuse a window the collection's log cannot fill before collecting.
    window_samples(config.window, COLLECTION_LOG_PERIOD, "IdentifyConfig.window")
    arrays, names = collect_log(config)
    save_log(out / "identification_log.npz", arrays, names)
    logs = [collected_log(config, arrays, names)]
    result = identify_logs(robot, config, logs)
    result.logs = []
    simulated = all(log.tau_true is not None for log in logs)
    return report_identification(result, out, config, simulated)


def report_identification(
    result: IdentificationResult,
    out: Path,
    config: IdentifyConfig,
    simulated: bool,
) -> dict:
    """`write_report` of `result`; identified from `simulated` logs (all carry the
    true torques), it is compared with the emulated servo
    (`config.station.servo_file`; evaluation only)."""
    robot = result.robot
    truth = (
        true_motor_model(
            robot,
            result.config.identified_joints(robot),
            servo_file=config.station.servo_file,
        )
        if simulated
        else None
    )
    return write_report(result, out, truth)


def identify_motor_model(config: IdentifyConfig, out: Path) -> Path:
    """A motor model identified now, for a run given none: `identify_collection`
    (validated `config`; its log, report and fits under `out`); the path of the
    model it wrote, out/motor_model.yaml (the `config.fit` fit)."""
    identify_collection(config, out)
    return out / "motor_model.yaml"


def collected_log(config: IdentifyConfig, arrays: dict, names: list[str]) -> RobotLog:
    """The collection's arrays (`collect_log`) as a log: the simulated servo ran at the
    station's gain, so the model holds at it."""
    return RobotLog.from_arrays(
        arrays,
        names,
        config.robot().joints,
        config.station.servo_gain_in_use(),
        "the collected log",
    )
