"""numba kernels (hrp2_drake/kernels.py): compiled before a real-time loop, never inside
it. The fused controller's steps compile (or load from the cache) in `warm_up`; a loop
refuses to start without it; frozen, a kernel called with a new signature raises
instead of compiling; the fused controller gives the same numbers compiled and as
Python source."""

import numpy as np
import pytest

from hrp2_drake import kernels
from hrp2_drake.assembly.builders import torque_chain_parts
from hrp2_drake.control.fused import FusedController
from hrp2_drake.hardware.control_loop import ControlLoop
from hrp2_drake.hardware.in_process import run_in_process
from hrp2_drake.hardware.link import RobotLink
from hrp2_drake.robot.ground_truth import true_motor_model
from hrp2_drake.robot.station import StationConfig, make_station
from hrp2_drake.tools.control import ControlConfig, control_reference

IIWA = StationConfig(robot="iiwa14", scenario="fixed_base")


def _controller() -> tuple[FusedController, object]:
    config = ControlConfig(robot="iiwa14", duration=1.0)
    robot = config.description()
    reference = control_reference(config)
    parts = torque_chain_parts(
        robot,
        reference,
        true_motor_model(robot),
        config.torque_control_at_period(),
        period=config.period(),
    )
    return FusedController(parts), reference


def test_the_loop_refuses_to_start_before_the_kernels_are_compiled():
    controller, reference = _controller()
    loop = ControlLoop(controller, RobotLink(), reference, duration=1.0)
    with pytest.raises(RuntimeError, match="refuses to start.*warm_up"):
        loop.run()
    assert controller.warm_up() >= 0.0 and controller.warmed_up


def test_frozen_the_controller_ticks_and_a_new_signature_raises():
    controller, reference = _controller()
    controller.warm_up()
    # The simulated robot's kernels (its servo's, its sensors') compile when a station
    # is made: before freezing, as a real robot's are compiled before its loop.
    make_station(IIWA)
    try:
        kernels.freeze()
        # A tick on the real arrays runs without compiling.
        run_in_process(IIWA, controller, reference, 20)
        compiled = [k for k in kernels.kernels() if k.signatures]
        assert compiled, "no kernel compiled"
        with pytest.raises(TypeError):  # float32: a signature never compiled
            compiled[0](*[np.zeros(3, np.float32)] * len(compiled[0].signatures[0]))
    finally:
        kernels.thaw()


@pytest.mark.slow
def test_the_fused_controller_compiled_equals_its_python_source():
    """200 ticks of the iiwa in closed loop, compiled and with every kernel its Python
    source (`kernels.interpreted`, what NUMBA_DISABLE_JIT=1 gives): the commands and
    τ̂ within 1e-12."""
    compiled = run_in_process(IIWA, _controller()[0], _controller()[1], 200)
    with kernels.interpreted():
        controller, reference = _controller()
        source = run_in_process(IIWA, controller, reference, 200)
    for (q_a, tau_a), (q_b, tau_b) in zip(compiled, source):
        np.testing.assert_allclose(q_a, q_b, rtol=0, atol=1e-12)
        np.testing.assert_allclose(tau_a, tau_b, rtol=0, atol=1e-12)
