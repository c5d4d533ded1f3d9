"""The work the fault tests (``test_kill_and_resume.py``) kill with SIGKILL and restart, run as
``python -m tests.faults.worker KIND ARGS``:

* ``render CACHE [DELAY]``: the dataset of ``tests/render/test_dataset.py`` with more views and
  lights (16 entries), sleeping DELAY seconds after each entry (a window to kill in);
* ``train CHECKPOINT OUT``: the tiny neural-wavelet model of ``tests/methods/test_wavelet_prt.py``
  trained by Adam with a checkpoint every 25 steps; its final params go to OUT and the run's
  ``resumed_from`` / ``step`` / number of losses to stdout as JSON;
* ``sweep OUT [DELAY]``: the fake method's 2 x 2 sweep of ``tests/test_sweep.py`` into OUT,
  sleeping DELAY seconds after each point; prints its counts;
* ``lm CHECKPOINT_DIR OUT``: an RRF kd-tree fit by LM (the step target of
  ``tests/methods/test_rrf.py``, 500 samples, depth 2: three batches of node fits) checkpointing
  each batch of node fits; params to OUT, the checkpoint counts to stdout;
* ``render-limited CACHE LIMIT``: ``render`` under a file-size limit of LIMIT bytes (set here, in
  the worker: a fork of the multithreaded test process to set it could deadlock).
"""

import json
import sys
import time


def render(cache: str, delay: float = 0.0):
    from jprt.render import cameras
    from jprt.render.dataset import render_dataset
    from jprt.render.lights import PointLights
    from jprt.render.scenes import cornell_box

    views = [cameras.look_at((x, 0, 3.9), (0, 0, 0), width=8, height=8) for x in (-0.3, -0.1, 0.1, 0.3)]
    lights = [PointLights.create([x, 0.6, 0], [2, 2, 2]) for x in (-0.3, -0.1, 0.1, 0.3)]
    ds = render_dataset(cornell_box(area_light=False), views, lights, spp=4, seed=7, cache_dir=cache, progress=False,
                        on_entry=(lambda name: time.sleep(delay)) if delay else None)
    print(json.dumps(ds.stats))
    return ds


TRAIN = {"steps": 120, "checkpoint_every": 10, "log_every": 10}


def train(checkpoint: str, out: str):
    from jprt import io
    from jprt.methods.wavelet_prt import model as wp
    from tests.methods.test_wavelet_prt import TINY, _fake_data

    cfg = dict(TINY, train=dict(TINY["train"], **TRAIN))
    result = wp.fit(_fake_data(n=4), cfg, checkpoint_path=checkpoint, progress=False)
    io.save_checkpoint(out, result.params)
    print(json.dumps({"resumed_from": result.info.get("resumed_from", 0), "step": result.info["step"],
                      "losses": len(result.info["losses"])}))
    return result


LM_CONFIG = {"model": {"hidden": [3]}, "tree": {"min_samples": 40, "max_depth": 2, "threshold": 0.01, "expand": 0.0},
             "train": {"max_iters": 15, "trial_iters": 15, "progress": False}}


def lm(checkpoint_dir, out: str):
    import numpy as np

    from jprt import io
    from jprt.methods.rrf import model as rrf

    rng = np.random.default_rng(0)
    x = rng.random((500, 2)).astype(np.float32)
    y = (1 + 0.3 * x[:, 0] + 0.2 * x[:, 1] + np.where(x[:, 0] < 0.3, 0.0, 1.0))[:, None]
    params, info = rrf.fit_arrays(x, y, np.zeros(len(x), np.int32), LM_CONFIG, checkpoint_dir=checkpoint_dir)
    io.save_checkpoint(out, params)
    print(json.dumps({k: v for k, v in info.get("checkpoint", {}).items() if k != "folder"}))
    return params, info


GRID = {"model.bias": [0.0, 0.02], "data.n": [2, 3]}


def sweep(out: str, delay: float = 0.0):
    import os
    import types

    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    import fake_method

    from jprt import runner
    from jprt import sweep as jsweep
    from jprt.methods import REGISTRY

    REGISTRY.setdefault("fake", fake_method.make_fake_method())
    experiment = types.SimpleNamespace(METHOD="fake", CONFIG=fake_method.config(out), held_out=fake_method.held_out,
                                       pathtracer=fake_method.pathtracer)

    def slow(module, cfg):
        summary = runner.run(module, cfg)
        time.sleep(delay)
        return summary

    record = jsweep.run_sweep(experiment, experiment.CONFIG, GRID, run=slow, progress=False)
    print(json.dumps(record["counts"]))
    return record


if __name__ == "__main__":
    kind, *args = sys.argv[1:]
    if kind == "render":
        render(args[0], float(args[1]) if len(args) > 1 else 0.0)
    elif kind == "lm":
        lm(*args)
    elif kind == "sweep":
        sweep(args[0], float(args[1]) if len(args) > 1 else 0.0)
    elif kind == "render-limited":
        import resource
        import signal

        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit then fails with EFBIG
        resource.setrlimit(resource.RLIMIT_FSIZE, (int(args[1]), int(args[1])))
        render(args[0])
    elif kind == "train":
        train(*args)
    else:
        raise SystemExit(f"unknown work {kind!r}")
