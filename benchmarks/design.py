"""Lighting design through a fitted model against Mitsuba (issue 48), as far as it is built.

    python benchmarks/design.py                      # -> benchmarks/results/design.json
    python benchmarks/design.py --run results/rrf_cornell/<hash> --configs 5 --spp 1024

The model: RRF on the Cornell box (``experiments/rrf_cornell.py``, preset ``demo``, fitted by the
runner unless ``--run`` names a run folder; its fit time is reported). At the run's camera
(``--size``):

* **gradient check** (``jprt.design.gradient_check``): the image objective against a Mitsuba
  render of a hidden light; at ``--configs`` random single-light configurations in the trained
  light box, the model's gradient (position and log intensity scale) against central finite
  differences of Mitsuba renders (``--spp``, the same seed on both sides), taken with two seeds:
  cosine similarity with their mean, and the Mitsuba noise level (the two seeds' disagreement);
* **inverse lighting** (``jprt.design.design_run``): Mitsuba renders (``--target-spp``) of 1 and 3
  hidden white point lights; the design from lights at random points of the box's middle (half
  the intensity); position error over the scene's diagonal (lights matched), intensity ratio,
  the objective on the model and on Mitsuba's verification render, the design's time.

* **the peer** (``_peer``): Mitsuba's own inverse rendering of the same lights on the same image
  objective (``jprt.render.inverse.SphereLights``: ``prb`` for the radiance, ``direct_projective``
  for the positions; ``jprt.design.mitsuba_design``: the same parameters and Adam from the
  same start), each checkpoint verified like jprt's result; the time it took to reach jprt's
  verified objective and the speed-up (``speed``, with the fit time and the break-even number of
  designs).

Other scenes are runs of their own merged into the same file (``--name NAME --merge``; each
scene records its command): another RRF run folder (``--run``; ``--configs 0`` skips the gradient
check, ``--peer-steps 0`` the peer), or ``--environment SCENE_FILE`` for irradiance targets through
SH PRT fitted on the file through its ceiling opening (``_environment_run``). ``not_run`` lists
the scenes a file does not have yet.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)

NOT_RUN = {
    "staircase": "a run of its own: --run FOLDER --name staircase --merge --configs 0, FOLDER an RRF of the "
                 "staircase (docs/design.md says how it is fitted)",
    "living_room": "a run of its own: --environment ../shared/assets/scenes/living-room/scene.xml --name "
                   "living_room --merge",
}


def _run_folder(args) -> tuple[str, dict]:
    from jprt.experiment import load_experiment, resolve_config
    from jprt.runner import run

    if args.run:
        with open(os.path.join(args.run, "summary.json")) as f:
            return args.run, json.load(f)
    module = load_experiment(os.path.join(ROOT, "experiments", "rrf_cornell.py"))
    summary = run(module, resolve_config(module, [], "demo"))
    return summary["output"], summary


def _target(problem, lights, spp: int, seed: int) -> np.ndarray:
    from jprt.inputs import PointLights
    from jprt.render import images

    problem.session.handle.set_lighting(PointLights.create(lights[0], lights[1]))
    r = images.centre_rays(problem.session.handle, problem.camera, spp=spp, seed=seed)
    full = np.asarray(r.direct, np.float32) + np.asarray(r.indirect, np.float32)
    return np.where(np.asarray(problem.gbuffer.valid, bool)[..., None], full, 0.0).astype(np.float32)


def _objective_file(folder: str, spec: dict, name: str = "objective.json") -> str:
    """``spec`` written as the objective file ``folder``/``name``; its path."""
    path = os.path.join(folder, name)
    with open(path, "w") as f:
        json.dump(spec, f)
    return path


def _image_objective(folder: str, target: np.ndarray) -> str:
    np.save(os.path.join(folder, "target.npy"), target)
    return _objective_file(folder, {"image": {"path": "target.npy", "quantity": "full"}})


def _bounds_met_by(means: dict, chosen: list) -> dict:
    """An objective file's spec of bounds a lighting with object ``means`` meets: the objects
    ``chosen`` get, alternately, min = 0.9 x and max = 1.1 x their mean irradiance there."""
    return {"objects": [{"name": n, "quantity": "irradiance",
                         **({"min": 0.9 * means[f"{n}.irradiance"]} if i % 2 == 0
                            else {"max": 1.1 * means[f"{n}.irradiance"]})} for i, n in enumerate(chosen)]}


_MACHINE: dict = {}


def _step_speed(rep: dict) -> dict:
    """A design's step judged against this machine: ms per step (the loop's wall time over its
    steps, visibility refreshes included) and its roofline (``jprt.eval.roofline_of``: XLA's
    FLOPs and bytes of one compiled step; the f32 matmul rate and the triad bandwidth measured
    once in this process). The steps are those the design took (``steps_taken``: it stops early once
    its traces stop improving), not its budget; the design before its correction
    (``rep["uncorrected"]``), whose steps they are."""
    from jprt import eval as jeval

    if not _MACHINE:
        _MACHINE.update(matmul_gflops=jeval.matmul_peak_gflops(), bandwidth_gbs=jeval.stream_bandwidth_gbs())
    seconds = rep["uncorrected"]["design_s"] if "uncorrected" in rep else rep["design_s"]
    ms = 1e3 * (seconds - (rep.get("search_s") or 0.0)) / max(int(rep.get("steps_taken", rep["steps"])), 1)
    cost = rep.get("step_cost") or {}
    roof = jeval.roofline_of(cost.get("flops"), cost.get("bytes"), frame_ms=ms,
                             peak_gflops=_MACHINE["matmul_gflops"], bandwidth_gbs=_MACHINE["bandwidth_gbs"])
    return {"step_ms": ms, "roofline": roof["roofline"]}


def _bounds_result(label: str, chosen: list, spec: dict, rep: dict) -> dict:
    """The benchmark's entry for a bounds design (``design_run``'s report ``rep``), printed in one
    line."""
    print(f"{label} on {chosen}: every bound met on Mitsuba's render: {rep['bounds_met_verified']} "
          f"({ {k: round(v['verified_mean'], 4) for k, v in rep['bounds'].items()} })", flush=True)
    return {"objective": spec, "found": rep["found"], "bounds": rep["bounds"],
            "bounds_met_verified": rep["bounds_met_verified"], "design_s": rep["design_s"],
            "steps_taken": rep.get("steps_taken"), **_step_speed(rep),
            "verify_spp": rep["verify_spp"], "target": "every bound met on the Mitsuba verification render"}


def _peer(args, pk, true_p, start: dict, diagonal: float, rep: dict, lo, hi) -> dict:
    """Mitsuba's inverse rendering of the same lights from the same start (``jprt.design.mitsuba_design``
    over ``jprt.render.inverse.SphereLights``) on the problem ``pk`` (``design.load_problem`` of
    the objective), every checkpoint verified like jprt's result (``_verify``, the same spp and
    seed); the time it took to reach jprt's verified objective, and the speed-up of jprt's design
    over it (a lower bound when it never did); beside it the same for jprt's design before its
    correction (``rep["uncorrected"]``, verified by ``_inverse``)."""
    from jprt import design
    from jprt.render.inverse import SphereLights

    k = len(true_p)
    sphere = SphereLights(pk.session.handle, pk.camera, pk.objective.image.target, pk.objective.image.mask,
                          count=k, radius=args.peer_radius * diagonal, spp=args.peer_spp)
    steps = args.peer_steps or 2 * args.steps
    res = design.mitsuba_design(sphere, start["position"], start["intensity"], lo, hi, steps=steps,
                                learning_rate=args.learning_rate, every=args.peer_every, seed=args.seed,
                                progress=False)
    for c in res.checkpoints:
        c["verified_objective"] = _verify(args, pk, c["position"], c["intensity"], rep["reference_power"])
    ours = rep["verified_objective"]
    reached = [c for c in res.checkpoints if c["verified_objective"] <= ours]
    seconds_to = reached[0]["seconds"] if reached else res.seconds
    unc = rep["uncorrected"]
    reached_unc = [c for c in res.checkpoints if c["verified_objective"] <= unc["verified_objective"]]
    seconds_unc = reached_unc[0]["seconds"] if reached_unc else res.seconds
    # beside the first touch (the target's reading): from which checkpoint on Mitsuba stays at or
    # below jprt's objective, since its noisy iterates can touch it once and settle above it
    below = [c["verified_objective"] <= ours for c in res.checkpoints]
    stays = next((i for i in range(len(below)) if all(below[i:])), None)
    cost = np.linalg.norm(res.position[:, None] - np.asarray(true_p)[None], axis=-1)
    return {"integrators": "prb (radiance, full transport) + direct_projective with guiding 'none' (positions)",
            "sphere_radius": args.peer_radius * diagonal, "spp": args.peer_spp, "steps": steps,
            "seconds": res.seconds, "seconds_per_step": res.seconds / max(steps, 1),
            "found": {"position": res.position.tolist(), "intensity": res.intensity.tolist()},
            "position_error_fraction": float(cost.min(axis=0).max() / diagonal),
            "verified_objective": res.checkpoints[-1]["verified_objective"],
            "best_verified_objective": min(c["verified_objective"] for c in res.checkpoints),
            "checkpoints": res.checkpoints, "history": res.history.tolist(),
            "reached_jprt": bool(reached), "seconds_to_jprt_objective": seconds_to,
            "checkpoints_at_or_below_jprt": int(sum(below)), "checkpoint_count": len(below),
            "seconds_to_stay_at_jprt_objective": None if stays is None else res.checkpoints[stays]["seconds"],
            "speedup": seconds_to / rep["design_s"], "speedup_is_lower_bound": not reached,
            "uncorrected": {"seconds_to_jprt_objective": seconds_unc, "speedup": seconds_unc / unc["design_s"],
                            "speedup_is_lower_bound": not reached_unc}}


def _verify(args, pk, position, intensity, reference: float) -> float:
    """The objective on Mitsuba's render of point lights (``design.rendered_terms`` at
    ``--target-spp``, the verification's seed): how every design and checkpoint is scored."""
    from jprt import design

    return float(sum(design.rendered_terms(pk.session.handle, pk.camera, pk.gbuffer, pk.objective, pk.masks,
                                           np.asarray(position), np.asarray(intensity), spp=args.target_spp,
                                           seed=args.seed + 101, reference_power=reference).values()))


