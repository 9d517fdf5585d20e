"""`hrp2-drake identify [--robot FILE] [--log LOG ...]`: motor identification of a
robot's controlled joints (paper Sec. 3, 5.2; HRP-2's right leg by default).

The command's pipeline: without logs, the identification on a collection on the
simulated robot (`assembly.identification.identify_collection`, what the paper's
reproduction and the balance experiment run too); with logs, the given logs read
(`identification.logs.read_logs`), identified (`identification.joint_fits.
identify_logs`) and reported the same way (`identification.report`): the Table 1
analogue, the validation table, Figures 1 and 3 and `motor_model.yaml`.
"""

from collections.abc import Sequence
from pathlib import Path

from hrp2_drake.assembly.identification import (
    IdentifyConfig,
    identify_collection,
    report_identification,
)
from hrp2_drake.identification.joint_fits import identify_logs
from hrp2_drake.identification.logs import read_logs


def run_identify(
    config: IdentifyConfig, out: Path, log_paths: Sequence[Path] | Path | None = None
) -> dict:
    """The whole `hrp2-drake identify`: collect (or read the logs), identify
    (`identify_logs`), report. `config` is validated by the caller (the command line
    validates it once; `IdentifyConfig.validate`)."""
    if isinstance(log_paths, (str, Path)):
        log_paths = [Path(log_paths)]
    if not log_paths:
        return identify_collection(config, out)
    out.mkdir(parents=True, exist_ok=True)
    robot = config.robot()
    logs, rows = read_logs(log_paths, robot)
    try:
        result = identify_logs(robot, config, logs)
    except (ValueError, KeyError) as error:
        message = (
            error.args[0] if isinstance(error, KeyError) and error.args else str(error)
        )
        where = (
            ""
            if any(message.startswith(str(p)) for p in log_paths)
            else f"{log_paths[0]}: "
        )
        raise ValueError(f"{where}{message}; no motor model written") from error
    result.logs = rows
    simulated = all(log.tau_true is not None for log in logs)
    return report_identification(result, out, config, simulated)
