"""hrp2_drake.simulation: the shared logger (one sink for every named port) logs what a
sink per port logs, and WitnessFreeLeafSystem leaves witness functions to the
subclasses that have them."""

from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, WitnessFunctionDirection
from pydrake.systems.primitives import Sine, VectorLogSink

from hrp2_drake.simulation import WitnessFreeLeafSystem, add_loggers, logs_to_arrays


def test_shared_logger_logs_what_a_sink_per_port_logs():
    builder = DiagramBuilder()
    sources = {
        "a": builder.AddSystem(Sine([1.0, 2.0], [3.0, 5.0], [0.1, 0.2])),
        "b": builder.AddSystem(Sine([0.5], [7.0], [0.3])),
        "c": builder.AddSystem(Sine([1.0, 1.0, 1.0], [1.0, 2.0, 3.0], [0.0] * 3)),
    }
    ports = {name: source.get_output_port(0) for name, source in sources.items()}
    shared = add_loggers(builder, ports, 0.001)
    per_port = {}
    for name, port in ports.items():
        per_port[name] = builder.AddSystem(VectorLogSink(port.size(), 0.001))
        builder.Connect(port, per_port[name].get_input_port())
    simulator = Simulator(builder.Build())
    simulator.AdvanceTo(0.05)
    context = simulator.get_context()
    expected = logs_to_arrays(per_port, context)
    actual = logs_to_arrays(shared, context)
    assert actual.keys() == expected.keys() == {"t", "a", "b", "c"}
    for name in expected:
        assert actual[name].tobytes() == expected[name].tobytes(), name
    assert actual["a"].shape == (51, 2)


class _NoWitness(WitnessFreeLeafSystem):
    def __init__(self):
        super().__init__()
        self.DeclareContinuousState(1)


class _OneWitness(_NoWitness):
    """A subclass with a witness function: it overrides DoGetWitnessFunctions."""

    def __init__(self):
        super().__init__()
        self.witness = self.MakeWitnessFunction(
            "x_minus_one",
            WitnessFunctionDirection.kCrossesZero,
            lambda context: context.get_continuous_state_vector()[0] - 1.0,
        )

    def DoGetWitnessFunctions(self, context):
        return [self.witness]


def test_witness_free_systems_have_no_witness_and_subclasses_may_add_theirs():
    plain, witnessed = _NoWitness(), _OneWitness()
    assert plain.GetWitnessFunctions(plain.CreateDefaultContext()) == []
    assert len(witnessed.GetWitnessFunctions(witnessed.CreateDefaultContext())) == 1
    # In a diagram too (the simulator asks the diagram).
    builder = DiagramBuilder()
    builder.AddSystem(_NoWitness())
    builder.AddSystem(_OneWitness())
    diagram = builder.Build()
    assert len(diagram.GetWitnessFunctions(diagram.CreateDefaultContext())) == 1


def test_logged_arrays_are_copies_that_do_not_keep_the_simulation_alive():
    import gc
    import weakref

    builder = DiagramBuilder()
    sine = builder.AddSystem(Sine([1.0, 2.0], [3.0, 5.0], [0.1, 0.2]))
    loggers = add_loggers(builder, {"a": sine.get_output_port(0)}, 0.001)
    simulator = Simulator(builder.Build())
    simulator.AdvanceTo(0.05)
    arrays = logs_to_arrays(loggers, simulator.get_context())
    assert all(a.flags.owndata for a in arrays.values())
    # Views of the log kept the log, its context and the Simulator alive as long as
    # the arrays lived (a diagram of C++ systems only: pydrake frees it).
    alive = weakref.ref(simulator)
    del simulator, loggers
    gc.collect()
    assert alive() is None
    assert arrays["a"].shape == (51, 2)