def _speed(inverse: dict, scenes: dict) -> dict:
    """jprt's design against Mitsuba's inverse rendering to the same verified objective, per
    problem ("scene/k_lights"); each scene's fit time and the number of designs after which
    fitting has paid for itself."""
    rows, no_peer = {}, []
    for name, r in inverse.items():
        if not isinstance(r.get("mitsuba"), dict):  # the peer not run on this problem
            no_peer.append(name)
            continue
        model = scenes.get(name.split("/")[0], {}).get("model", {})
        fit = float(model.get("fit_s") or 0.0) + float(model.get("dataset_s") or 0.0)
        peer = r["mitsuba"]
        saved = peer["seconds_to_jprt_objective"] - r["design_s"]
        rows[name] = {"jprt_design_s": r["design_s"], "mitsuba_s": peer["seconds_to_jprt_objective"],
                      "speedup": peer["speedup"], "speedup_is_lower_bound": peer["speedup_is_lower_bound"],
                      "fit_s": fit, "break_even_designs": (fit / saved) if saved > 0 else None}
    return {"per_problem": rows, "target": "jprt at least 20x faster (fit excluded)",
            "met": bool(rows) and all(v["speedup"] >= 20 for v in rows.values()),
            "met_on": sorted(rows), "not_measured": sorted(no_peer)}


