"""A jit-compiled Adam (optax) training loop with bit-identical checkpoint resume.

    result = train(loss_fn, params, sampler, key=key, steps=10_000, learning_rate=schedule,
                   checkpoint_path="run/ckpt.npz", checkpoint_every=500, log_path="run/metrics.jsonl")

* ``sampler(key, step) -> batch`` draws a minibatch; ``loss_fn(params, batch) -> scalar``. With
  ``data=`` (a pytree of arrays, e.g. a whole training set) the sampler is called as
  ``sampler(key, step, data)`` and ``data`` is passed to the jitted step as an argument instead
  of being baked into the compiled program as constants.
* The key of step t is ``fold_in(key, t)``, so a run resumed from the checkpoint of step t draws
  exactly the batches an uninterrupted run would: parameters, optimiser state and key are saved
  bit-exactly (``jprt.checkpoint.save_checkpoint``, atomic), and the resumed run is bit-identical.
* ``ema_decay`` > 0 also keeps an exponential moving average of the parameters (Polyak
  averaging, ema <- d ema + (1 - d) params after every step, saved and resumed with the rest):
  the average over the last ~1 / (1 - d) steps is less noisy than the last iterate, so it moves
  less with minibatch noise and with the last-bit differences another machine's code makes.
* A progress bar (``jprt.progress``) shows the loss and samples/s; every ``log_every`` steps a JSON line
  {"step", "loss", "samples_per_s", "lr", "elapsed_s"} is appended to ``log_path``.
"""

from __future__ import annotations

import json
import os
import time
import warnings
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jprt.progress import bar as progress_bar

__all__ = ["TrainState", "TrainResult", "train"]


class TrainState(NamedTuple):
    """Everything a resumed run needs.

    Fields:
      params:    the model parameters (pytree).
      opt_state: optax Adam state (pytree).
      step:      () int32, number of completed steps.
      ema:       the parameters' exponential moving average (pytree like params), or None when
                 ``train(ema_decay=0)``.
    """

    params: Any
    opt_state: Any
    step: jax.Array
    ema: Any = None


class TrainResult(NamedTuple):
    """``state`` after the last step, ``losses`` (steps run by this call,), ``resumed_from`` step."""

    state: TrainState
    losses: np.ndarray
    resumed_from: int


def _batch_size(batch) -> int:
    leaves = jax.tree_util.tree_leaves(batch)
    return int(leaves[0].shape[0]) if leaves and getattr(leaves[0], "ndim", 0) else 1


def train(loss_fn: Callable, params, sampler: Callable, *, key, steps: int, learning_rate=1e-3,
          b1: float = 0.9, b2: float = 0.99, eps: float = 1e-15, checkpoint_path: str | None = None,
          checkpoint_every: int = 1000, log_path: str | None = None, log_every: int = 50, progress: bool | None = None,
          stop_after: int | None = None, data=None, ema_decay: float = 0.0) -> TrainResult:
    """Run Adam for ``steps`` steps from ``params`` (or from ``checkpoint_path`` if it exists).

    Args:
      learning_rate: a float or an optax schedule (step -> lr).
      b1, b2, eps: Adam constants (defaults as Müller et al. 2022 / Raghavan et al. 2023).
      stop_after: stop (and checkpoint) after this many steps of this call, as an interruption
        would; the run can be resumed later (tests use it).
      data: optional pytree handed to ``sampler`` as its third argument (see the module docstring).
      ema_decay: d in [0, 1): 0 keeps no average (``state.ema`` is None); otherwise
        ``state.ema`` is the parameters' moving average, started at ``params``.
      progress: show the bar (``jprt.progress``; None: its policy, ``$JPRT_PROGRESS`` or
        whether stderr is a terminal).
    """
    import optax

    from jprt.checkpoint import CorruptCheckpoint, load_checkpoint, save_checkpoint

    if steps < 0:
        raise ValueError(f"steps must be >= 0, got {steps}")
    if not 0.0 <= ema_decay < 1.0:
        raise ValueError(f"ema_decay must be in [0, 1), got {ema_decay}")
    optimizer = optax.adam(learning_rate, b1=b1, b2=b2, eps=eps)
    ema0 = jax.tree_util.tree_map(jnp.asarray, params) if ema_decay > 0 else None
    state = TrainState(params, optimizer.init(params), jnp.zeros((), jnp.int32), ema0)
    resumed_from = 0
    if checkpoint_path and os.path.exists(checkpoint_path):
        try:
            loaded, _, _ = load_checkpoint(checkpoint_path, like=state)
        except CorruptCheckpoint as e:
            # detected (truncated or bit-flipped), kept aside for inspection, and rebuilt: training
            # starts over rather than from damaged state
            os.replace(checkpoint_path, checkpoint_path + ".corrupt")
            warnings.warn(f"{e}; moved to {checkpoint_path}.corrupt, training from step 0", stacklevel=2)
        else:
            state = TrainState(*loaded)
            resumed_from = int(state.step)

    @jax.jit
    def step_fn(state: TrainState, data):
        args = (jax.random.fold_in(key, state.step), state.step) + (() if data is None else (data,))
        batch = sampler(*args)
        loss, grads = jax.value_and_grad(loss_fn)(state.params, batch)
        updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        ema = None if state.ema is None else jax.tree_util.tree_map(
            lambda a, p: ema_decay * a + (1.0 - ema_decay) * p, state.ema, params)
        return TrainState(params, opt_state, state.step + 1, ema), loss

    def lr_at(step):
        return float(learning_rate(step)) if callable(learning_rate) else float(learning_rate)

    probe = (key, jnp.zeros((), jnp.int32)) + (() if data is None else (data,))
    batch_size = _batch_size(jax.eval_shape(sampler, *probe))
    todo = max(0, steps - resumed_from)
    if stop_after is not None:
        todo = min(todo, stop_after)
    losses = np.empty((todo,), np.float32)
    if log_path:
        os.makedirs(os.path.dirname(os.path.abspath(log_path)), exist_ok=True)
    log = open(log_path, "a") if log_path else None
    bar = progress_bar(total=steps, progress=progress, initial=resumed_from, desc="adam", unit="step",
                       dynamic_ncols=True)
    t0 = last_t = time.perf_counter()
    last_step = resumed_from
    try:
        for i in range(todo):
            state, loss = step_fn(state, data)
            losses[i] = loss
            step = resumed_from + i + 1
            bar.update(1)
            if step % log_every == 0 or i == todo - 1:
                now = time.perf_counter()
                rate = (step - last_step) * batch_size / max(now - last_t, 1e-9)
                bar.set_postfix(loss=f"{float(loss):.4g}", samples_per_s=f"{rate:.3g}")
                if log:
                    log.write(json.dumps({"step": step, "loss": float(loss), "samples_per_s": rate,
                                          "lr": lr_at(step - 1), "elapsed_s": now - t0}) + "\n")
                    log.flush()
                last_t, last_step = now, step
            if checkpoint_path and (step % checkpoint_every == 0 or i == todo - 1):
                save_checkpoint(checkpoint_path, state, step=step)
    finally:
        bar.close()
        if log:
            log.close()
    return TrainResult(state, losses, resumed_from)
