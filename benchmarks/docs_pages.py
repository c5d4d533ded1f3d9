"""The documentation site's benchmark pages, generated from ``benchmarks/results/*.json``.

Every number on a benchmark page comes from its JSON: the pages are rendered here, generically
(nested dicts become tables or sections, lists of records become tables), with a short
hand-written introduction per benchmark that names what is measured and holds no number. The
figures a benchmark writes beside its JSON are copied next to its page.

    python benchmarks/docs_pages.py            # writes docs/benchmarks/*.md (and the figures)
    python benchmarks/docs_pages.py --check    # exit 1 when a committed page differs from its JSON

``tests/test_docs.py`` fails when a committed page is not what ``pages()`` renders now.
"""

from __future__ import annotations

import argparse
import glob
import json
import math
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RESULTS = os.path.join(ROOT, "benchmarks", "results")
OUT = os.path.join(ROOT, "docs", "benchmarks")

#: Per benchmark (the JSON's stem): its page title, what it measures (no numbers: they live in
#: the JSON), the command that writes it, and the figures it writes beside the JSON.
INTROS: dict[str, dict] = {
    "atlas": {
        "title": "The speed-accuracy atlas",
        "intro": "Every registered method on shared tasks (a scene, a lighting kind and a held-out set no "
                 "method trains on), each swept over its main size knob, against Mitsuba's own "
                 "speed-accuracy curve measured in the same run. Each point's equal-error spp and speedup "
                 "are read off that curve. A method that does not take a task's lighting is listed as not "
                 "run, with the reason. See [Sweeps and the atlas](../sweeps.md).",
        "make": "make bench-atlas",
        "figures": [("atlas_local_lights.png", "local lights: held-out indirect RMSE against frame time"),
                    ("atlas_environment.png", "environment relighting: held-out indirect RMSE against frame time")],
    },
    "contract_refactor": {
        "title": "Contract refactor check",
        "intro": "The record of the method-contract refactor: every experiment's `test` preset compared, "
                 "number by number, with the summaries recorded before the refactor "
                 "(`benchmarks/results/pre_contract/`), and data-driven PRT's Cornell-box run against "
                 "`datadriven.json`. It stays as it was; the methods have changed on purpose since, so "
                 "rerunning it today differs (see the changelog).",
        "make": "python benchmarks/reproduce_presets.py --small",
    },
    "datadriven": {
        "title": "Data-driven PRT",
        "intro": "Data-driven PRT (Belcour et al. 2022) on the Spot model in a room corner (the top-level "
                 "numbers) and on the Cornell box (`cornell`): held-out lightmap RMSE over spot-light "
                 "configurations, the projection onto the basis (what the basis can represent), the ridge "
                 "parameter and measurement-point sweeps, bake and frame times, and equal error against "
                 "Mitsuba at the same texels. See [Data-driven PRT](../methods/datadriven.md).",
        "make": "make bench-datadriven",
    },
    "device_evaluators": {
        "title": "Evaluators on a GPU",
        "intro": "The RRF renderer and neural-wavelet PRT networks timed on the one GPU lent so far: frame "
                 "times by tile and chunk layout and by matmul precision, the accuracy cost of the default "
                 "precision, and the CPU export they were measured against. The wavelet networks are "
                 "initialised, not trained: their cost does not depend on the weights.",
        "make": "python benchmarks/device_evaluators.py export RUN OUT.npz; "
                "python benchmarks/device_evaluators.py measure OUT.npz out.json",
    },
    "design": {
        "title": "Lighting design through a fitted model",
        "intro": "Lights placed by gradient descent through a fitted model, checked against Mitsuba, per scene "
                 "(`scenes`, each with the command of its own run): the model's gradient of an image objective "
                 "against central finite differences of Mitsuba renders (Cornell box; the two seeds' "
                 "disagreement is the noise level); hidden point lights recovered from Mitsuba renders of them "
                 "through RRF (position error over the scene's diagonal, intensity ratio, the objective on the "
                 "model and on Mitsuba's verification render, and Mitsuba's own inverse rendering from the same "
                 "start where it was run); bounds on objects' irradiance that a hidden lighting meets, designed "
                 "and checked on Mitsuba's render (point lights through RRF; an environment's turn and scale "
                 "through SH PRT on the living room); the speed-up to the same verified objective. See "
                 "[Lighting design](../design.md).",
        "make": "python benchmarks/design.py",
    },
    "export": {
        "title": "Exported evaluators in ONNX",
        "intro": "The ONNX models `jprt export` writes for the neural evaluators (RRF, neural-wavelet PRT, SG "
                 "environment visibility), each fitted at its `test` preset: onnxruntime's CPU frame time at "
                 "the run's view beside the jitted JAX evaluator's on the same frame and lighting, in one "
                 "process, with the largest difference between the two frames over the frame's peak and the "
                 "operations written by hand for the conversion. See "
                 "[Use a jprt model in an engine](../engines.md).",
        "make": "python benchmarks/export.py",
    },
    "lm": {
        "title": "Levenberg-Marquardt solver",
        "intro": "`jprt.solve.lm` against jaxopt's Levenberg-Marquardt on the same least-squares problem: time "
                 "per iteration, memory as the number of samples grows, and the solver's FLOP rate as a "
                 "fraction of the matmul rate measured in the same process.",
        "make": "python benchmarks/lm.py",
    },
    "mrt": {
        "title": "Modular Radiance Transfer (small)",
        "intro": "MRT (Loos et al. 2011) at the `small` preset: texel RMSE on a maze with a cycle and on a "
                 "larger held-out maze, the projection floor, the error by each reduced dimension, by "
                 "feedback bounces, without interfaces or enrichment, data-driven PRT on the same texels, "
                 "vector irradiance and volume probes, frame time by number of blocks, and equal error "
                 "against Mitsuba. See [MRT](../methods/mrt.md).",
        "make": "make bench-mrt",
    },
    "mrt_paper": {
        "title": "Modular Radiance Transfer (paper sizes)",
        "intro": "MRT at the paper's sizes (the `paper` preset): the same measurements as the `small` run. "
                 "See [MRT](../methods/mrt.md).",
        "make": "python benchmarks/mrt.py --preset paper --out benchmarks/results/mrt_paper.json",
    },
    "real_scenes": {
        "title": "Real scenes",
        "intro": "Every method that fits an interior, on scenes nobody tuned it on (`experiments/real_scenes.py`): "
                 "relative RMSE of the indirect light per object over the held-out lightings, the "
                 "references' own noise, each prediction's mean over the reference's, and the path "
                 "tracer's cost. See [Your own scene](../own-scene.md) for the protocol.",
        "make": "python benchmarks/real_scenes.py (one scene: --scene X --merge)",
    },
    "rrf_cornell": {
        "title": "Radiance Regression Functions (Cornell box)",
        "intro": "RRF (Ren et al. 2013) on the Cornell box at the `small` config: held-out indirect RMSE and its "
                 "99.9th percentile, the references' own noise, frame time with one and four lights, "
                 "equal error against Mitsuba, and the experiment's ablations (attribute sets, split rule, "
                 "a single MLP of equal size, training size and spp, robustness over subsets and "
                 "initialisations). See [RRF](../methods/rrf.md).",
        "make": "make bench-rrf",
        "figures": [("rrf_tail_small.png", "reference | RRF | error, the worst 0.1 % of pixel channels in red "
                                           "(experiments/rrf_tail.py, tail.figures)")],
    },
    "sg_lightfield": {
        "title": "SG light-field textures",
        "intro": "SG light-field textures (Currius et al. 2020) at the `small` preset: the CNN's lobes against "
                 "the per-texel baselines at the baked texels and halfway between them, held-out PSNR by "
                 "roughness and lobe count, where the error comes from, float16 storage, the environment "
                 "setting of §5, frame times and equal error against Mitsuba. "
                 "See [SG light-field textures](../methods/sg_lightfield.md).",
        "make": "make bench-sg",
    },
    "sg_environment": {
        "title": "SG environment visibility",
        "intro": "SG environment visibility (Currius et al. 2020, §5) at its default `small` preset: glossy "
                 "receivers of the open-top Cornell box reflecting a distant environment, scored against "
                 "Mitsuba's direct light from held-out views under the map W_E was computed for, the map "
                 "turned and a synthetic sky; the 256^2 frame against its roofline, and equal error. "
                 "See [SG environment visibility](../methods/sg_environment.md).",
        "make": "make bench-sg-environment",
    },
    "sg_shading": {
        "title": "SG light-field textures: shading one lobe",
        "intro": "The run-time shading of SG light-field textures, one light lobe reflected by the GGX BRDF, "
                 "against a float64 brute-force integral over a grid of lobe sharpness, roughness and view "
                 "angle: directions drawn from the lobe alone, the default (broad lobes integrated at "
                 "directions drawn from the BRDF), other bounds between the two, and Appendix B's product. "
                 "See [SG light-field textures](../methods/sg_lightfield.md).",
        "make": "python benchmarks/sg_shading.py",
    },
    "sphere": {
        "title": "Spherical bases",
        "intro": "Cube-map Haar wavelets against PyWavelets, SH projection against a NumPy reference, and the "
                 "error table of the SG x warped-GGX ASG convolution (Currius et al., Appendix B) against "
                 "float64 quadrature, each peer measured in the same run.",
        "make": "make bench",
    },
    "wavelet_prt": {
        "title": "Neural-wavelet PRT",
        "intro": "Neural-wavelet PRT (Raghavan et al. 2023) on the glossy Cornell box with an open top, relit "
                 "by held-out environment maps in several categories: PSNR per map and view distance, "
                 "the ground-truth transport check, frame times and FLOPs, equal error against Mitsuba, "
                 "the speed-accuracy front over MLP width, rank and K, the generalisation variants and the "
                 "ablations. See [Neural-wavelet PRT](../methods/wavelet_prt.md).",
        "make": "make bench-wavelet",
    },
    "wavelet_reruns": {
        "title": "Neural-wavelet PRT reruns",
        "intro": "The `small` model rebuilt twice, each in a fresh process from an empty dataset cache, once "
                 "with XLA's default flags and once with other vector widths and LLVM's optimisation off: "
                 "the spread of held-out PSNR between the two trainings, overall and per map.",
        "make": "python benchmarks/wavelet_reruns.py",
    },
}