def _hidden_positions(pb, lo, hi, rng, k: int, margin: float = 0.15) -> np.ndarray:
    """``k`` hidden light positions uniform in the light box less ``margin`` of it on each side,
    each drawn again there while it is inside geometry, touches a surface or (in a scene file)
    lights too little of what the file's camera sees (``jprt.render.sampling.free_lights``, the
    rule every training and held-out light follows)."""
    from jprt.render.sampling import free_lights

    mid_lo, mid_hi = lo + margin * (hi - lo), hi - margin * (hi - lo)
    positions = lo + (hi - lo) * rng.uniform(margin, 1.0 - margin, (k, 3))
    return free_lights(pb.session.handle.description, positions, mid_lo, mid_hi, rng)


def _inverse(args, folder: str, pb, lo, hi, diagonal: float, rng, work: str) -> dict:
    """Inverse lighting of 1 and 3 hidden white point lights (``design.design_run`` from the lights
    ``design.search_start`` finds, or with ``--start box`` from lights in the box's middle at half
    the intensity), each against the peer (``_peer``) from the lights in the box's middle: the
    search is jprt's work, counted in ``design_s`` (``search_s`` beside it)."""
    from scipy.optimize import linear_sum_assignment

    from jprt import design

    inverse = {}
    for k in (1, 3):
        true_p = _hidden_positions(pb, lo, hi, rng, k)
        true_i = np.ones((k, 3))
        path = _image_objective(work, _target(pb, (true_p, true_i), args.target_spp, 2 + k))
        box = {"position": lo + (hi - lo) * rng.uniform(0.3, 0.7, (k, 3)), "intensity": np.full((k, 3), 0.5)}
        rep = design.design_run(folder, path, lights=k, size=args.size, steps=args.steps,
                                start="search" if args.start == "search" else box,
                                learning_rate=args.learning_rate,
                                verify_spp=args.target_spp, seed=args.seed, progress=False)
        pk = design.load_problem(folder, path, size=args.size, progress=False)

        def match(found):
            cost = np.linalg.norm(np.asarray(found["position"])[:, None] - true_p[None], axis=-1)
            rows, cols = linear_sum_assignment(cost)
            return cost[rows, cols] / diagonal, (np.asarray(found["intensity"])[rows] / true_i[cols]).mean(axis=1)

        error, ratio = match(rep["found"])
        # the lights before the correction, verified alike: what the correction bought
        unc = rep["uncorrected"]
        unc["verified_objective"] = _verify(args, pk, unc["position"], unc["intensity"], rep["reference_power"])
        unc["position_error_fraction"], unc["intensity_ratio"] = (a.tolist() for a in match(unc))
        # the peer starts where jprt's design started, before its search: the search is jprt's work, timed in design_s
        peer = _peer(args, pk, true_p, box, diagonal, rep, lo, hi) if args.peer_steps != 0 else None
        inverse[f"{k}_lights"] = {
            "hidden": {"position": true_p.tolist(), "intensity": true_i.tolist()},
            "found": rep["found"], "start": rep["start"],
            "position_error_fraction": error.tolist(), "intensity_ratio": ratio.tolist(),
            "model_objective": rep["model_objective"], "verified_objective": rep["verified_objective"],
            "design_s": rep["design_s"], "search_s": rep.get("search_s"), "start_from": args.start,
            "correction": rep["correction"], "uncorrected": unc,
            "verify_s": rep["verify_s"], "steps": rep["steps"], "steps_taken": rep.get("steps_taken"),
            **_step_speed(rep),
            "position_within_3_percent": bool(np.all(error <= 0.03)),
            "intensity_within_10_percent": bool(np.all(np.abs(ratio - 1.0) <= 0.10)),
            "mitsuba": peer if peer is not None else "not run (--peer-steps 0)",
            "verified_within_1_2x_of_mitsuba": None if peer is None else
            bool(rep["verified_objective"] <= 1.2 * peer["verified_objective"])}
        if peer is not None:
            print(f"  Mitsuba's inverse rendering: verified {peer['verified_objective']:.4g} after {peer['seconds']:.1f} "
                  f"s; reached jprt's verified objective: {peer['reached_jprt']}, speed-up {peer['speedup']:.1f}x",
                  flush=True)
        print(f"{k} hidden lights: position error {np.round(error, 4)} of the diagonal, "
              f"intensity x{np.round(ratio, 3)}, objective model {rep['model_objective']:.4g} / "
              f"Mitsuba {rep['verified_objective']:.4g} (before the correction {unc['verified_objective']:.4g}), "
              f"{rep['design_s']:.1f} s", flush=True)
    return inverse


