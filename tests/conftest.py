import os

import pytest

os.environ.setdefault("MPLBACKEND", "Agg")


@pytest.fixture(scope="session")
def short_identification():
    """A shortened identification run on the hanging robot (about 45 s simulated, the
    `ideal` servo),
    shared by the tests that need data or an identified motor model.

    Returns (config, log, joint_names, result)."""
    from hrp2_drake.experiments.identification import (
        IdentifyConfig,
        collect_log,
        identify,
    )

    from hrp2_drake.robot.station import StationConfig

    # The `ideal` servo: these tests check the machinery against the exact linear law;
    # `reproduce` reports what the calibrated servo costs.
    config = IdentifyConfig(
        duration_scale=0.5, station=StationConfig(scenario="hanging", servo_file="ideal")
    )
    log, names = collect_log(config, progress=False)
    return config, log, names, identify(config, log, names)


@pytest.fixture(scope="session")
def identified_model(short_identification):
    """The right leg's motor model identified by the asymmetric fit."""
    return short_identification[3].identified
