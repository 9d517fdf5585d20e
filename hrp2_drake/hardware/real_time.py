"""What a real-time loop asks of the operating system and of Python: a CPU, the
SCHED_FIFO scheduler (`RealTimeConfig`, `request_real_time`), and no garbage collection
inside the loop (`garbage_collector_frozen`). The controller's loop
(`hardware.control_loop`), the robot's bridge (`hardware.robot_bridge`) and the
recorder (`tools.record`) use them.
"""

import contextlib
import gc
import math
import os
from collections.abc import Iterator
from dataclasses import dataclass


@dataclass
class RealTimeConfig:
    """How the loop asks the operating system for real time.

    Args:
        cpu: pin the process to this CPU (-1: leave it).
        priority: ask for SCHED_FIFO at this priority (0: the normal scheduler).
        freeze_gc: collect and freeze the garbage collector's objects after start-up
            and disable it while the loop runs.
    """

    cpu: int = -1
    priority: int = 0
    freeze_gc: bool = True


def request_real_time(config: RealTimeConfig) -> dict:
    """Pins the CPU and asks for SCHED_FIFO as configured; what was granted."""
    granted = {"cpu": None, "scheduler": "SCHED_OTHER", "error": ""}
    if config.cpu >= 0:
        try:
            os.sched_setaffinity(0, {config.cpu})
            granted["cpu"] = config.cpu
        except OSError as error:
            granted["error"] += f"cpu {config.cpu}: {error.strerror}; "
    if config.priority > 0:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(config.priority))
            granted["scheduler"] = f"SCHED_FIFO {config.priority}"
        except (OSError, AttributeError) as error:
            granted["error"] += f"SCHED_FIFO: {getattr(error, 'strerror', error)}; "
    return granted


@contextlib.contextmanager
def garbage_collector_frozen(freeze: bool = True) -> Iterator[None]:
    """Within it, Python's garbage collector does not run (the objects of start-up
    collected and frozen first): a collection of a process that imported Drake takes
    tens of ms, more than a period. Everything the same without `freeze`."""
    if freeze:
        gc.collect()
        gc.freeze()
        gc.disable()
    try:
        yield
    finally:
        if freeze:
            gc.enable()
            gc.unfreeze()


def check_time(value, name: str) -> None:
    """Raises ValueError naming `name` unless `value` is a time: finite, > 0 (s)."""
    if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
        raise ValueError(f"{name}: {value!r} must be a finite number > 0 (s)")

