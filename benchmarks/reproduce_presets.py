"""Do the experiments still compute the same numbers? Runs every experiment's ``test`` preset
twice, at the working tree and at an earlier commit (``--against``, default ``BASELINE``: the
last commit before the library-first refactor), and compares the two summaries number by
number. The earlier commit runs from a detached git worktree (its own imports, its own
``JPRT_CACHE``) in the same process tree, so both sides see the same machine and libraries.
``--recorded`` compares with the summaries recorded at commit a2cefc4 instead
(``benchmarks/results/pre_contract/``, before the method contract of issue 13; later, intended
changes of the methods have moved many of those numbers).

A number counts when its key (nested keys joined by dots; keys under ``extra`` or renamed to the
common schema are matched to their old names) is in both summaries and is not a timing, a rate
measured on the machine, or a path; it agrees when the relative difference is at most ``--rtol``
(1e-6). Keys only the earlier commit wrote are listed as absent. With ``--small`` it also runs
data-driven PRT's ``small`` preset (the Cornell box, the quickest full-size run, ~6 min) and
compares it with the accuracy figures of ``benchmarks/results/datadriven.json`` (its "cornell"
entry). Writes benchmarks/results/contract_refactor.json; exits 1 when a number differs.

    python benchmarks/reproduce_presets.py                   # ~8 min on 2 cores: both commits
    python benchmarks/reproduce_presets.py --against HEAD~5  # another earlier commit
    python benchmarks/reproduce_presets.py --recorded        # ~3 min: against pre_contract/
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
RECORDED = os.path.join(HERE, "results", "pre_contract")
#: The last commit before issue 46's refactor (experiments made thin, modules split by concern).
BASELINE = "faf4041"
EXPERIMENTS = ("datadriven", "rrf_cornell", "rrf_glossy", "wavelet_prt_cornell")
#: Not numbers of the method: timings, seconds, rates measured on the machine, paths, hashes.
SKIP = ("_s", "_ms", "ms_", "_us", "seconds", "speedup", "total", "output", "device", "hash", "backend", "time",
        "gflops", "fraction_of_peak")
#: Old summary key -> key in the common schema.
RENAMED = {"indirect_relative_rmse": "indirect_rel_rmse", "psnr_indirect_far": "psnr_indirect",
           "rmse_indirect_far_set": "indirect_rmse"}


def flatten(d, prefix: str = "") -> dict:
    """Nested dicts and lists -> {"a.b.0": leaf}."""
    if isinstance(d, dict):
        return {k: v for key, val in d.items() for k, v in flatten(val, f"{prefix}{key}.").items()}
    if isinstance(d, list):
        return {k: v for i, val in enumerate(d) for k, v in flatten(val, f"{prefix}{i}.").items()}
    return {prefix[:-1]: d}


def compare(old: dict, new: dict, rtol: float) -> dict:
    """Every number of ``old`` against ``new`` (see the module docstring)."""
    def common(d: dict) -> dict:
        return {(k[len("extra."):] if k.startswith("extra.") else k): v for k, v in flatten(d).items()}
    old, new = common(old), common(new)
    equal, differ, absent = 0, [], []
    for key, v in old.items():
        if not isinstance(v, (int, float)) or isinstance(v, bool) or any(s in key for s in SKIP) \
                or key.endswith(".ms"):
            continue
        w = new.get(key, new.get(RENAMED.get(key, "")))
        if not isinstance(w, (int, float)) or isinstance(w, bool):
            absent.append(key)
        elif (math.isnan(v) and math.isnan(w)) or abs(v - w) <= rtol * max(abs(v), abs(w), 1e-30):
            equal += 1
        else:
            differ.append({"key": key, "recorded": v, "now": w})
    return {"equal": equal, "differ": differ, "absent": absent}


#: Run in a subprocess whose sys.path starts at another commit's tree: one experiment's test
#: preset, its summary written as JSON (argv: tree, experiment, output folder, summary file).
_RUN_AT = """
import json, os, sys
tree, name, out, dest = sys.argv[1:]
sys.path.insert(0, tree)
import jprt
assert os.path.dirname(os.path.dirname(os.path.abspath(jprt.__file__))) == os.path.abspath(tree), jprt.__file__
from jprt.runner import run_file
summary = run_file(os.path.join(tree, "experiments", name + ".py"), "test", ["output.dir=" + out])
with open(dest, "w") as f:
    json.dump(summary, f, default=str)
