"""Simulation helpers every layer may use: loggers for named ports, logs as arrays,
and a simulation loop that shows progress.
"""

import sys
import time
from typing import Callable

import numpy as np
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, OutputPort
from pydrake.systems.primitives import VectorLogSink


def add_loggers(
    builder: DiagramBuilder, ports: dict[str, OutputPort], period: float
) -> dict[str, VectorLogSink]:
    """A VectorLogSink per named port, publishing every `period` seconds."""
    loggers = {}
    for name, port in ports.items():
        logger = builder.AddNamedSystem(f"log_{name}", VectorLogSink(port.size(), period))
        builder.Connect(port, logger.get_input_port())
        loggers[name] = logger
    return loggers


def logs_to_arrays(loggers: dict[str, VectorLogSink], root_context) -> dict[str, np.ndarray]:
    """{"t": times, name: (samples, size) array} from the loggers' logs."""
    out: dict[str, np.ndarray] = {}
    for name, logger in loggers.items():
        log = logger.FindLog(root_context)
        out.setdefault("t", log.sample_times())
        out[name] = log.data().T
    return out


def run_with_progress(
    simulator: Simulator,
    duration: float,
    label: str,
    stream=None,
    steps: int = 10,
    on_step: Callable[[float], None] | None = None,
) -> float:
    """Advances `simulator` by `duration`, printing progress (one updating line on a
    terminal, a line per step otherwise); returns the real-time factor (simulated
    seconds per wall-clock second)."""
    stream = stream or sys.stderr
    t0 = simulator.get_context().get_time()
    wall0 = time.perf_counter()
    simulator.Initialize()
    tty = stream.isatty()
    prefix = "\r" if tty else ""
    for k in range(1, steps + 1):
        simulator.AdvanceTo(t0 + duration * k / steps)
        wall = time.perf_counter() - wall0
        print(
            f"{prefix}{label}: {duration * k / steps:6.2f}/{duration:.2f} s "
            f"simulated, {duration * k / steps / max(wall, 1e-9):5.2f}x real time",
            end="" if tty and k < steps else "\n",
            file=stream,
            flush=True,
        )
        if on_step is not None:
            on_step(simulator.get_context().get_time())
    return duration / max(time.perf_counter() - wall0, 1e-9)