GENERATED = ("<!-- Generated by benchmarks/docs_pages.py from benchmarks/results/{name}.json: "
             "do not edit; run `python benchmarks/docs_pages.py`. -->\n")


# ---------------------------------------------------------------------------------------------
# Formatting


def fmt(x) -> str:
    """A JSON scalar as table text: floats to 4 significant digits (integers and large values
    without a fraction), booleans and null spelled out."""
    if x is None:
        return "null"
    if isinstance(x, bool):
        return "true" if x else "false"
    if isinstance(x, int):
        return str(x)
    if isinstance(x, float):
        if math.isnan(x) or math.isinf(x):
            return str(x)
        if x == 0:
            return "0"
        if x == int(x) and abs(x) < 1e15:
            return str(int(x))
        a = abs(x)
        if a >= 1e7:
            return f"{x:.4g}"
        if a >= 1000:
            return f"{x:.0f}"
        if a >= 1e-3:
            return f"{x:.4g}"
        return f"{x:.3e}"
    return text(str(x))


def text(s: str) -> str:
    """A JSON string as Markdown text: characters Markdown would read as markup escaped."""
    s = s.replace("\\", "\\\\").replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")
    for c in "*_`|[]":
        s = s.replace(c, "\\" + c)
    return " ".join(s.split())


