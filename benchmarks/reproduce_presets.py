"""Do the experiments still compute the same numbers? Runs every experiment's ``test`` preset
and compares each summary with one recorded earlier (``benchmarks/results/pre_contract/``: the
summaries of commit a2cefc4, before the method contract of issue 13), number by number.

A number counts when its key (nested keys joined by dots; keys now under ``extra`` or renamed to
the common schema are matched to their old names) is in both summaries and is not a timing or a
path; it agrees when the relative difference is at most ``--rtol`` (1e-6). Same seeds, same
machine kind; Mitsuba renders of two processes can differ by about one float32 ulp.
With ``--small`` it also runs data-driven PRT's ``small`` preset (the Cornell box, the quickest
full-size run, ~6 min) and compares it with the accuracy figures of
``benchmarks/results/datadriven.json`` (its "cornell" entry). Writes
benchmarks/results/contract_refactor.json.

    python benchmarks/reproduce_presets.py          # ~3 min on 2 cores
    python benchmarks/reproduce_presets.py --small  # + ~6 min
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
RECORDED = os.path.join(HERE, "results", "pre_contract")
EXPERIMENTS = ("datadriven", "rrf_cornell", "rrf_glossy", "wavelet_prt_cornell")
#: Not numbers of the method: timings, seconds, paths, hashes.
SKIP = ("_s", "_ms", "ms_", "_us", "seconds", "speedup", "total", "output", "device", "hash", "backend", "time")
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
    old = flatten(old)
    new = {(k[len("extra."):] if k.startswith("extra.") else k): v for k, v in flatten(new).items()}
    equal, differ, absent = 0, [], []
    for key, v in old.items():
        if not isinstance(v, (int, float)) or isinstance(v, bool) or any(s in key for s in SKIP):
            continue
        w = new.get(key, new.get(RENAMED.get(key, "")))
        if not isinstance(w, (int, float)) or isinstance(w, bool):
            absent.append(key)
        elif (math.isnan(v) and math.isnan(w)) or abs(v - w) <= rtol * max(abs(v), abs(w), 1e-30):
            equal += 1
        else:
            differ.append({"key": key, "recorded": v, "now": w})
    return {"equal": equal, "differ": differ, "absent": absent}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rtol", type=float, default=1e-6)
    parser.add_argument("--out", default=os.path.join(HERE, "results", "contract_refactor.json"))
    parser.add_argument("--small", action="store_true", help="also data-driven PRT's small preset vs datadriven.json")
    args = parser.parse_args()
    sys.path.insert(0, ROOT)
    from jprt.eval import write_benchmark
    from jprt.runner import flat_summary, run_file

    work = tempfile.mkdtemp(prefix="jprt_reproduce_")
    os.environ["JPRT_CACHE"] = os.path.join(work, "cache")
    result = {}
    for name in EXPERIMENTS:
        summary = run_file(os.path.join(ROOT, "experiments", f"{name}.py"), "test", [f"output.dir={work}/{name}"])
        with open(os.path.join(RECORDED, f"{name}_test.json")) as f:
            result[name] = compare(json.load(f), summary, args.rtol)
        edit = os.path.join(RECORDED, f"{name}_test_material_edit.json")
        if os.path.isfile(edit):
            with open(edit) as f:
                result[f"{name}/material_edit"] = compare(json.load(f), summary["extra"]["material_edit"], args.rtol)
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
    write_benchmark(args.out, result, "python benchmarks/reproduce_presets.py" + (" --small" if args.small else ""),
                    rtol=args.rtol,
                    recorded="benchmarks/results/pre_contract/*.json (commit a2cefc4, test presets)",
                    notes="absent keys: test_resolution / timing_resolution are config inputs (in config.json); "
                          "rrf_glossy's rmse_augmented was a copy of indirect_rmse written with ablations off")
    return 0 if result["all_equal"] else 1


if __name__ == "__main__":
    sys.exit(main())
