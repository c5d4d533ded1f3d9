"""Scale-out on Ray: independent jobs (sweep points, dataset render shards) as Ray tasks.

Ray is an optional dependency (``pip install -e ".[ray]"``; ``make test`` installs it). Nothing
here runs unless asked: ``jprt sweep --ray`` or the environment variable ``JPRT_RAY_ADDRESS``:

* ``JPRT_RAY_ADDRESS=auto`` (or ``host:port``): join a running cluster (``ray start --head`` on one
  machine, ``ray start --address=host:port`` on the others);
* ``--ray`` without the variable: a local Ray instance on this machine's cores (no dashboard).

Dataset renders are sharded two ways: ``jprt.render.dataset.render_dataset`` renders its (view,
lighting) entries in shards, and the lightmap methods render blocks (``map_blocks``): data-driven
PRT its lighting configurations, SH PRT its SH functions, each block seeded by its own index.

Tasks write only content-addressed, atomic, checksummed entries (``jprt.cache``) or their own
report folders, so a cluster fills the same cache a laptop would, and a retried task (a worker
that died) rewrites the same files. On a cluster, point ``JPRT_CACHE`` of every node at one shared
folder. A worker that dies is retried (``max_retries``); an exception raised by the job itself is
returned to the caller, not retried. One model's training stays in one process (JAX device
sharding is the way to spread that).
"""

from __future__ import annotations

import os
from typing import Any, Callable, Sequence

__all__ = ["requested", "connect", "map_tasks", "map_blocks"]


def requested(flag: bool | None = None) -> bool:
    """Whether to use Ray: ``flag`` when given, else whether ``JPRT_RAY_ADDRESS`` is set."""
    return bool(os.environ.get("JPRT_RAY_ADDRESS")) if flag is None else bool(flag)


def connect(address: str | None = None, *, num_cpus: int | None = None):
    """The ``ray`` module, connected: to ``address`` / ``$JPRT_RAY_ADDRESS`` when given, else a
    local instance with ``num_cpus`` CPUs (default one per core) that inherits the ``JPRT_*`` and
    ``DRJIT_*`` environment; reused when this process is already connected."""
    try:
        import ray
    except ImportError as e:  # an optional extra: say how to get it
        raise RuntimeError('Ray is not installed: pip install -e ".[ray]" (make test installs it)') from e
    if ray.is_initialized():
        return ray
    address = address or os.environ.get("JPRT_RAY_ADDRESS") or None
    if address in (None, "", "local"):
        ray.init(num_cpus=num_cpus or os.cpu_count(), include_dashboard=False, log_to_driver=False,
                 runtime_env={"env_vars": {k: v for k, v in os.environ.items() if k.startswith(("JPRT_", "DRJIT_"))}})
    else:
        ray.init(address=address, log_to_driver=False)
    return ray


def map_tasks(fn: Callable, args: Sequence[tuple], *, num_cpus: float = 1, num_gpus: float = 0,
              max_retries: int = 3, on_done: Callable[[int, Any], None] | None = None) -> list:
    """``[fn(*a) for a in args]`` as Ray tasks (each needing ``num_cpus`` / ``num_gpus``), results
    in the order of ``args``; ``on_done(index, result)`` is called as each one finishes. A task
    whose worker dies is retried up to ``max_retries`` times; ``fn``'s own exceptions propagate."""
    ray = connect()
    remote = ray.remote(num_cpus=num_cpus, num_gpus=num_gpus, max_retries=int(max_retries))(fn)
    refs = [remote.remote(*a) for a in args]
    index = {ref: i for i, ref in enumerate(refs)}
    results: list = [None] * len(refs)
    pending = list(refs)
    while pending:
        done, pending = ray.wait(pending, num_returns=1)
        i = index[done[0]]
        results[i] = ray.get(done[0])
        if on_done is not None:
            on_done(i, results[i])
    return results


def map_blocks(fn: Callable, args: Sequence[tuple], *, ray: bool | None = None, desc: str = "blocks",
               progress: bool | None = None) -> list:
    """``[fn(*a) for a in args]``, in order, with a progress bar over the blocks: as Ray tasks of
    one CPU each when Ray is ``requested(ray)``, else in this process. ``fn`` is a module-level
    function (Ray pickles it by reference) whose result depends only on its arguments (seeds
    included), so both ways give the same arrays (up to Mitsuba's float rounding across processes)."""
    from jprt.progress import bar as progress_bar

    bar = progress_bar(total=len(args), progress=progress, desc=desc, unit="block")
    if requested(ray) and args:
        out = map_tasks(fn, args, on_done=lambda i, r: bar.update(1))
    else:
        out = []
        for a in args:
            out.append(fn(*a))
            bar.update(1)
    bar.close()
    return out
