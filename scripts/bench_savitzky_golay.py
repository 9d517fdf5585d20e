"""Per-tick cost of SavitzkyGolayFilter's periodic update (microseconds).

Two measures per filter size, plus a baseline in the same run:
- "update": the discrete update alone (EvalUniquePeriodicDiscreteUpdate, then
  SetDiscreteState, as the simulator does), input fixed on the context;
- "simulated": a Simulator advancing a ConstantVectorSource -> filter diagram, per tick;
- "baseline ... noop": the same simulation with a Python LeafSystem whose periodic
  update does nothing, i.e. the framework's own per-tick cost (use it for ratios).

Run: .venv/bin/python scripts/bench_savitzky_golay.py
"""

from __future__ import annotations

import time

import numpy as np
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, LeafSystem
from pydrake.systems.primitives import ConstantVectorSource

from hrp2_drake.estimation.savitzky_golay import SavitzkyGolayFilter

PERIOD = 1e-3  # s
WINDOW = 80  # samples (paper, Sec. 5.1)


class _NoopPeriodicSystem(LeafSystem):
    """signal (k) -> a periodic discrete update that only reads its input."""

    def __init__(self, num_signals: int):
        super().__init__()
        self._signal = self.DeclareVectorInputPort("signal", num_signals)
        self._state = self.DeclareDiscreteState(num_signals)
        self.DeclareStateOutputPort("value", self._state)
        self.DeclarePeriodicDiscreteUpdateEvent(PERIOD, 0.0, self._update)

    def _update(self, context, discrete_state):
        self._signal.Eval(context)


def _signal(num_signals: int) -> np.ndarray:
    return np.linspace(-1.0, 1.0, num_signals)


def _us_per_update(system: SavitzkyGolayFilter, num_ticks: int) -> float:
    context = system.CreateDefaultContext()
    system.get_input_port().FixValue(context, _signal(system.num_signals()))
    start = time.perf_counter()
    for tick in range(num_ticks):
        context.SetTime(tick * PERIOD)
        context.SetDiscreteState(system.EvalUniquePeriodicDiscreteUpdate(context))
    return (time.perf_counter() - start) / num_ticks * 1e6


def _us_per_simulated_tick(system: LeafSystem, num_ticks: int) -> float:
    builder = DiagramBuilder()
    k = system.get_input_port().size()
    source = builder.AddSystem(ConstantVectorSource(_signal(k)))
    builder.AddSystem(system)
    builder.Connect(source.get_output_port(), system.get_input_port())
    simulator = Simulator(builder.Build())
    simulator.Initialize()
    start = time.perf_counter()
    simulator.AdvanceTo(num_ticks * PERIOD)
    return (time.perf_counter() - start) / num_ticks * 1e6


def bench_savitzky_golay(
    num_signals_list=(30, 66), num_ticks: int = 3000
) -> list[dict]:
    """Measures the filter for each k in num_signals_list, orders 2 and 1, N = 80.

    k = 30 is HRP-2's joint encoders (order 2) or one IMU + four F/T sensors
    (3 + 3 + 4 * 6, order 1). Returns rows {"name", "us_per_tick"}.
    """
    rows = []
    for k in num_signals_list:
        rows.append(
            {
                "name": f"baseline noop periodic LeafSystem k={k} (simulated)",
                "us_per_tick": _us_per_simulated_tick(
                    _NoopPeriodicSystem(k), num_ticks
                ),
            }
        )
        for order in (2, 1):
            label = f"SavitzkyGolayFilter k={k} order={order} window={WINDOW}"
            make = lambda k=k, order=order: SavitzkyGolayFilter(  # noqa: E731
                k, WINDOW, order, PERIOD
            )
            rows.append(
                {
                    "name": f"{label} (update)",
                    "us_per_tick": _us_per_update(make(), num_ticks),
                }
            )
            rows.append(
                {
                    "name": f"{label} (simulated)",
                    "us_per_tick": _us_per_simulated_tick(make(), num_ticks),
                }
            )
    return rows


if __name__ == "__main__":
    for row in bench_savitzky_golay():
        print(f"{row['us_per_tick']:9.2f} us/tick  {row['name']}")
