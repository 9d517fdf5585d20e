import os

import pytest

os.environ.setdefault("MPLBACKEND", "Agg")


@pytest.fixture(scope="session")
def short_identification():
    """A shortened identification run on the hanging robot (about 45 s simulated, the
    `ideal` servo),
    shared by the tests that need data or an identified motor model.

    Returns (config, log, joint_names, result)."""
    from hrp2_drake.assembly.identification import (
        IdentifyConfig,
        collect_log,
        collected_log,
    )
    from hrp2_drake.identification.joint_fits import identify_logs
    from hrp2_drake.robot.station import StationConfig

    # The `ideal` servo: these tests check the machinery against the exact linear law;
    # `reproduce` reports what the calibrated servo costs.
    config = IdentifyConfig(
        duration_scale=0.5,
        station=StationConfig(scenario="hanging", servo_file="ideal"),
    )
    log, names = collect_log(config, progress=False)
    result = identify_logs(config.robot(), config, [collected_log(config, log, names)])
    return config, log, names, result


@pytest.fixture(scope="session")
def identified_model(short_identification):
    """The right leg's motor model identified by the asymmetric fit."""
    return short_identification[3].identified


@pytest.fixture(scope="session")
def xl330_prior():
    """A fixed XL330 servo, independent of the shipped (calibrated) servo.yaml: BAM's
    published XL330 model m1 (bam/params/xl330/m1.json: kt 0.387 N·m/A, R 4.02 Ω,
    friction 0.0128 N·m + 0.0037 N·m·s/rad) in the emulator's law at kp 400 and 7.4 V,
    the prior of `calibrate --robot xl330_pendulum --log`."""
    from hrp2_drake.robot.servo import ServoJointParams, ServoParams

    return ServoParams(
        joints={
            "servo": ServoJointParams(
                k1=0.386695764,
                k2=0.00366167228,
                k3=0.0128327204,
                k4=2.12020866,
                k5=0.0962621498,
                v_coulomb=0.05,
                encoder_resolution=0.00153398079,
                stall_current=1.84211628,
                no_load_speed=19.1365325,
                gain=400.0,
            )
        }
    )