def _irradiance_targets(args, folder: str, pb, lo, hi, rng, work: str, objects: int = 2) -> dict:
    """Bounds on the mean irradiance of named objects that a lighting is known to meet: two hidden
    point lights rendered by Mitsuba (``--target-spp``); the ``objects`` objects the frame shows
    most of (diffuse albedo above 0.05) get, alternately, min = 0.9 x and max = 1.1 x their
    irradiance there. The design starts from two other lights at a quarter of the intensity and
    is verified on Mitsuba's render of what it found (``design_run``): every bound met or not."""
    from jprt import design

    names = list(pb.session.handle.object_names())
    gb = pb.gbuffer
    chosen = _largest_objects(pb, names, objects)
    probe = design.load_objective({"objects": [{"name": n, "min": 1.0} for n in chosen]}, names)
    masks = design.object_masks(probe, gb.object_id, names, gb.valid)
    hidden = (_hidden_positions(pb, lo, hi, rng, 2), np.ones((2, 3)))
    _, means = design.rendered_terms(pb.session.handle, pb.camera, gb, probe, masks, hidden[0], hidden[1],
                                     spp=args.target_spp, seed=7, means=True)
    spec = _bounds_met_by(means, chosen)
    path = _objective_file(work, spec, "irradiance_objective.json")
    start = {"position": lo + (hi - lo) * rng.uniform(0.3, 0.7, (2, 3)), "intensity": np.full((2, 3), 0.25)}
    rep = design.design_run(folder, path, lights=2, size=args.size, steps=args.steps, start=start,
                            learning_rate=args.learning_rate, verify_spp=args.target_spp, seed=args.seed,
                            progress=False)
    return {**_bounds_result("irradiance targets", chosen, spec, rep),
            "hidden": {"position": hidden[0].tolist(), "intensity": hidden[1].tolist()}, "start": rep["start"]}