def is_leaf(v) -> bool:
    """A value shown in one table cell: a scalar or a short list of scalars."""
    return not isinstance(v, (dict, list)) or (isinstance(v, list) and all(not isinstance(e, (dict, list)) for e in v))


def cell(v) -> str:
    if isinstance(v, list):
        return "[" + ", ".join(fmt(e) for e in v) + "]"
    return fmt(v)


def ordered(d: dict) -> dict:
    """``d`` with numeric keys ("4", "16", "1024") in numeric order; other dicts as written."""
    try:
        return dict(sorted(d.items(), key=lambda kv: float(kv[0])))
    except (TypeError, ValueError):
        return d


def flatten(v, prefix: str = "") -> dict:
    """The leaves of nested dicts under dotted keys (lists of records are not leaves: left out)."""
    out = {}
    for k, x in ordered(v).items():
        key = f"{prefix}{k}"
        if isinstance(x, dict) and x:
            out.update(flatten(x, key + "."))
        elif is_leaf(x):
            out[key] = x
    return out


def union(keysets) -> list:
    seen = {}
    for keys in keysets:
        for k in keys:
            seen.setdefault(k, None)
    return list(seen)


def table(header: list, rows: list) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return lines + [""]


def records_table(records: list[dict], labels: list[str] | None = None) -> list[str]:
    """A table of records: one row per record, one column per (flattened) key; transposed when
    there are few records and many keys."""
    flat = [flatten(r) for r in records]
    keys = union(f.keys() for f in flat)
    labels = labels or [str(i) for i in range(len(records))]
    if len(records) <= 8 and len(keys) > len(records):
        return table([""] + [text(lab) for lab in labels],
                     [[text(k)] + [cell(f[k]) if k in f else "" for f in flat] for k in keys])
    return table(([""] if labels else []) + [text(k) for k in keys],
                 [[text(lab)] + [cell(f[k]) if k in f else "" for k in keys] for lab, f in zip(labels, flat)])


