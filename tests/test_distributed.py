"""Scale-out on a local Ray instance (2 CPUs, no dashboard): a sweep under Ray equals the
in-process sweep point for point, survives a worker that dies, and re-runs nothing; a dataset
rendered in Ray shards equals the single-process one."""

import os
import textwrap

import fake_method
import numpy as np
import pytest

from jprt import distributed, sweep
from jprt.experiment import load_experiment
from jprt.methods import REGISTRY

ray = pytest.importorskip("ray", reason="Ray is the optional [ray] extra (make test installs it)")


@pytest.fixture(scope="module")
def local_ray():
    distributed.connect(num_cpus=2)
    yield ray
    ray.shutdown()


@pytest.fixture
def experiment(monkeypatch, tmp_path):
    """A fake experiment file (workers load it by path); its point with model.bias == 0.01 kills
    its worker the first time it runs (``os._exit``), leaving a marker file."""
    monkeypatch.setitem(REGISTRY, "fake", fake_method.make_fake_method())
    marker = tmp_path / "crashed_once"
    path = tmp_path / "fake_experiment.py"
    path.write_text(textwrap.dedent(f"""
        import os
        import sys
        sys.path.insert(0, {os.path.dirname(os.path.abspath(fake_method.__file__))!r})
        import fake_method
        from fake_method import pathtracer
        from jprt.methods import REGISTRY

        REGISTRY.setdefault("fake", fake_method.make_fake_method())  # in the Ray workers
        METHOD = "fake"
        CONFIG = fake_method.config({str(tmp_path / "out")!r})


        def held_out(run):
            if run.method_config["model"]["bias"] == 0.01 and not os.path.exists({str(marker)!r}):
                open({str(marker)!r}, "w").close()
                os._exit(1)  # the worker dies mid-point
            return fake_method.held_out(run)
    """))
    return load_experiment(str(path)), marker


GRID = {"model.bias": [0.0, 0.02], "data.n": [2, 3]}
SAME = ("indirect_rmse", "indirect_rel_rmse", "psnr_indirect", "ssim_indirect", "psnr_full", "model_bytes",
        "equal_error_spp")


@pytest.mark.slow  # ~13 s; Ray still runs by default (the dataset-shard test below)
def test_sweep_on_ray_equals_the_in_process_sweep(local_ray, experiment, tmp_path, monkeypatch):
    module, _ = experiment
    local = sweep.run_sweep(module, module.CONFIG, GRID, progress=False, ray=False)
    config = {**module.CONFIG, "output": {"dir": str(tmp_path / "ray_out")}}
    on_ray = sweep.run_sweep(module, config, GRID, progress=False, ray=True)
    assert on_ray["counts"] == {"done": 4, "cached": 0, "failed": 0}
    for a, b in zip(local["rows"], on_ray["rows"]):
        assert {k: a[k] for k in GRID} == {k: b[k] for k in GRID}
        assert {k: a[k] for k in SAME} == {k: b[k] for k in SAME}

    def no_tasks(*args, **kwargs):
        raise AssertionError("a finished sweep submitted Ray tasks")

    monkeypatch.setattr(distributed, "map_tasks", no_tasks)
    again = sweep.run_sweep(module, config, GRID, progress=False, ray=True)
    assert again["counts"] == {"done": 0, "cached": 4, "failed": 0}  # nothing rendered or trained again


@pytest.mark.slow  # ~12 s with its Ray start; Ray itself still runs by default (the dataset-shard test)
def test_a_worker_that_dies_is_retried_and_nothing_is_duplicated(local_ray, experiment, tmp_path):
    module, marker = experiment
    grid = {"model.bias": [0.0, 0.01, 0.02, 0.03]}
    record = sweep.run_sweep(module, module.CONFIG, grid, progress=False, ray=True)
    assert marker.exists()  # the 0.01 point did kill its first worker
    assert record["counts"] == {"done": 4, "cached": 0, "failed": 0}
    assert [r["model.bias"] for r in record["rows"]] == grid["model.bias"]
    folders = [r["folder"] for r in record["rows"]]
    assert len(set(folders)) == 4 and all(os.path.isfile(os.path.join(f, "summary.json")) for f in folders)
    assert record["rows"][1]["indirect_rmse"] == pytest.approx(0.01, rel=1e-3)


@pytest.mark.mitsuba
def test_dataset_rendered_in_ray_shards_equals_the_single_process_one(local_ray, mi, tmp_path):
    from jprt.render import cameras
    from jprt.render.dataset import render_dataset
    from jprt.render.lights import PointLights

    cams = cameras.orbit((0, 0, 0), 3.9, 2, arc_deg=30, width=8, height=8)
    lights = [PointLights.create([0, 0.5, 0], [2, 2, 2]), PointLights.create([0.3, 0.6, -0.2], [1, 2, 3])]
    kwargs = dict(scene={"name": "cornell_box", "area_light": False}, cameras=cams, lightings=lights, spp=4,
                  progress=False)
    single = render_dataset(**kwargs, cache_dir=str(tmp_path / "single"), ray=False)
    sharded = render_dataset(**kwargs, cache_dir=str(tmp_path / "sharded"), ray=True, shards=3)
    assert sharded.stats["rendered"] == single.stats["rendered"] == 2 + 2 + 4  # lightings, G-buffers, items
    assert os.path.basename(single.folder) == os.path.basename(sharded.folder)  # same content address
    for c in range(2):
        for name, a in single.gbuffer(c)._asdict().items():
            np.testing.assert_array_equal(np.asarray(a), np.asarray(getattr(sharded.gbuffer(c), name)), err_msg=name)
    for k in range(len(single)):
        for field in ("direct", "indirect"):
            # same seeds; Mitsuba in another process: equal up to float32 rounding (identical when measured)
            np.testing.assert_allclose(sharded.radiance(k)[field], single.radiance(k)[field], rtol=1e-6, atol=1e-12)
    again = render_dataset(**kwargs, cache_dir=str(tmp_path / "sharded"), ray=True)
    assert again.stats == {"rendered": 0, "cached": 8, "corrupt": 0}


@pytest.mark.slow  # the shard test above covers the mechanism in the default suite
@pytest.mark.mitsuba
@pytest.mark.parametrize("name", ["datadriven", "sh_prt"])
def test_lightmap_method_rendered_in_ray_blocks_equals_the_single_process_one(local_ray, mi, tmp_path, name):
    """Data-driven PRT's configurations and SH PRT's SH functions as Ray tasks (``make_dataset(ray=True)``)."""
    m = REGISTRY[name]
    config = m.resolve(m.presets["test"])
    single = m.make_dataset(config["scene"], config, cache_dir=str(tmp_path / "single"), progress=False, ray=False)
    sharded = m.make_dataset(config["scene"], config, cache_dir=str(tmp_path / "ray"), progress=False, ray=True)
    fields = ("direct", "indirect", "direct_test", "indirect_test") if name == "datadriven" else ("transfer",)
    for field in fields:  # same seeds; Mitsuba in other processes: equal up to float32 rounding
        a, b = np.asarray(getattr(single, field)), np.asarray(getattr(sharded, field))
        assert a.shape == b.shape and np.abs(a).max() > 0, field
        np.testing.assert_allclose(b, a, rtol=1e-6, atol=1e-9, err_msg=field)
    np.testing.assert_array_equal(single.atlas["texel_index"], sharded.atlas["texel_index"])
