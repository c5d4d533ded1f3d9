"""The ``jprt`` command: ``info``, ``render`` (a dataset from an experiment config), ``run`` (an
experiment), ``sweep`` (a grid of overrides over an experiment, ``jprt.sweep``), ``atlas`` (every
method against Mitsuba on a built-in task or a scene file, ``jprt.atlas``), ``view`` (relight a
run in the browser, ``jprt.view``), ``export`` (a run folder as glTF lightmaps or ONNX for engines,
``jprt.export``), ``design`` (the lighting that meets an objective, found through a run's model and
checked with Mitsuba, ``jprt.design``).

    jprt info
    jprt render experiments/cornell_gt.py --set dataset.spp=16
    jprt run experiments/cornell_gt.py --set dataset.cameras.width=64
    jprt run experiments/rrf_cornell.py --config results/rrf_cornell/sweep_<hash>/selected.json
    jprt sweep experiments/datadriven.py --grid basis.n=[4,16,64] --select "indirect_rmse<=0.02" \
        --minimize frame_ms
    jprt atlas path/to/scene.xml --lighting point --select "indirect_rel_rmse<=0.3" --minimize frame_ms
    jprt export results/sh_prt/<hash> --out exports/sh_prt
    jprt design results/rrf_cornell/<hash> --objective objective.json --lights 2 --out design.json

An experiment file defines ``CONFIG`` (a nested dict) and ``METHOD`` (run by ``jprt.runner``) or
``main(config)``. ``--set a.b=value``
overrides are typed and deep-merged; an unknown key is an error naming the nearest valid key.
Errors in the input are reported as one line on stderr (exit status 2).
"""

from __future__ import annotations

import argparse
import importlib
import os
import platform
import sys

from jprt.experiment import load_experiment, resolve_config

__all__ = ["main", "load_experiment", "resolve_config"]


def _sweep(args) -> int:
    from jprt import sweep

    if not os.path.isfile(args.experiment):
        raise FileNotFoundError(f"experiment or sweep file not found: {args.experiment}")
    if sweep.is_sweep_file(args.experiment):
        spec = sweep.load_sweep_file(args.experiment)
        experiment, preset = spec["experiment"], args.preset or spec.get("preset")
        grid = {**spec["grid"], **sweep.parse_grid(args.grid)}
        overrides = list(spec.get("set", [])) + args.overrides
    else:
        experiment, preset, grid, overrides = args.experiment, args.preset, sweep.parse_grid(args.grid), args.overrides
    if not grid:
        raise ValueError("a sweep needs at least one --grid key=[values] (or a sweep file's SWEEP['grid'])")
    module = load_experiment(experiment)
    config = resolve_config(module, overrides, preset)
    record = sweep.run_sweep(module, config, grid, label=os.path.basename(experiment), ray=args.ray or None,
                             num_cpus=args.cpus, num_gpus=args.gpus)
    if args.select:
        if not args.minimize:
            raise ValueError("--select needs --minimize KEY (e.g. frame_ms)")
        row = sweep.select(record["rows"], args.select, args.minimize)
        chosen = sweep.selected_config(config, row, list(grid))
        path = os.path.join(record["folder"], "selected.json")
        from jprt.io import write_json

        write_json(path, {"experiment": os.path.abspath(experiment), "select": args.select,
                          "minimize": args.minimize, "point": {k: row[k] for k in grid},
                          "summary": {k: row.get(k) for k in sweep.ROW_KEYS}, "config": chosen})
        print(f"selected {({k: row[k] for k in grid})}: {args.minimize} = {row[args.minimize]}; "
              f"run it with: jprt run {experiment} --config {path}")
    return 0 if not record["counts"]["failed"] else 1


def _atlas(args) -> int:
    import json

    from jprt import atlas
    from jprt.config import apply_overrides

    if args.config_file:  # a selection (or any atlas config) run as it is
        if args.target:
            raise ValueError("give a task or scene file, or --config FILE, not both")
        with open(args.config_file) as f:
            loaded = json.load(f)
        config = apply_overrides(loaded.get("config", loaded), args.overrides)
    elif not args.target:
        raise ValueError(f"jprt atlas needs a task ({', '.join(atlas.TASKS)}) or a scene file, or --config FILE")
    else:
        config = atlas.atlas_config(args.target, args.lighting, args.preset, out=args.out, select=args.select or "",
                                    minimize=args.minimize, overrides=args.overrides)
    record = atlas.run_atlas(config)
    status = [m["status"] for t in record["tasks"].values() for m in t["methods"].values()]
    if "done" not in status:
        print("jprt atlas: no method ran (atlas.md says why each was not run)", file=sys.stderr)
    return 0 if "done" in status and "failed" not in status else 1