def heading(level: int, title: str) -> list[str]:
    if level <= 6:
        return ["#" * level + " " + text(title), ""]
    return [f"**{text(title)}**", ""]


def alike(dicts: list[dict]) -> bool:
    """Whether sibling dicts are records of one kind (enough of their leaves shared)."""
    sets = [set(flatten(d)) for d in dicts]
    if len(sets) < 2 or not all(sets):
        return False
    common = set.intersection(*sets)
    return len(common) >= 0.5 * len(set.union(*sets))


def block(v, level: int) -> list[str]:
    """A JSON value as Markdown: headings at ``level`` for the parts that need them."""
    if isinstance(v, list):
        if not v:
            return ["(empty)", ""]
        if all(isinstance(e, dict) for e in v):
            return records_table(v)
        if is_leaf(v):
            return [cell(v), ""]
        return ["```json", json.dumps(v, indent=1), "```", ""]
    if not isinstance(v, dict):
        return [fmt(v), ""]
    if not v:
        return ["(empty)", ""]
    v = ordered(v)
    lines = []
    leaves = {k: x for k, x in v.items() if is_leaf(x)}
    columns = [x for x in leaves.values() if isinstance(x, list)]
    if len(leaves) == len(v) and len(leaves) > 1 and len(columns) == len(leaves) and len({len(c) for c in columns}) == 1 \
            and len(columns[0]) > 1:
        # parallel lists: one column each
        lines += table([text(k) for k in leaves], [[fmt(c[i]) for c in columns] for i in range(len(columns[0]))])
        return lines
    if leaves:
        lines += table(["key", "value"], [[text(k), cell(x)] for k, x in leaves.items()])
    dicts = {k: x for k, x in v.items() if isinstance(x, dict) and x}
    if alike(list(dicts.values())):
        lines += records_table(list(dicts.values()), list(dicts))
        for k, x in dicts.items():  # what a flat table cannot hold: lists of records
            for sub, y in _nested_lists(x):
                lines += heading(level, f"{k}: {sub}") + block(y, level + 1)
        rest = {}
    else:
        rest = dicts
    for k, x in v.items():
        if k in leaves or (k in dicts and k not in rest):
            continue
        lines += heading(level, str(k)) + block(x, level + 1)
    return lines


def _nested_lists(d: dict, prefix: str = ""):
    for k, x in d.items():
        if isinstance(x, dict):
            yield from _nested_lists(x, f"{prefix}{k}.")
        elif isinstance(x, list) and not is_leaf(x):
            yield f"{prefix}{k}", x


# ---------------------------------------------------------------------------------------------
# Pages


def context_of(data: dict) -> dict:
    """The run's context (command, date, device, notes) wherever the JSON keeps it."""
    ctx = dict(data.get("context") or {})
    for key in ("command", "commands", "date", "device", "device_kind", "note", "notes", "jax"):
        if key in data and key not in ctx and is_leaf(data[key]):
            ctx[key] = data[key]
    return ctx


def render(name: str, data: dict) -> str:
    """The Markdown page of one benchmark JSON."""
    meta = INTROS.get(name, {})
    lines = [GENERATED.format(name=name), f"# {meta.get('title', name)}", ""]
    if meta.get("intro"):
        lines += [meta["intro"], ""]
    lines += [f"Source: `benchmarks/results/{name}.json`" + (f", written by `{meta['make']}`." if meta.get("make") else "."), ""]
    ctx = context_of(data)
    if ctx:
        lines += heading(2, "Run")
        for k, x in ctx.items():
            if isinstance(x, list):
                lines += [f"**{text(k)}**", ""] + [f"- {text(str(e))}" for e in x] + [""]
            else:
                lines += [f"**{text(k)}**: {cell(x) if not isinstance(x, str) else text(x)}", ""]
    for fig, caption in meta.get("figures", []):
        if os.path.exists(os.path.join(RESULTS, fig)):
            lines += [f"![{text(caption)}]({fig})", "", f"*{text(caption)}*", ""]
    body = {k: x for k, x in data.items() if k != "context" and k not in ctx}
    leaves = {k: x for k, x in body.items() if is_leaf(x)}
    if leaves:
        lines += heading(2, "Results") + table(["key", "value"], [[text(k), cell(x)] for k, x in leaves.items()])
    for k, x in body.items():
        if k not in leaves:
            lines += heading(2, str(k)) + block(x, 3)
    while lines and lines[-1] == "":
        lines.pop()
    return "\n".join(lines) + "\n"


