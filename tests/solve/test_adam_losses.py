"""Adam loop (bit-identical resume, logs) and losses."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from jprt.nn import mlp
from jprt.solve import adam, losses

NET = mlp((2, 16, 1), activation="relu", init="he")


def sampler(key, step):
    x = jax.random.uniform(key, (32, 2), minval=-1, maxval=1)
    return {"x": x, "y": jnp.sin(3 * x[:, :1]) * x[:, 1:]}


def loss_fn(params, batch):
    return losses.mse(NET.apply(params, batch["x"]), batch["y"])


def test_resume_at_step_50_of_100_is_bit_identical(tmp_path):
    params = NET.init(jax.random.PRNGKey(0))
    key = jax.random.PRNGKey(1)
    schedule = optax.cosine_decay_schedule(1e-2, 100)
    full = adam.train(loss_fn, params, sampler, key=key, steps=100, learning_rate=schedule, progress=False)
    ckpt = str(tmp_path / "ckpt.npz")
    first = adam.train(loss_fn, params, sampler, key=key, steps=100, learning_rate=schedule, checkpoint_path=ckpt,
                       checkpoint_every=25, stop_after=50, progress=False)
    assert int(first.state.step) == 50
    resumed = adam.train(loss_fn, params, sampler, key=key, steps=100, learning_rate=schedule, checkpoint_path=ckpt,
                         checkpoint_every=25, progress=False, log_path=str(tmp_path / "logs" / "metrics.jsonl"),
                         log_every=10)
    assert resumed.resumed_from == 50 and int(resumed.state.step) == 100
    jax.tree_util.tree_map(lambda a, b: np.testing.assert_array_equal(np.asarray(a), np.asarray(b)),
                           full.state.params, resumed.state.params)
    np.testing.assert_array_equal(np.concatenate([first.losses, resumed.losses]), full.losses)
    lines = [json.loads(line) for line in open(tmp_path / "logs" / "metrics.jsonl")]  # folder created
    assert [line["step"] for line in lines] == [60, 70, 80, 90, 100]
    assert all(line["samples_per_s"] > 0 for line in lines)
    assert full.losses[-10:].mean() < full.losses[:10].mean()


def test_ema_is_the_moving_average_of_the_iterates_and_resumes_bit_identically(tmp_path):
    """state.ema follows ema <- d ema + (1 - d) params after every step from ema_0 = params_0,
    and a run interrupted after step 3 of 5 ends with the same average to the bit."""
    params = NET.init(jax.random.PRNGKey(0))
    key, d = jax.random.PRNGKey(1), 0.75
    ckpt = str(tmp_path / "steps.npz")
    iterates, ema = [], params
    for step in range(1, 6):  # one step per call, resumed from the checkpoint of the one before
        r = adam.train(loss_fn, params, sampler, key=key, steps=5, learning_rate=1e-2, checkpoint_path=ckpt,
                       stop_after=1, progress=False, ema_decay=d)
        assert int(r.state.step) == step
        iterates.append(r.state.params)
        ema = jax.tree_util.tree_map(lambda a, p: d * a + (1 - d) * p, ema, r.state.params)
    full = adam.train(loss_fn, params, sampler, key=key, steps=5, learning_rate=1e-2, progress=False, ema_decay=d)
    jax.tree_util.tree_map(lambda a, b: np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-7),
                           full.state.ema, ema)
    jax.tree_util.tree_map(lambda a, b: np.testing.assert_array_equal(np.asarray(a), np.asarray(b)),
                           full.state.params, iterates[-1])
    # the average is not the last iterate (it lags it)
    assert not np.allclose(np.asarray(full.state.ema["layers"][0]["w"]), np.asarray(full.state.params["layers"][0]["w"]))
    ckpt2 = str(tmp_path / "half.npz")
    adam.train(loss_fn, params, sampler, key=key, steps=5, learning_rate=1e-2, checkpoint_path=ckpt2, stop_after=3,
               progress=False, ema_decay=d)
    resumed = adam.train(loss_fn, params, sampler, key=key, steps=5, learning_rate=1e-2, checkpoint_path=ckpt2,
                         progress=False, ema_decay=d)
    jax.tree_util.tree_map(lambda a, b: np.testing.assert_array_equal(np.asarray(a), np.asarray(b)),
                           full.state.ema, resumed.state.ema)
    assert adam.train(loss_fn, params, sampler, key=key, steps=2, progress=False).state.ema is None
    with pytest.raises(ValueError, match="ema_decay"):
        adam.train(loss_fn, params, sampler, key=key, steps=2, progress=False, ema_decay=1.0)


def test_mu_law_sign_extension():
    x = jnp.array([-10.0, -1.0, -1e-3, 0.0, 1e-3, 1.0, 10.0])
    tm = losses.mu_law(x)
    np.testing.assert_allclose(tm, -tm[::-1], atol=1e-7)  # odd function: negatives are handled
    assert float(tm[3]) == 0.0 and float(losses.mu_law(1.0)) == pytest.approx(1.0)
    assert bool(jnp.all(jnp.diff(tm) > 0))
    # A negative prediction of a positive target is penalised more than zero is.
    assert float(losses.mu_law_l2(jnp.array([-0.5]), jnp.array([0.5]))) > float(
        losses.mu_law_l2(jnp.array([0.0]), jnp.array([0.5])))
    g = jax.grad(lambda p: losses.mu_law_l2(p, jnp.array([1.0, 2.0])))(jnp.array([-1.0, 0.5]))
    assert bool(jnp.all(jnp.isfinite(g)))


def test_other_losses():
    p, t = jnp.array([1.0, 2.0, 4.0]), jnp.array([1.0, 3.0, 3.0])
    assert float(losses.mse(p, t)) == pytest.approx(2 / 3)
    assert float(losses.relative_l2(p, t)) == pytest.approx(2 / 19)
    assert float(losses.log_l2(jnp.array([np.e - 1]), jnp.array([0.0]))) == pytest.approx(1.0, rel=1e-6)
    assert float(losses.log_l2(jnp.array([-5.0]), jnp.array([0.0]))) == 0.0  # clamped at 0