def _info() -> int:
    from jprt import __version__
    from jprt.render import setup

    lines = [f"jprt {__version__}", f"python {platform.python_version()} ({sys.executable})"]
    try:  # first, so DRJIT_LIBLLVM_PATH is set before anything imports drjit
        mi = setup.mitsuba()
        active = mi.variant()
    except Exception as e:
        active = f"unavailable ({e})"
    for mod in ("numpy", "jax", "jaxlib", "optax", "mitsuba", "drjit", "OpenEXR"):
        try:
            lines.append(f"{mod} {importlib.import_module(mod).__version__}")
        except Exception as e:  # report, don't crash: info is for diagnosing installs
            lines.append(f"{mod} unavailable ({type(e).__name__}: {e})")
    lines.append(f"mitsuba variant: {setup.variant()}")
    lib = setup.find_libllvm()
    lines.append(f"llvm library: {lib or 'NOT FOUND (' + setup.INSTALL_COMMAND + ')'}"
                 + (f" (LLVM {setup.llvm_major(lib)})" if lib else ""))
    lines.append(f"mitsuba active variant: {active}")
    try:
        import jax

        lines.append("jax devices: " + ", ".join(str(d) for d in jax.devices()))
    except Exception as e:
        lines.append(f"jax devices: unavailable ({e})")
    from jprt.cache import cache_root

    lines.append(f"cache: {cache_root()}")
    print("\n".join(lines))
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``jprt`` command; returns the exit status."""
    parser = argparse.ArgumentParser(prog="jprt", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("info", help="versions, Mitsuba variant, LLVM library, JAX devices")
    for name, help_text in (("render", "render the dataset of an experiment config"),
                            ("run", "run an experiment file (CONFIG + METHOD, or main)")):
        p = sub.add_parser(name, help=help_text)
        p.add_argument("experiment", help="path to an experiment .py file")
        p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                       help="override a config value (repeatable), e.g. --set dataset.spp=16")
        p.add_argument("--preset", default=None, help="a named config preset of the experiment (e.g. small, paper)")
        p.add_argument("--config", dest="config_file", default=None, metavar="FILE.json",
                       help="a JSON config merged before --set (e.g. a sweep's selected.json)")
    p = sub.add_parser("sweep", help="run a grid of config overrides (or a sweep file) through the runner")
    p.add_argument("experiment", help="an experiment .py file, or a sweep file experiments/sweeps/*.py")
    p.add_argument("--grid", action="append", default=[], metavar="KEY=[V1,V2]", help="a swept key (repeatable)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--preset", default=None)
    p.add_argument("--select", default=None, metavar="KEY>=VALUE[,...]",
                   help="pick the cheapest point meeting these constraints (writes selected.json)")
    p.add_argument("--minimize", default=None, metavar="KEY", help="what --select minimises, e.g. frame_ms")
    p.add_argument("--ray", action="store_true",
                   help="run the points as Ray tasks (a local instance, or $JPRT_RAY_ADDRESS=auto|host:port)")
    p.add_argument("--cpus", type=float, default=None,
                   help="CPUs one point needs on Ray (default: the config's resources.cpus, else 1)")
    p.add_argument("--gpus", type=float, default=None,
                   help="GPUs one point needs on Ray (default: the config's resources.gpus, else 0)")
    p = sub.add_parser("atlas", help="every method that takes the lighting against Mitsuba, on a task or scene file")
    p.add_argument("target", nargs="?", metavar="SCENE_OR_TASK",
                   help="a scene file (path/to/scene.xml) or a built-in task (local_lights, environment)")
    p.add_argument("--lighting", choices=("point", "env", "environment", "file"), default=None,
                   help="a scene file's lighting: point lights in its light region, held-out environment maps "
                        "through a ceiling opening, or its own emitters (default point)")
    p.add_argument("--select", default=None, metavar="KEY<=VALUE[,...]",
                   help="each method's cheapest point meeting these constraints (writes selected_<task>_<method>.json)")
    p.add_argument("--minimize", default="frame_ms", metavar="KEY", help="what --select minimises (default frame_ms)")
    p.add_argument("--preset", default=None, help="sizes: small (default) or test (seconds)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a value of the atlas config (tasks.<task>..., eval...)")
    p.add_argument("--out", default=None, help="output folder (default results/atlas/<task>)")
    p.add_argument("--config", dest="config_file", default=None, metavar="FILE.json",
                   help="run an atlas config as it is (a selected_<task>_<method>.json)")
    p = sub.add_parser("view", help="relight a trained model of a run folder interactively in the browser")
    p.add_argument("folder", help="a run folder written by `jprt run` (config.json, summary.json, model.npz)")
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default: localhost only)")
    p.add_argument("--port", type=int, default=8080)
    p.add_argument("--size", type=int, default=128, help="resolution of the refined frame (square)")
    p.add_argument("--preview", type=int, default=48, help="resolution while the view or lighting changes")
    p = sub.add_parser("export", help="a run folder as glTF lightmaps (lightmap methods) or ONNX (neural evaluators)")
    p.add_argument("folder", help="a run folder written by `jprt run` or `jprt atlas` (config.json, summary.json, "
                                  "model.npz)")
    p.add_argument("--out", required=True, help="the export folder (created; export.json names every file in it)")
    p.add_argument("--size", type=int, default=64,
                   help="the square frame the ONNX model takes, at the run's default view (default 64)")
    p.add_argument("--no-onnx", dest="onnx", action="store_false", help="skip the ONNX conversion")
    p = sub.add_parser("design", help="the lighting that meets an objective file, found through a run's model and "
                                      "rendered by Mitsuba to check it")
    p.add_argument("folder", help="a run folder: point lights for RRF, data-driven PRT and MRT; an environment's "
                                  "turn and scale for neural-wavelet PRT, SH PRT and SG environment visibility")
    p.add_argument("--objective", required=True, help="the objective file (JSON; jprt.design says what it holds)")
    p.add_argument("--lights", type=int, default=1, help="point lights to place (default 1; point-light models)")
    p.add_argument("--size", type=int, default=64, help="the square frame at the run's camera (default 64; a "
                                                        "target image sets it)")
    p.add_argument("--steps", type=int, default=200, help="Adam steps (default 200)")
    p.add_argument("--lr", type=float, default=0.05, help="Adam's learning rate on the unconstrained "
                                                          "parameters (default 0.05)")
    p.add_argument("--optimise", default=None, help="what moves (comma-separated): position, power, colour for "
                                                    "point lights (default position,power); rotation, scale, "
                                                    "colour for an environment (default rotation,scale)")
    p.add_argument("--env", default=None, help="the environment map to turn and scale: one of the run's by name "
                                               "(default the first) or an environment-map file")
    p.add_argument("--start", choices=("spread", "search"), default="spread",
                   help="point lights: start spread over the light region (default), or at the candidates a "
                        "search of traced positions finds best (jprt.design.search_start; for lights to recover "
                        "from an image, whose shadows the gradient alone does not move)")
    p.add_argument("--correct", type=int, default=1,
                   help="point lights: passes of the correction (default 1; 0: none): the lights found are "
                        "rendered by Mitsuba, the model's error there is held and the design runs again "
                        "(jprt.design.model_offset)")
    p.add_argument("--correct-spp", type=int, default=256, help="Mitsuba's spp for the correction's render "
                                                                "(default 256)")
    p.add_argument("--verify-spp", type=int, default=256, help="Mitsuba's spp for the verification render")
    p.add_argument("--out", default=None, help="write the report here (JSON)")
    args = parser.parse_args(argv)

    from jprt.config import ConfigError
    from jprt.render.setup import LLVMNotFoundError

    try:
        if args.command == "info":
            return _info()
        if args.command == "sweep":
            return _sweep(args)
        if args.command == "atlas":
            return _atlas(args)
        if args.command == "view":
            from jprt.view import check_run_folder, serve

            check_run_folder(args.folder)  # one clear line before anything heavy is imported
            serve(args.folder, host=args.host, port=args.port, size=args.size, preview=args.preview)
            return 0
        if args.command == "export":
            from jprt.export import export_run
            from jprt.view import check_run_folder

            check_run_folder(args.folder)
            manifest = export_run(args.folder, args.out, size=args.size, onnx=args.onnx, progress=True)
            print(f"{manifest['method']} exported to {os.path.abspath(args.out)} ({len(manifest['files']) + 1} files; "
                  "export.json says what each holds)")
            return 0
        if args.command == "design":
            return _design(args)
        module = load_experiment(args.experiment)
        config = resolve_config(module, args.overrides, args.preset, args.config_file)
        if args.command == "render":
            from jprt.render.dataset import from_config

            if "dataset" not in config:
                raise ValueError(f"{args.experiment}: CONFIG has no 'dataset' section to render")
            ds = from_config(config["dataset"])
            print(f"dataset: {ds.folder} ({len(ds)} items; rendered {ds.stats['rendered']} entries, "
                  f"reused {ds.stats['cached']})")
            return 0
        if callable(getattr(module, "main", None)):
            module.main(config)
        else:
            from jprt.runner import run

            run(module, config)
        return 0
    except (ConfigError, LLVMNotFoundError, FileNotFoundError, ValueError) as e:
        print(f"jprt: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("jprt: interrupted", file=sys.stderr)
        return 130


def _design(args) -> int:
    import json

    from jprt.design import design_run, report_lines
    from jprt.view import check_run_folder

    check_run_folder(args.folder)
    report = design_run(args.folder, args.objective, lights=args.lights, size=args.size, steps=args.steps,
                        learning_rate=args.lr, verify_spp=args.verify_spp, correct=args.correct,
                        correct_spp=args.correct_spp, env=args.env, progress=True,
                        start="search" if args.start == "search" else None,
                        optimise=None if args.optimise is None else [s.strip() for s in args.optimise.split(",")
                                                                      if s.strip()])
    print("\n".join(report_lines(report)))
    if args.out:
        with open(args.out, "w") as f:
            json.dump(report, f, indent=1)
        print(f"report: {os.path.abspath(args.out)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