def index(entries: list[tuple[str, dict]]) -> str:
    lines = [GENERATED.format(name="*").replace("results/*.json", "results/*.json (this index)"),
             "# Benchmarks", "",
             "Each page is generated from one JSON in `benchmarks/results/` by `benchmarks/docs_pages.py`: "
             "no number on these pages is typed by hand. A benchmark script writes its JSON (the command "
             "is on each page); `python benchmarks/docs_pages.py` renders the pages again, and "
             "`tests/test_docs.py` fails when a committed page differs from what its JSON renders to. "
             "Timings are of the machine named on each page, against peers measured in the same run; "
             "compare ratios, not milliseconds, across pages.", ""]
    rows = []
    for name, data in entries:
        ctx = context_of(data)
        date = ctx.get("date", "")
        rows.append([f"[{INTROS.get(name, {}).get('title', name)}]({name}.md)", f"`{name}.json`",
                     text(str(date)[:10]) if date else "", text(str(ctx.get("device", ctx.get("device_kind", ""))))])
    lines += table(["benchmark", "file", "date", "device"], rows)
    lines += ["[Every evaluator against its roofline](rooflines.md): the roofline records of all these "
              "JSONs in one table.", ""]
    return "\n".join(lines).rstrip("\n") + "\n"


#: The fraction of its roofline every evaluator is asked to reach (issue 49).
ROOFLINE_TARGET = 0.5


def _rooflines(v, path: tuple = ()):
    """(path, roofline) of every roofline record in a JSON tree: a dict under a key that starts
    with "roofline" and holds ``fraction_of_roofline``."""
    if isinstance(v, dict):
        for k, x in v.items():
            if str(k).startswith("roofline") and isinstance(x, dict) and "fraction_of_roofline" in x:
                yield path + (str(k),), x
            else:
                yield from _rooflines(x, path + (str(k),))
    elif isinstance(v, list):
        for i, x in enumerate(v):
            yield from _rooflines(x, path + (str(i),))


def _times_frames(v) -> bool:
    """Whether a JSON tree times an evaluator's frame (a ``frame_ms`` key anywhere)."""
    if isinstance(v, dict):
        return "frame_ms" in v or any(_times_frames(x) for x in v.values())
    return isinstance(v, list) and any(_times_frames(x) for x in v)


