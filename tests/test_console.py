"""The console of a run (hrp2_drake.console): one line format, each repeated warning
printed once and counted, the counts printed when the run ends."""

import logging
import warnings

from hrp2_drake import console


def _fallback(
    logger: logging.Logger, t: float, reason: str = "|tau_estimated| exceeds tau_limit"
):
    # The message of DeltaQTorqueController's shell, as it logs it.
    logger.warning(
        "%s %s: falling back to position control at t = %.6g s: %s",
        "DeltaQTorqueController",
        "::_::control::torque_controller",
        t,
        reason,
    )


def test_a_repeated_warning_is_printed_once_then_counted(capsys):
    logger = logging.getLogger("hrp2_drake.control.torque_controller")
    with console.session("hrp2-drake experiment") as session:
        for k in range(5):
            _fallback(logger, 0.512 + 0.001 * k)
        for k in range(3):
            _fallback(logger, 0.6 + k, "q_measured is not finite")
        logging.getLogger("hrp2_drake.paper.reproduce").info("motion: done in 12 s")
        logging.getLogger("somebody.else").info("not shown")
        assert session.repeats() == {
            "warning: DeltaQTorqueController ::_::control::torque_controller: falling "
            "back to position control at t = … s: |tau_estimated| exceeds tau_limit": 4,
            "warning: DeltaQTorqueController ::_::control::torque_controller: falling "
            "back to position control at t = … s: q_measured is not finite": 2,
        }
    err = capsys.readouterr().err.splitlines()
    assert err == [
        "hrp2-drake experiment: warning: DeltaQTorqueController "
        "::_::control::torque_controller: falling back to position control at "
        "t = 0.512 s: |tau_estimated| exceeds tau_limit",
        "hrp2-drake experiment: warning: DeltaQTorqueController "
        "::_::control::torque_controller: falling back to position control at "
        "t = 0.6 s: q_measured is not finite",
        "hrp2-drake experiment: motion: done in 12 s",
        "hrp2-drake experiment: warning: repeated 4 more times: DeltaQTorqueController "
        "::_::control::torque_controller: falling back to position control at t = … s: "
        "|tau_estimated| exceeds tau_limit",
        "hrp2-drake experiment: warning: repeated 2 more times: DeltaQTorqueController "
        "::_::control::torque_controller: falling back to position control at t = … s: "
        "q_measured is not finite",
    ]
    # The session is over: logging is as it was (Python's last resort for warnings).
    assert console.current() is None and console.line("x") == "x"
    assert not [
        h for h in logging.getLogger().handlers if isinstance(h, console._Handler)
    ]


def test_counts_of_a_worker_are_printed_by_the_parent_at_the_end(capsys):
    logger = logging.getLogger("hrp2_drake.control.safety")
    with console.session(
        "hrp2-drake reproduce", context="motion", summary=False
    ) as worker:
        for k in range(7):
            logger.warning(
                "SafetySupervisor x: fault at t = %.6g s (encoder jump)", 1.0 + k
            )
        counts = worker.repeats()  # what a worker returns in its step's summary
    assert counts == {"warning: SafetySupervisor x: fault at t = … s (encoder jump)": 6}
    assert capsys.readouterr().err.splitlines() == [
        "hrp2-drake reproduce: motion: warning: SafetySupervisor x: fault at t = 1 s "
        "(encoder jump)"
    ]
    with console.session("hrp2-drake reproduce") as parent:
        parent.add_repeats(counts, "motion")
        parent.add_repeats({}, "force")
    assert capsys.readouterr().err.splitlines() == [
        "hrp2-drake reproduce: motion: warning: repeated 6 more times: "
        "SafetySupervisor x: fault at t = … s (encoder jump)"
    ]


def test_python_warnings_take_the_same_format_and_are_counted(capsys):
    with console.session("hrp2-drake identify"):
        for _ in range(3):
            warnings.warn_explicit(
                "rank deficient at 3 samples", UserWarning, "fit.py", 12
            )
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 2
    assert err[0].startswith(
        "hrp2-drake identify: warning: fit.py:12: UserWarning: rank"
    )
    assert err[1].startswith(
        "hrp2-drake identify: warning: repeated 2 more times: fit.py:"
    )


def test_template_keeps_names_and_masks_numbers():
    assert console.template("RLEG_JOINT4 at t = 0.512 s, K6=0.1, 1e-3 rad, -2 N·m") == (
        "RLEG_JOINT4 at t = … s, K6=…, … rad, … N·m"
    )


def test_a_line_is_one_write_so_processes_sharing_stderr_keep_it_whole():
    """print() writes the text and its newline apart: unbuffered (PYTHONUNBUFFERED),
    two processes' lines could then interleave. `say` and the progress lines write
    each line whole."""
    from pydrake.systems.analysis import Simulator
    from pydrake.systems.primitives import ConstantVectorSource

    from hrp2_drake.simulation import run_with_progress

    class Writes:
        def __init__(self):
            self.calls = []

        def write(self, text):
            self.calls.append(text)

        def flush(self):
            pass

        def isatty(self):
            return False

    stream = Writes()
    with console.session("hrp2-drake experiment", context="motion", summary=False):
        console.say("hanging: best window 40", stream)
        run_with_progress(
            Simulator(ConstantVectorSource([1.0])), 0.01, "run", stream, steps=2
        )
    assert stream.calls[0] == "hrp2-drake experiment: motion: hanging: best window 40\n"
    assert len(stream.calls) == 3 and all(c.endswith("\n") for c in stream.calls)
    assert stream.calls[1].startswith(
        "hrp2-drake experiment: motion: run:   0.01/0.01 s"
    )