def _environment_run(scene: str) -> tuple[str, dict]:
    """SH PRT fitted on the scene file ``scene`` lit through its ceiling opening, at the sizes
    ``experiments/real_scenes.py`` gives it on real interiors (nothing chosen here), saved as a run
    folder (``jprt.runner.save_fit``) under results/design_sh_prt/<scene>; with the seconds
    ``make_dataset`` and the fit took (``make_dataset`` reads its cache when an earlier run baked
    the same dataset: then ``dataset_s`` is that read, not the bake)."""
    from jprt.experiment import load_experiment
    from jprt.methods import REGISTRY
    from jprt.methods.scene_file import scene_config
    from jprt.render.sampling import scene_regions
    from jprt.runner import save_fit

    real = load_experiment(os.path.join(ROOT, "experiments", "real_scenes.py")).CONFIG
    dark = {"name": "xml", "path": os.path.abspath(scene), "keep_emitters": False}
    desc = {**dark, "opening": real["environment"]["opening"]}
    cfg = scene_config("sh_prt", desc, scene_regions(dark), real["sh_prt"])
    m = REGISTRY["sh_prt"]
    t0 = time.perf_counter()
    dataset = m.make_dataset(desc, cfg, progress=False)
    t1 = time.perf_counter()
    result = m.fit(dataset, cfg)
    t2 = time.perf_counter()
    stem = os.path.basename(os.path.dirname(os.path.abspath(scene)))
    folder = save_fit(os.path.join(ROOT, "results", "design_sh_prt", stem), "sh_prt", cfg, result.params)
    with open(os.path.join(folder, "summary.json")) as f:
        summary = json.load(f)
    return folder, {**summary, "dataset_s": t1 - t0, "train_s": t2 - t1}


