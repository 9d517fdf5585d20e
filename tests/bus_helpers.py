"""What the bus loop tests share (tests/test_dynamixel_loop.py, test_feetech_loop.py):
`hrp2-drake sim-servo` in its own process in lock step, and `hrp2-drake control
--port` against it."""

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

from hrp2_drake.robot.ground_truth import true_motor_model

CLI = [sys.executable, "-m", "hrp2_drake.cli"]


class SimServo:
    """`hrp2-drake sim-servo` in its own process; `port` is the pseudo-terminal it
    printed."""

    def __init__(self, robot: str, *options: str, out: Path | None = None):
        command = CLI + ["sim-servo", "--robot", robot, "--lockstep", *options]
        if out is not None:
            command += ["--out", str(out)]
        self.popen = subprocess.Popen(
            command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        deadline = time.monotonic() + 120
        line = ""
        while time.monotonic() < deadline:
            line = self.popen.stdout.readline()
            if "sim-servo:" in line and " on /dev/" in line or not line:
                break
        assert " on /dev/" in line, (
            line,
            self.popen.stderr.read() if self.popen.poll() is not None else "",
        )
        self.port = line.split(" on ")[1].split()[0]

    def stop(self) -> None:
        if self.popen.poll() is None:
            self.popen.send_signal(signal.SIGTERM)
            try:
                self.popen.wait(20)
            except subprocess.TimeoutExpired:
                self.popen.kill()
                self.popen.wait(10)

    def kill(self) -> None:
        self.popen.kill()
        self.popen.wait(10)


def motor_model(tmp_path: Path, robot: str) -> Path:
    from hrp2_drake.description import load_robot_description

    path = tmp_path / f"{robot}_motor_model.yaml"
    true_motor_model(load_robot_description(robot)).save(path)
    return path


def control(
    tmp_path: Path,
    robot: str,
    port: str,
    model: Path,
    duration: float,
    *options: str,
    timeout: float = 600,
) -> subprocess.CompletedProcess:
    return subprocess.run(
        CLI
        + [
            "control",
            "--robot",
            robot,
            "--port",
            port,
            "--lockstep",
            "--motor-model",
            str(model),
            "--duration",
            str(duration),
            "--out",
            str(tmp_path / "control"),
            *options,
        ],
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def report(tmp_path: Path) -> dict:
    return json.loads((tmp_path / "control" / "control.json").read_text())