def rooflines(entries: list[tuple[str, dict]]) -> str:
    """The page of every roofline of every benchmark JSON (``_rooflines``), one row each, and the
    JSONs that time a frame without one."""
    lines = [GENERATED.format(name="*").replace("results/*.json", "results/*.json (every roofline)"),
             "# Every evaluator against its roofline", "",
             "Each row is one roofline record found in a benchmark JSON (`jprt.eval.roofline`, or the "
             "method's own through `Method.frame_report`; `roof` says which compute roof it takes: "
             "`matmul` is the f32 matmul rate, `networks` RRF's networks' products timed alone). The "
             "attainable rate is min(compute roof, intensity x bandwidth), with the bandwidth a streaming "
             "triad measured in the same process; the fraction is the frame's achieved rate over it. "
             f"Issue 49 asks every evaluator at its default size for {ROOFLINE_TARGET} or more. Rows "
             "without a `roof` predate the key (a matmul roof). Runs from before the triad wrote into its "
             "own input (CHANGELOG.md, 2026-12-06, afternoon) timed page faults with it and read the "
             "bandwidth several times too low, so their memory-bound fractions are too high (some above "
             "1). Rows without `frame_transcendentals` predate loop-aware counting (CHANGELOG.md, "
             "2026-12-06, from 20:00): XLA's analysis counted a tiled evaluator's loop body once, so their "
             "FLOPs and bytes for a `lax.map` over tiles (SG light-field and SG environment frames) are "
             "one tile's. `stream at its size` is the same triad moving the frame's bytes in one call "
             "(`jprt.eval.stream_at_size`) over the 256 MiB triad's rate: below the target, no single call "
             "moving those bytes reaches the target on the memory roof here (rows before 2026-12-08 lack "
             "it). Each row's date is the run that wrote its JSON.", ""]
    rows, missing = [], []
    for name, data in entries:
        found = list(_rooflines(data))
        date = text(str(context_of(data).get("date", ""))[:10])
        for path, r in found:
            frac = r.get("fraction_of_roofline")
            rows.append([f"[{name}]({name}.md)", text(".".join(path)), text(str(r.get("roof", ""))),
                         text(str(r.get("bound", ""))), fmt(r.get("frame_flops") and r["frame_flops"] / 1e6),
                         fmt(r.get("frame_bytes") and r["frame_bytes"] / 1e6), fmt(r.get("matmul_gflops")),
                         fmt(r.get("bandwidth_gbs")), fmt(r.get("attainable_gflops")), fmt(frac),
                         "" if frac is None else ("yes" if frac >= ROOFLINE_TARGET else "no"),
                         "" if r.get("stream_fraction_at_frame_bytes") is None
                         else fmt(r["stream_fraction_at_frame_bytes"]), date])
        if not found and _times_frames(data):
            missing.append(f"- [{name}]({name}.md) (`{name}.json`, {date or 'undated'})")
    lines += table(["benchmark", "record", "roof", "bound", "MFLOP", "MB", "compute roof GFLOP/s", "GB/s",
                    "attainable GFLOP/s", "fraction", f">= {ROOFLINE_TARGET}", "stream at its size", "date"], rows)
    if missing:
        lines += ["## Timed without a roofline", "",
                  "These JSONs time a frame (`frame_ms`) and carry no roofline yet; their next run adds one.",
                  ""] + missing + [""]
    return "\n".join(lines).rstrip("\n") + "\n"


def pages() -> dict[str, str | bytes]:
    """Every generated file under docs/benchmarks/, by name: the pages (text) and figures (bytes)."""
    entries = []
    for path in sorted(glob.glob(os.path.join(RESULTS, "*.json"))):
        name = os.path.splitext(os.path.basename(path))[0]
        with open(path, encoding="utf-8") as f:
            entries.append((name, json.load(f)))
    out: dict[str, str | bytes] = {"index.md": index(entries), "rooflines.md": rooflines(entries)}
    for name, data in entries:
        out[f"{name}.md"] = render(name, data)
        for fig, _ in INTROS.get(name, {}).get("figures", []):
            src = os.path.join(RESULTS, fig)
            if os.path.exists(src):
                with open(src, "rb") as f:
                    out[fig] = f.read()
    return out


def differences(folder: str = OUT) -> list[str]:
    """Files of ``folder`` that differ from ``pages()``, are missing, or are left over."""
    want = pages()
    bad = []
    for name, content in want.items():
        path = os.path.join(folder, name)
        mode = "rb" if isinstance(content, bytes) else "r"
        if not os.path.exists(path):
            bad.append(f"{name}: missing")
            continue
        with open(path, mode, **({} if mode == "rb" else {"encoding": "utf-8"})) as f:
            if f.read() != content:
                bad.append(f"{name}: differs from what its JSON renders to")
    for path in glob.glob(os.path.join(folder, "*")):
        if os.path.basename(path) not in want:
            bad.append(f"{os.path.basename(path)}: not generated from any JSON")
    return bad


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="compare instead of writing; exit 1 on a difference")
    parser.add_argument("--out", default=OUT, help="the folder of the pages (default docs/benchmarks)")
    args = parser.parse_args(argv)
    if args.check:
        bad = differences(args.out)
        for line in bad:
            print(line, file=sys.stderr)
        return 1 if bad else 0
    os.makedirs(args.out, exist_ok=True)
    want = pages()
    for path in glob.glob(os.path.join(args.out, "*")):
        if os.path.basename(path) not in want:
            os.remove(path)
    for name, content in want.items():
        if isinstance(content, bytes):
            with open(os.path.join(args.out, name), "wb") as f:
                f.write(content)
        else:
            with open(os.path.join(args.out, name), "w", encoding="utf-8") as f:
                f.write(content)
    print(f"wrote {len(want)} files to {os.path.relpath(args.out, ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