def _environment_targets(args, folder: str, env: str, rng, work: str, objects: int = 2) -> dict:
    """Bounds on the mean irradiance of named objects that a turn and scale of the map ``env`` is
    known to meet: the map turned by a hidden angle and scaled by a hidden factor, rendered by
    Mitsuba (``design.rendered_environment_terms``, ``--target-spp``); the ``objects`` objects the
    frame shows most of (diffuse albedo above 0.05) get, alternately, min = 0.9 x and max = 1.1 x
    their irradiance there. The design starts from the map as it is (angle 0, scale 1) and is
    verified on Mitsuba's render of what it found (``design_run``)."""
    from jprt import design

    pb = design.load_problem(folder, _image_objective(work, np.zeros((args.size, args.size, 3), np.float32)),
                             size=args.size, env=env, progress=False)
    chosen = _largest_objects(pb, list(pb.session.handle.object_names()), objects)
    probe = _objective_file(work, {"objects": [{"name": n, "min": 1.0} for n in chosen]}, "environment_probe.json")
    pb = design.load_problem(folder, probe, size=args.size, env=env, progress=False)
    angle, scale = float(rng.uniform(np.pi / 3, 5 * np.pi / 3)), np.full(3, 1.5)
    _, means = design.rendered_environment_terms(pb, angle, scale, spp=args.target_spp, seed=7, means=True)
    spec = _bounds_met_by(means, chosen)
    path = _objective_file(work, spec, "environment_objective.json")
    rep = design.design_run(folder, path, size=args.size, steps=args.steps, learning_rate=args.learning_rate,
                            verify_spp=args.target_spp, seed=args.seed, env=env, progress=False)
    return {**_bounds_result("environment targets", chosen, spec, rep), "environment": os.path.basename(env),
            "hidden": {"rotation_deg": float(np.degrees(angle)), "scale": scale.tolist()}}


