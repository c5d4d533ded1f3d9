"""The one progress policy (``jprt.progress``): a call's ``progress=`` wins, else
``$JPRT_PROGRESS``, else whether stderr is a terminal; and every method's fit and dataset
follow it (no method turns its bars off on its own)."""

import inspect
import io
import sys

import pytest

from jprt import progress
from jprt.methods import REGISTRY


class _Terminal(io.StringIO):
    def isatty(self):
        return True


@pytest.mark.parametrize("value, expected", [("0", False), ("false", False), ("OFF", False), ("no", False),
                                             ("1", True), ("yes", True), ("on", True)])
def test_environment_decides_when_the_call_does_not(monkeypatch, value, expected):
    monkeypatch.setenv(progress.ENV, value)
    assert progress.enabled() is expected
    assert progress.enabled(True) is True and progress.enabled(False) is False  # the call wins


def test_unset_follows_the_terminal(monkeypatch):
    monkeypatch.delenv(progress.ENV, raising=False)
    monkeypatch.setattr(sys, "stderr", io.StringIO())
    assert progress.enabled() is False
    monkeypatch.setattr(sys, "stderr", _Terminal())
    assert progress.enabled() is True


def test_bar_and_say_are_silent_when_off(monkeypatch):
    monkeypatch.setenv(progress.ENV, "0")
    err = io.StringIO()
    monkeypatch.setattr(sys, "stderr", err)
    assert list(progress.bar(range(3), desc="x")) == [0, 1, 2]
    b = progress.bar(total=2)
    b.update(2)
    b.close()
    progress.say("label")("hello")
    assert err.getvalue() == ""
    progress.say("label", True)("hello")
    assert err.getvalue() == "label: hello\n"


@pytest.mark.parametrize("name", sorted(REGISTRY))
def test_methods_leave_progress_to_the_policy(name):
    """A method's fit and make_dataset default ``progress`` to None (the policy), never to a
    fixed on or off of their own."""
    m = REGISTRY[name]
    for fn in (m.fit, m.make_dataset):
        assert not hasattr(fn, "keywords"), f"{name}: {fn} is a partial fixing its own arguments"
        parameter = inspect.signature(fn).parameters.get("progress")
        if parameter is not None:
            assert parameter.default is None, f"{name}: {fn.__qualname__}(progress={parameter.default!r})"
    for config in (m.resolve(), *(m.resolve(preset) for preset in m.presets.values())):
        assert config.get("train", {}).get("progress") is None, f"{name}: a config that fixes train.progress"
