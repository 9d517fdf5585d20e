"""The message-driven loops fail safe (hardware/control_loop.py, transport.py): the hub,
the robot (`sim-robot`) and the controller (`control`) as separate processes on
127.0.0.1, and each fault a robot's operator meets: the hub killed, a malformed or a
replayed encoder message, the robot killed, the controller killed, a listener that is
not a hub. Each ends with a ramp (where the robot can still be reached), a clean exit,
one line, and a report that names the fault and its time."""

import json
import signal
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from hrp2_drake.hardware.messages import SignalCodec
from hrp2_drake.hardware.transport import TcpqTransport, check_url, open_transport

ROBOT = "iiwa14"
CLI = [sys.executable, "-m", "hrp2_drake.cli"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class _Process:
    """A child process whose stderr is collected by a thread."""

    def __init__(self, argv):
        self.popen = subprocess.Popen(
            argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        self.lines: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self):
        for line in self.popen.stderr:
            self.lines.append(line.rstrip())

    def wait_for(self, text: str, timeout: float = 60.0) -> None:
        deadline = time.monotonic() + timeout
        while not any(text in line for line in self.lines):
            if self.popen.poll() is not None or time.monotonic() > deadline:
                raise AssertionError(f"no '{text}' in {self.lines}")
            time.sleep(0.05)

    def finish(self, timeout: float = 30.0) -> int:
        code = self.popen.wait(timeout)
        self._reader.join(5)
        return code

    def kill(self):
        if self.popen.poll() is None:
            self.popen.kill()
            self.popen.wait(10)


@pytest.fixture
def rig(tmp_path):
    """Starts the hub and the robot; `control(...)` starts the controller."""
    port = _free_port()
    url = f"tcpq://127.0.0.1:{port}"
    from hrp2_drake.description import load_robot_description
    from hrp2_drake.robot.ground_truth import true_motor_model

    model = tmp_path / "motor_model.yaml"
    true_motor_model(load_robot_description(ROBOT)).save(model)
    hub = subprocess.Popen(
        [sys.executable, "-m", "hrp2_drake.hardware.tcpq_hub", "--port", str(port)],
        stdout=subprocess.PIPE,
        text=True,
    )
    assert "hub on" in hub.stdout.readline()
    processes = {"hub": hub}

    class Rig:
        def __init__(self):
            self.url, self.out = url, tmp_path

        def robot(self, duration=30.0):
            # In lock step: its clock is the controller's commands, not the machine's.
            robot = _Process(
                CLI
                + [
                    "sim-robot",
                    "--robot",
                    ROBOT,
                    "--lcm",
                    url,
                    "--lockstep",
                    "--duration",
                    str(duration),
                    "--out",
                    str(tmp_path / "robot"),
                ]
            )
            processes["robot"] = robot
            robot.wait_for("sim-robot: iiwa14 on")
            self.robot_process = robot
            return robot

        def control(self, duration=3.0):
            config = tmp_path / "control.yaml"
            config.write_text("loop: {wait_timeout: 20.0}\n")
            control = _Process(
                CLI
                + [
                    "control",
                    "--robot",
                    ROBOT,
                    "--lcm",
                    url,
                    "--motor-model",
                    str(model),
                    "--config",
                    str(config),
                    "--duration",
                    str(duration),
                    "--out",
                    str(tmp_path / "control"),
                ]
            )
            processes["control"] = control
            control.wait_for("control: running")
            return control

        def kill_hub(self):
            hub.kill()
            hub.wait(10)

        def report(self):
            return json.loads((tmp_path / "control" / "control.json").read_text())

        def robot_report(self):
            return json.loads((tmp_path / "robot" / "sim_robot.json").read_text())

    yield Rig()
    for process in processes.values():
        if isinstance(process, _Process):
            process.kill()
        elif process.poll() is None:
            process.kill()
            process.wait(10)


def _publish_from_a_third_client(url: str, channel: str, data: bytes) -> None:
    _, _, address = url.partition("://")
    host, port = address.split(":")
    client = TcpqTransport(host, int(port))
    client.publish(channel, data)
    time.sleep(0.2)
    client.close()


def _held_after(rig, periods: int) -> None:
    """The robot holds its pose since `periods` of its own periods after the last new
    command (its watchdog), and kept that command since (sim_robot.npz)."""
    data = np.load(rig.out / "robot" / "sim_robot.npz")
    held = data["holding"] > 0
    assert held[-1]
    first_hold = len(held) - int(np.argmax(~held[::-1]))  # the last stretch of holding
    last_command = np.flatnonzero(data["commanded"][:first_hold] > 0)[-1]
    assert first_hold - last_command == periods
    assert np.ptp(data["q_cmd"][first_hold:], axis=0).max() == 0.0


@pytest.mark.slow
def test_a_run_ends_with_a_ramp_and_a_report(rig):
    rig.robot(duration=4.0)
    control = rig.control(duration=2.0)
    assert control.finish() == 0, control.lines
    report = rig.report()
    assert report["fault"] == "" and report["ramped"]
    # The lock-step robot waits on its first sample: every period of 2 s, no move.
    assert report["ticks"] == 2001 and report["approach_s"] == 0.0
    assert report["torque_share"] == 1.0
    assert (rig.out / "control" / "latency.png").stat().st_size > 1000
    assert (
        "How the run ended:** its duration"
        in (rig.out / "control" / "control.md").read_text()
    )
    # The robot's watchdog held the pose once the controller had gone: 6 of its own
    # periods after its last command (watchdog_periods 5), whatever the machine.
    assert rig.robot_process.finish(120) == 0
    summary = rig.robot_report()
    assert summary["watchdog_trips"] == 1 and summary["holding"]
    _held_after(rig, 6)


@pytest.mark.slow
def test_the_hub_killed(rig):
    robot = rig.robot()
    control = rig.control(duration=10.0)
    time.sleep(1.0)
    rig.kill_hub()
    assert control.finish(60) == 1, control.lines  # not SIGABRT (-6)
    assert robot.finish(60) == 1, robot.lines
    assert "the transport is gone" in control.lines[-1]
    assert "the transport is gone" in robot.lines[-1]
    report = rig.report()
    assert "the transport is gone" in report["fault"] and report["fault_time"] > 0.0
    assert "watchdog holds its pose" in (rig.out / "control" / "control.md").read_text()
    assert rig.robot_report()["holding"]


@pytest.mark.slow
def test_a_replayed_sample_is_refused_and_a_malformed_stream_ramps_out(rig):
    robot = rig.robot()
    control = rig.control(duration=10.0)
    time.sleep(1.5)
    joints = [f"iiwa_joint_{k}" for k in range(1, 8)]
    old = SignalCodec(joints, "IIWA14_Q_MEASURED").encode(np.zeros(7), 0.0005)
    _publish_from_a_third_client(rig.url, "IIWA14_Q_MEASURED", old)
    time.sleep(0.3)
    other = SignalCodec([f"other_{k}" for k in range(7)], "IIWA14_Q_MEASURED")
    _publish_from_a_third_client(
        rig.url, "IIWA14_Q_MEASURED", other.encode(np.zeros(7), 1e6)
    )
    assert control.finish() == 1, control.lines
    report = rig.report()
    assert report["refused_samples"] >= 1
    assert "coordinates" in report["fault"] and report["ramped"]
    assert "coordinates" in control.lines[-1]
    # Until the malformed message, the old sample did not disturb torque control.
    assert report["events"] == [] and report["torque_share"] == 1.0
    robot.popen.send_signal(signal.SIGTERM)
    robot.finish()


@pytest.mark.slow
def test_the_robot_killed(rig):
    robot = rig.robot()
    control = rig.control(duration=10.0)
    time.sleep(1.0)
    robot.kill()
    assert control.finish(60) == 1, control.lines
    report = rig.report()
    assert "the robot went silent" in report["fault"] and report["ramped"]
    assert "went silent" in control.lines[-1]
    # The report's tracking stops at the last real sample (no frozen encoders in it).
    text = (rig.out / "control" / "control.md").read_text()
    assert (
        "the robot went silent" in text and f"t = {report['fault_time']:.3f} s" in text
    )


@pytest.mark.slow
def test_the_controller_killed_the_robot_holds(rig):
    """The robot's watchdog counts its own periods: killed mid-run, the controller's
    last command is held for 5 periods, then the measured pose, for good."""
    robot = rig.robot(duration=8.0)
    control = rig.control(duration=30.0)
    time.sleep(1.0)
    control.kill()
    assert robot.finish(120) == 0
    summary = rig.robot_report()
    assert summary["watchdog_trips"] == 1 and summary["holding"]
    _held_after(rig, 6)


def test_a_listener_that_is_not_a_hub(tmp_path):
    with socket.create_server(("127.0.0.1", 0)) as server:
        port = server.getsockname()[1]
        start = time.monotonic()
        with pytest.raises(ConnectionError, match="did not answer as an LCM tcpq hub"):
            open_transport(f"tcpq://127.0.0.1:{port}", timeout=0.3)
        # It gives up instead of waiting forever: a bound for a hang, not a speed.
        assert time.monotonic() - start < 30.0


@pytest.mark.parametrize(
    "url, words",
    [
        ("bogus://x", "unknown scheme 'bogus'"),
        ("udpm://300.1.1.1:7667", "'300.1.1.1' is not an IP address"),
        ("udpm://10.0.0.1:7667", "is not a multicast group"),
        ("tcpq://127.0.0.1", "a port in 1-65535"),
        ("tcpq://127.0.0.1:99999", "Port out of range"),
    ],
)
def test_bad_urls_get_one_line(url, words):
    with pytest.raises(ValueError, match=words):
        check_url(url)


def test_no_hub_is_one_line():
    port = _free_port()
    with pytest.raises(ConnectionError, match="cannot connect"):
        open_transport(f"tcpq://127.0.0.1:{port}")


def test_the_hub_with_a_bad_or_busy_port_is_one_line():
    hub = [sys.executable, "-m", "hrp2_drake.hardware.tcpq_hub", "--port"]
    done = subprocess.run(hub + ["99999"], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and "a TCP port is 0-65535" in done.stderr
    assert "Traceback" not in done.stderr
    with socket.create_server(("127.0.0.1", 0)) as busy:
        port = busy.getsockname()[1]
        done = subprocess.run(
            hub + [str(port)], capture_output=True, text=True, timeout=60
        )
    assert done.returncode == 2 and "cannot listen on 127.0.0.1" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1


# ------------------------------------------------ what the machine cannot grant


def _refused(config, *words: str) -> None:
    with pytest.raises(ValueError) as info:
        config.validate(0.001, "ControlConfig.loop")
    line = str(info.value)
    assert "\n" not in line
    for word in words:
        assert word in line, line


def test_a_cpu_or_priority_that_cannot_be_granted_is_refused_at_load():
    """A CPU the process may not run on, and a SCHED_FIFO priority out of its range,
    are one line naming the key, before any loop starts; the defaults and what the
    machine has are accepted."""
    import os

    from hrp2_drake.hardware.control_loop import LoopSettings
    from hrp2_drake.hardware.real_time import RealTimeConfig

    cpus = sorted(os.sched_getaffinity(0))
    high = os.sched_get_priority_max(os.SCHED_FIFO)
    LoopSettings().validate(0.001, "ControlConfig.loop")
    LoopSettings(real_time=RealTimeConfig(cpu=cpus[-1], priority=high)).validate(0.001)
    for cpu in (max(cpus) + 1, 4096, -2):
        _refused(
            LoopSettings(real_time=RealTimeConfig(cpu=cpu)),
            "ControlConfig.loop.real_time.cpu",
            f"{cpu}",
            "-1: no pinning",
        )
    for priority in (high + 1, -1):
        _refused(
            LoopSettings(real_time=RealTimeConfig(priority=priority)),
            "ControlConfig.loop.real_time.priority",
            f"{priority}",
            f"SCHED_FIFO's range 1..{high}",
        )


def test_control_refuses_a_cpu_it_cannot_have_in_one_line(
    tmp_path, capsys, monkeypatch
):
    """`control --config` with `loop.real_time.cpu` beyond the machine's CPUs: exit
    code 2 and one line naming the file and the key, before any robot is reached."""
    from hrp2_drake.cli import main
    from hrp2_drake.paper import hrp2
    from hrp2_drake.tools import control

    def not_run(*args, **kwargs):
        raise AssertionError("ran despite a bad config")

    monkeypatch.setattr(control, "run_control", not_run)
    joints = hrp2.RIGHT_LEG
    (tmp_path / "motor.yaml").write_text(
        f"joint_names: [{', '.join(joints)}]\n"
        f"k_tau: [{', '.join(['1e-4'] * len(joints))}]\n"
        f"k_v: [{', '.join(['1e-2'] * len(joints))}]\n"
    )
    (tmp_path / "control.yaml").write_text("loop: {real_time: {cpu: 4096}}\n")
    code = main(
        [
            "control",
            "--lcm",
            "memq://",
            "--motor-model",
            str(tmp_path / "motor.yaml"),
            "--config",
            str(tmp_path / "control.yaml"),
            "--out",
            str(tmp_path / "out"),
        ]
    )
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(lines) == 1, lines
    assert "control.yaml" in lines[0] and "loop.real_time.cpu: 4096" in lines[0], lines
