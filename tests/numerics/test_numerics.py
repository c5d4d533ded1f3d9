"""float32 against float64 for every public differentiable function (issue 20; the harness and
the docstring grammar are in ``harness.py``)."""

import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from . import cases
from .harness import Problem, check, draw_args, parse, public_functions

FUNCTIONS = public_functions()
SPECS = {name: parse(name, fn) for name, fn in FUNCTIONS if "Numerics:" in (fn.__doc__ or "")}
COVERED = sorted(name for name, spec in SPECS.items() if spec.exempt is None)


def test_every_public_function_states_its_numerics():
    """A public function of jprt.sphere, jprt.nn, jprt.solve.losses or a method's model.py joins
    only with a Numerics section: its domain and float32 tolerance, or why it is not
    differentiable (the list comes from introspection, not from this file)."""
    missing = [name for name, fn in FUNCTIONS if name not in SPECS]
    assert not missing, "no 'Numerics:' section in the docstring of:\n  " + "\n  ".join(missing)
    assert len(FUNCTIONS) > 100 and len(COVERED) > 40  # the modules are all found
    for name, spec in SPECS.items():
        if spec.case is not None:
            assert hasattr(cases, spec.case), f"{name}: no case {spec.case!r} in tests/numerics/cases.py"


@pytest.mark.parametrize("name", COVERED)
def test_float32_matches_float64(name):
    """Values and vector-Jacobian products in float32 within the function's stated tolerance
    of float64 at Hypothesis-drawn points of its stated domain (its ends always included),
    and the float64 gradient within 1e-4 of finite differences. One derandomised example per
    function, each a batch of 16-64 points: the cost is XLA compiling the two programs
    (~0.7 s a function), so points come in batches rather than in more examples."""
    spec = SPECS[name]

    @settings(max_examples=1, deadline=None, derandomize=True, database=None,
              suppress_health_check=list(HealthCheck), phases=(Phase.explicit, Phase.generate))
    @given(data=st.data(), seed=st.integers(0, 2**16))
    def inner(data, seed):
        if spec.case is not None:
            problem = getattr(cases, spec.case)(data.draw, spec)
        else:
            args = draw_args(data.draw, spec)
            grad = spec.grad or [a.name for a in spec.args if a.kind in ("float", "unit")]
            problem = Problem(spec.fn, args, grad)
        domains = {a.name: (a.lo, a.hi) for a in spec.args if a.kind == "float"}
        check(problem, spec, seed, domains)

    inner()
