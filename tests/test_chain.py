"""The chain declared once (`hrp2_drake.chain`): a table's rule (one tick from sample
to command, loops only through held outputs) is enforced when it is made, and its two
shells, the Diagram and the fused plan, give the same signals tick by tick."""

from dataclasses import replace

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import TrajectorySource
from pydrake.trajectories import PiecewisePolynomial

from hrp2_drake.chain import (
    Chain,
    FusedChain,
    Row,
    Sum,
    add_chain,
    args,
    entries,
    whole,
)
from hrp2_drake.estimation.savitzky_golay import (
    SavitzkyGolayFilter,
    SavitzkyGolayFilterStep,
)
from hrp2_drake.simulation import SampleHold

PERIOD = 0.01


def _filter_row(name: str, size: int, source, held=frozenset()) -> Row:
    """A Savitzky-Golay filter (order 1, window 5) of `size` signals as a row."""
    return Row(
        name=name,
        system_name=name,
        make_step=lambda: SavitzkyGolayFilterStep(size, 5, 1, PERIOD, "end"),
        make_system=lambda: SavitzkyGolayFilter(size, 5, 1, PERIOD, "end"),
        inputs={"signal": source},
        arguments=args("signal"),
        outputs={
            "value": "value",
            "derivative": "derivative",
            "input_fault": "input_fault",
        },
        logged={f"{name}_value": whole(f"{name}/value")},
        held=held,
        initialize=args("signal"),
    )


def _table() -> Chain:
    """Three signals filtered; two of them (reordered) filtered again; the sum of
    the two filters' input faults logged."""
    first = _filter_row("first", 3, whole("station/x"))
    second = _filter_row("second", 2, entries("first/value", [2, 0], name="picked"))
    faults = Sum(("first/input_fault", "second/input_fault"), name="faults")
    second = replace(second, logged=second.logged | {"faults": faults})
    return Chain((first, second), None, {})


def test_a_row_that_reads_a_later_row_is_refused_unless_held():
    late = _filter_row("late", 2, whole("station/x"))
    early = _filter_row("early", 2, whole("late/value"))
    with pytest.raises(ValueError, match="'early'.*computed later in the tick"):
        Chain((early, late), None, {})
    held = _filter_row("late", 2, whole("station/x"), held=frozenset({"value"}))
    Chain((early, held), None, {})  # a loop through a held output: allowed


@pytest.mark.parametrize(
    "source, message",
    [
        (whole("nowhere/value"), "no row 'nowhere'"),
        (whole("first/nothing"), "row 'first' has no output 'nothing'"),
        (whole("reference/q_ref"), "unknown reference 'q_ref'"),
        (whole("first"), "is not '<scope>/<name>'"),
    ],
)
def test_a_source_that_names_nothing_is_one_clear_error(source, message):
    first = _filter_row("first", 3, whole("station/x"))
    with pytest.raises(ValueError, match=message):
        Chain((first, _filter_row("second", 3, source)), None, {})


def test_the_diagram_and_the_fused_plan_give_the_same_signals():
    chain = _table()
    times = np.arange(0.0, 0.5, PERIOD / 4)
    samples = np.vstack([np.sin(3 * times), np.cos(5 * times), times**2])
    signal = PiecewisePolynomial.FirstOrderHold(times, samples)

    builder = DiagramBuilder()
    # The station: the signal sampled every period (as a sensor sampler does).
    source = builder.AddSystem(TrajectorySource(signal))
    sampler = builder.AddSystem(SampleHold(3, PERIOD, 0.0, signal.value(0.0)[:, 0]))
    builder.Connect(source.get_output_port(), sampler.get_input_port())
    added = add_chain(builder, chain, {"station/x": sampler.get_output_port()})
    for name, port in added.logged.items():
        builder.ExportOutput(port, name)
    diagram = builder.Build()
    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()

    fused = FusedChain(chain, [("station/x", 3)], lambda *event: None)
    x = fused.view("station/x")
    x[:] = signal.value(0.0)[:, 0]
    fused.initialize(0.0)
    simulator.Initialize()
    for k in range(30):
        t = k * PERIOD
        x[:] = signal.value(t)[:, 0]
        fused.tick(t)
        # The Diagram shows sample k's tick until its updates at the next instant
        # (Drake updates at the start of a step): compare just before them, at the
        # float time of the next event (k·period, as Drake computes it).
        simulator.AdvanceTo((k + 1) * PERIOD)
        for name, source in chain.logged().items():
            rows = fused.logged_rows(source)
            expected = sum(fused.state[r] for r in rows)
            got = diagram.GetOutputPort(name).Eval(context)
            np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12, err_msg=name)
    # The selection is one Selector, the sum one Adder, in the Diagram.
    names = {system.get_name() for system in diagram.GetSystems()}
    assert {"picked", "faults"} <= names
