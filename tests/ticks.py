"""Drive one of the chain's LeafSystems tick by tick, as the station's sampler does,
without a Simulator: the timing rule of `hrp2_drake.step` made explicit for tests.

Tick k: the inputs hold sample k (fixed on the context), the context's time is
k·period, the outputs are the tick of sample k (direct feedthrough); then the commit
at (k + 1)·period, the next sampling instant, stores that tick as the system's state.
"""

from collections.abc import Callable, Sequence

import numpy as np
from pydrake.systems.framework import Context, InputPort, System


def run_ticks(
    system: System,
    context: Context,
    inputs: dict[InputPort, Sequence[np.ndarray]],
    period: float,
    each: Callable[[int, Context], None] | None = None,
    t0: float = 0.0,
    initialize: bool = True,
) -> Context:
    """Runs len(samples) ticks of `system` (its context `context`): before tick k each
    port of `inputs` holds its sample k; `each(k, context)` reads the outputs of tick
    k; then the tick is committed (the system's unique periodic update, at the next
    sampling instant). With `initialize`, the initialization events run first, on
    sample 0 at t0. Returns `context`."""
    count = len(next(iter(inputs.values()))) if inputs else 0
    for k in range(count):
        for port, samples in inputs.items():
            port.FixValue(context, np.asarray(samples[k], float))
        context.SetTime(t0 + k * period)
        if k == 0 and initialize:
            system.ExecuteInitializationEvents(context)
        if each is not None:
            each(k, context)
        commit(system, context, t0 + (k + 1) * period)
    return context


def commit(system: System, context: Context, t: float) -> None:
    """The commit at the sampling instant t: the tick of the sample now held becomes
    the system's state, t the time of the next sample."""
    context.SetTime(t)
    context.SetDiscreteState(system.EvalUniquePeriodicDiscreteUpdate(context))