"""


def summaries_at(rev: str, work: str) -> dict:
    """Every experiment's ``test``-preset summary computed by commit ``rev`` (a detached git
    worktree under ``work``, removed afterwards; its own ``JPRT_CACHE``)."""
    tree = os.path.join(work, f"tree_{rev}")
    subprocess.run(["git", "-C", ROOT, "worktree", "add", "--detach", "-q", tree, rev], check=True)
    env = dict(os.environ, JPRT_CACHE=os.path.join(work, f"cache_{rev}"), PYTHONPATH=tree)
    found = {}
    try:
        for name in EXPERIMENTS:
            dest = os.path.join(work, f"{rev}_{name}.json")
            subprocess.run([sys.executable, "-c", _RUN_AT, tree, name, os.path.join(work, rev, name), dest],
                           check=True, env=env, cwd=tree)
            with open(dest) as f:
                found[name] = json.load(f)
    finally:
        subprocess.run(["git", "-C", ROOT, "worktree", "remove", "--force", tree], check=False)
    return found


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rtol", type=float, default=1e-6)
    parser.add_argument("--out", default=os.path.join(HERE, "results", "contract_refactor.json"))
    parser.add_argument("--small", action="store_true", help="also data-driven PRT's small preset vs datadriven.json")
    parser.add_argument("--against", metavar="REV", default=BASELINE,
                        help=f"the earlier commit whose summaries are computed and compared (default {BASELINE})")
    parser.add_argument("--recorded", action="store_true",
                        help="compare with benchmarks/results/pre_contract/ (commit a2cefc4) instead")
    args = parser.parse_args()
    sys.path.insert(0, ROOT)
    from jprt.eval import write_benchmark
    from jprt.runner import flat_summary, run_file

    work = tempfile.mkdtemp(prefix="jprt_reproduce_")
    earlier = None if args.recorded else summaries_at(args.against, work)
    os.environ["JPRT_CACHE"] = os.path.join(work, "cache")
    result = {}
    for name in EXPERIMENTS:
        summary = run_file(os.path.join(ROOT, "experiments", f"{name}.py"), "test", [f"output.dir={work}/{name}"])
        if earlier is not None:
            result[name] = compare(earlier[name], summary, args.rtol)
        else:
            with open(os.path.join(RECORDED, f"{name}_test.json")) as f:
                result[name] = compare(json.load(f), summary, args.rtol)
            edit = os.path.join(RECORDED, f"{name}_test_material_edit.json")
            if os.path.isfile(edit):
                with open(edit) as f:
                    result[f"{name}/material_edit"] = compare(json.load(f), summary["extra"]["material_edit"],
                                                              args.rtol)
        print(f"{name}: {result[name]['equal']} equal, {len(result[name]['differ'])} differ, "
              f"absent {result[name]['absent']}")
    if args.small:
        summary = flat_summary(run_file(os.path.join(ROOT, "experiments", "datadriven.py"), "small",
                                        [f"output.dir={work}/datadriven_small"]))
        with open(os.path.join(HERE, "results", "datadriven.json")) as f:
            recorded = json.load(f)["cornell"]
        keys = [k for k in recorded if k not in ("targets", "report", "config_hash")]
        result["datadriven_small_vs_datadriven.json"] = compare({k: recorded[k] for k in keys},
                                                                {k: summary.get(k) for k in keys}, args.rtol)
        r = result["datadriven_small_vs_datadriven.json"]
        print(f"datadriven small vs datadriven.json: {r['equal']} equal, {len(r['differ'])} differ, "
              f"absent {r['absent']}")
    result["all_equal"] = all(not r["differ"] for r in result.values() if isinstance(r, dict))
    command = "python benchmarks/reproduce_presets.py" + (" --small" if args.small else "") + \
        (" --recorded" if args.recorded else f" --against {args.against}")
    write_benchmark(args.out, result, command, rtol=args.rtol,
                    recorded=(f"the test presets run at commit {args.against} in the same run" if earlier else
                              "benchmarks/results/pre_contract/*.json (commit a2cefc4, test presets)"),
                    notes=("absent keys: wavelet_prt_cornell's hand-rolled front became a sweep file "
                           "(experiments/sweeps/wavelet_prt_front.py, run by jprt sweep)" if earlier else
                           "absent keys: test_resolution / timing_resolution are config inputs (in config.json); "
                           "rrf_glossy's rmse_augmented was a copy of indirect_rmse written with ablations off"))
    return 0 if result["all_equal"] else 1


if __name__ == "__main__":
    sys.exit(main())
