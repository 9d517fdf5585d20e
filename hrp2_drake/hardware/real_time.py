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

    def validate(self, where: str = "RealTimeConfig") -> None:
        """Raises ValueError naming `where`.<field> for what the machine cannot grant:
        a CPU this process may not run on (`os.sched_getaffinity`), a SCHED_FIFO
        priority out of its range (`os.sched_get_priority_min/max`)."""
        cpus = sorted(_available_cpus())
        if not _is_int(self.cpu) or not (self.cpu == -1 or self.cpu in cpus):
            raise ValueError(
                f"{where}.cpu: {self.cpu!r} is not a CPU this machine gives the "
                f"process ({_ranges(cpus)}; -1: no pinning)"
            )
        low, high = _fifo_priorities()
        if not _is_int(self.priority) or not (
            self.priority == 0 or low <= self.priority <= high
        ):
            raise ValueError(
                f"{where}.priority: {self.priority!r} is out of SCHED_FIFO's range "
                f"{low}..{high} (0: the normal scheduler)"
            )


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _available_cpus() -> set[int]:
    """The CPUs this process may be pinned to."""
    if hasattr(os, "sched_getaffinity"):
        return set(os.sched_getaffinity(0))
    return set(range(os.cpu_count() or 1))


def _fifo_priorities() -> tuple[int, int]:
    """SCHED_FIFO's priority range on this system (Linux: 1..99)."""
    if hasattr(os, "SCHED_FIFO"):
        return (
            os.sched_get_priority_min(os.SCHED_FIFO),
            os.sched_get_priority_max(os.SCHED_FIFO),
        )
    return 1, 99


def _ranges(numbers: list[int]) -> str:
    """CPUs [0, 1, 2, 5] as "CPUs 0-2, 5"."""
    runs: list[list[int]] = []
    for n in numbers:
        if runs and n == runs[-1][1] + 1:
            runs[-1][1] = n
        else:
            runs.append([n, n])
    text = ", ".join(f"{a}-{b}" if b > a else f"{a}" for a, b in runs)
    return f"CPU{'s' if len(numbers) > 1 else ''} {text}"


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