def _largest_objects(pb, names: list, count: int) -> list:
    """The ``count`` objects with the most valid pixels of diffuse albedo above 0.05 in the
    problem's frame (the objects whose irradiance the frame can read)."""
    gb = pb.gbuffer
    valid = np.asarray(gb.valid, bool)
    ids = np.asarray(gb.object_id)[valid]
    albedo = np.asarray(gb.diffuse_albedo).mean(axis=-1)[valid]
    counts = {int(i): int(np.sum((ids == i) & (albedo > 0.05))) for i in np.unique(ids) if 0 <= i < len(names)}
    return [names[i] for i, _ in sorted(counts.items(), key=lambda t: -t[1])[:count]]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--run", default=None, help="an RRF run folder (default: fit the demo preset)")
    parser.add_argument("--name", default="cornell_box", help="the scene's key in the results")
    parser.add_argument("--merge", action="store_true",
                        help="update this scene's entries of an existing --out file, keep the others")
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--configs", type=int, default=5, help="gradient-check configurations (0: none)")
    parser.add_argument("--spp", type=int, default=1024, help="Mitsuba's spp for the finite differences")
    parser.add_argument("--target-spp", type=int, default=1024, help="Mitsuba's spp for the hidden lights' renders")
    parser.add_argument("--steps", type=int, default=300, help="jprt's design steps")
    parser.add_argument("--learning-rate", type=float, default=0.05, help="Adam's rate (both designers)")
    parser.add_argument("--peer-spp", type=int, default=16, help="Mitsuba inverse rendering: spp of each render")
    parser.add_argument("--peer-radius", type=float, default=0.005,
                        help="Mitsuba inverse rendering: each light's sphere radius over the scene's diagonal")
    parser.add_argument("--peer-every", type=int, default=25, help="Mitsuba inverse rendering: verify every N steps")
    parser.add_argument("--peer-steps", type=int, default=None,
                        help="Mitsuba inverse rendering: Adam steps (default twice --steps: its gradients are noisy; 0: "
                             "no peer)")
    parser.add_argument("--environment", default=None, metavar="SCENE_FILE",
                        help="irradiance targets through an environment-lit model instead: SH PRT fitted on this "
                             "scene file through its ceiling opening (or the environment-lit --run)")
    parser.add_argument("--env", default=None, help="the environment map file the design turns and scales "
                        "(default: the first held-out map of experiments/real_scenes.py)")
    parser.add_argument("--start", choices=("box", "search"), default="search",
                        help="inverse lighting's start: jprt.design.search_start's candidates (default) or the "
                             "middle of the light box (the peer starts from the box's middle either way)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=os.path.join(HERE, "results", "design.json"))
    args = parser.parse_args()
    if args.environment:
        return _environment_main(args, parser)
    from jprt import design
    from jprt.render.setup import mitsuba

    mitsuba()
    t0 = time.perf_counter()
    folder, summary = _run_folder(args)
    work = tempfile.mkdtemp(prefix="jprt_design_")
    # the problem's frame and region (the objective file is replaced per target below)
    probe = _image_objective(work, np.zeros((args.size, args.size, 3), np.float32))
    pb = design.load_problem(folder, probe, size=args.size, progress=False)
    lo, hi = pb.lo, pb.hi
    box = pb.session.handle.scene.bbox()
    diagonal = float(np.linalg.norm(np.asarray(box.max) - np.asarray(box.min)))
    rng = np.random.default_rng(args.seed)

    # gradient check: the image objective of one hidden light, at random configurations
    hidden = (_hidden_positions(pb, lo, hi, rng, 1, margin=0.2), np.ones((1, 3)))
    pb = design.load_problem(folder, _image_objective(work, _target(pb, hidden, args.target_spp, 1)),
                             size=args.size, progress=False)
    checks = []
    for c in range(int(args.configs)):
        pos = lo + (hi - lo) * rng.uniform(0.2, 0.8, (1, 3))
        t1 = time.perf_counter()
        g = design.gradient_check(pb.session.handle, pb.camera, pb.gbuffer, pb.frame, pb.objective, pb.masks, pos,
                                  np.full((1, 3), 0.8), visibility_fn=pb.visibility, spp=args.spp)
        g.update(position=pos.tolist(), seconds=time.perf_counter() - t1)
        checks.append(g)
        print(f"gradient check {c}: cosine {g['cosine']:.4f} (seed against seed {g['cosine_seeds']:.4f}, "
              f"noise {g['noise']:.3f})", flush=True)

    inverse = _inverse(args, folder, pb, lo, hi, diagonal, rng, work)
    targets = _irradiance_targets(args, folder, pb, lo, hi, rng, work)
    model = {"method": "rrf", "run": os.path.relpath(folder, ROOT), "config_hash": summary.get("config_hash"),
             "fit_s": summary.get("train_s"), "dataset_s": summary.get("dataset_s")}
    scene = {"model": model, "frame": [args.size, args.size], "scene_diagonal": diagonal,
             "light_region": {"lo": lo.tolist(), "hi": hi.tolist()}, "seconds": time.perf_counter() - t0}
    result = _merged(args)
    result["scenes"][args.name] = scene
    if checks:
        check = {"scene": args.name, "spp": args.spp, "configurations": checks,
                 "cosine_min": float(min(c["cosine"] for c in checks)), "target": "cosine >= 0.9 per configuration",
                 "met": bool(all(c["cosine"] >= 0.9 for c in checks))}
        other = result.get("gradient_check") or {}
        if other.get("scene") not in (None, args.name):  # another scene's check stays where it is
            scene["gradient_check"] = check
        else:
            result["gradient_check"] = check
    result["inverse_lighting"][args.name] = inverse
    result["irradiance_targets"][args.name] = targets
    _write(args, parser, result)
    return 0


def _environment_main(args, parser) -> int:
    """``--environment``: SH PRT on the scene file (or the environment-lit ``--run``) and the
    irradiance targets through it (``_environment_targets``), merged into ``--out`` like a scene."""
    from jprt.render.setup import mitsuba

    mitsuba()
    t0 = time.perf_counter()
    if args.run:
        folder, summary = _run_folder(args)
    else:
        folder, summary = _environment_run(args.environment)
    env = args.env
    if env is None:
        from jprt.experiment import load_experiment

        first = load_experiment(os.path.join(ROOT, "experiments", "real_scenes.py")).CONFIG["environment"]["maps"][0]
        env = os.path.join(ROOT, "..", "shared", "assets", "envmaps", f"{first}.hdr")
    work = tempfile.mkdtemp(prefix="jprt_design_")
    targets = _environment_targets(args, folder, env, np.random.default_rng(args.seed), work)
    result = _merged(args)
    model = {"method": summary.get("method"), "run": os.path.relpath(folder, ROOT),
             "config_hash": summary.get("config_hash"), "fit_s": summary.get("train_s"),
             "dataset_s": summary.get("dataset_s")}
    result["scenes"][args.name] = {"model": model, "frame": [args.size, args.size],
                                   "seconds": time.perf_counter() - t0}
    result["irradiance_targets"][args.name] = targets
    result["inverse_lighting"].pop(args.name, None)  # a point-light run of the same name is not this model's
    _write(args, parser, result)
    return 0


def _command(args, parser) -> str:
    """The command line that reproduces this run (the options that differ from their defaults)."""
    return "python benchmarks/design.py" + "".join(
        f" --{k.replace('_', '-')} {v}" for k, v in vars(args).items() if k != "out" and v is not None
        and v is not False and v != parser.get_default(k)).replace(" --merge True", " --merge")


def _merged(args) -> dict:
    """The results to write: empty, or with ``--merge`` those of ``--out`` as they are."""
    result = {"scenes": {}, "gradient_check": None, "inverse_lighting": {}, "irradiance_targets": {},
              "not_run": dict(NOT_RUN)}
    if args.merge and os.path.exists(args.out):
        with open(args.out) as f:
            old = json.load(f)
        result.update({k: old[k] for k in result if k in old})
    result["not_run"].pop(args.name, None)
    return result


def _write(args, parser, result: dict) -> None:
    """``result`` with its speed table (``_speed``) to ``--out``, with the command that made it."""
    from jprt.eval import write_benchmark

    result["inverse_lighting"]["target"] = ("position error <= 3 % of the scene's size per light, intensity "
                                            "within 10 %")
    result["speed"] = _speed({f"{s}/{k}": v for s, rows in result["inverse_lighting"].items()
                              if isinstance(rows, dict) for k, v in rows.items() if isinstance(v, dict)},
                             result["scenes"])
    command = _command(args, parser)
    result["scenes"][args.name]["command"] = command  # each scene's own run (--merge keeps the others')
    if result.get("gradient_check") and result["gradient_check"].get("scene") == args.name and args.configs:
        result["gradient_check"]["command"] = command
    write_benchmark(args.out, result, command,
                    notes="gradient check: parameters are each light's position (world units) and log intensity "
                          "scale; finite differences central, step 0.01 of the scene's diagonal (position) and "
                          "0.05 (log scale), Mitsuba full radiance (direct + indirect) along the G-buffer's pixel-centre "
                          "rays; noise = |g_seed1 - g_seed2| / |g_seed1 + g_seed2|. Inverse lighting: image "
                          "objective (relative squared error of the full image), Adam with cosine decay, visibility "
                          "traced every 10 steps; position error over the scene's bounding-box diagonal. Irradiance "
                          "targets: bounds a hidden lighting meets on Mitsuba's render (min 0.9 x, max 1.1 x its "
                          "means), designed from another start and checked on Mitsuba's render of the result.")


if __name__ == "__main__":
    sys.exit(main())
