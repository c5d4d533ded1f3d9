"""Ground-truth reports: a rendered dataset written out as EXR, PNG previews, a contact sheet and JSON."""

from __future__ import annotations

import os
import time

import numpy as np

from jprt import io
from jprt.config import save_resolved
from jprt.metrics import tonemap
from jprt.render.dataset import from_config

__all__ = ["write_ground_truth"]


def _normal_preview(normal: np.ndarray, valid: np.ndarray) -> np.ndarray:
    return np.where(valid[..., None], 0.5 * (normal + 1.0), 0.0)


def write_ground_truth(config: dict) -> dict:
    """Render (or reuse) ``config['dataset']`` and write per item direct / indirect / full EXRs,
    G-buffer EXRs (position, normal, uv, albedo, roughness, object id, valid), PNG previews, a
    contact sheet and ``summary.json`` under ``config['output']['dir']/<config hash>/``.

    Returns the summary dict.
    """
    t0 = time.perf_counter()
    ds = from_config(config["dataset"])
    render_s = time.perf_counter() - t0
    from jprt.hashing import config_hash

    out = os.path.join(config["output"]["dir"], config_hash(config))
    os.makedirs(out, exist_ok=True)
    save_resolved(config, out)
    exposure = float(config["output"].get("exposure", 0.0))

    items = []
    sheet_rows = []
    for k, it in enumerate(ds.items):
        rad = ds.radiance(k)
        full = rad["direct"] + rad["indirect"]
        stem = f"light{it.lighting:02d}_view{it.camera:02d}"
        for name, image in (("direct", rad["direct"]), ("indirect", rad["indirect"]), ("full", full)):
            io.write_exr(os.path.join(out, f"{stem}_{name}.exr"), image)
            io.write_png(os.path.join(out, f"{stem}_{name}.png"), image, exposure=exposure)
        gb = ds.gbuffer(it.camera) if ds.spec["render"]["gbuffers"] else None
        items.append({
            "lighting": it.lighting,
            "camera": it.camera,
            "direct_mean_rgb": rad["direct"].mean(axis=(0, 1)).tolist(),
            "indirect_mean_rgb": rad["indirect"].mean(axis=(0, 1)).tolist(),
            "indirect_fraction": float(rad["indirect"].mean() / max(full.mean(), 1e-30)),
            "indirect_min": float(rad["indirect"].min()),
            "valid_fraction": float(gb.valid.mean()) if gb is not None else None,
        })
        sheet_rows.append((stem, rad["direct"], rad["indirect"], full,
                           _normal_preview(gb.normal, gb.valid) if gb is not None else None))
    if ds.spec["render"]["gbuffers"]:
        for ci in range(len(ds.cameras)):
            gb = ds.gbuffer(ci)
            stem = f"gbuffer_view{ci:02d}"
            io.write_exr(os.path.join(out, f"{stem}_position.exr"), gb.position)
            io.write_exr(os.path.join(out, f"{stem}_normal.exr"), gb.normal)
            io.write_exr(os.path.join(out, f"{stem}_albedo.exr"), gb.diffuse_albedo)
            io.write_exr(os.path.join(out, f"{stem}_attributes.exr"),
                         np.stack([gb.uv[..., 0], gb.uv[..., 1], gb.roughness, gb.object_id.astype(np.float32),
                                   gb.valid.astype(np.float32)], axis=-1),
                         channels=["u", "v", "roughness", "object_id", "valid"])
            io.write_png(os.path.join(out, f"{stem}_normal.png"), _normal_preview(gb.normal, gb.valid), tonemapped=True)
    sheet = os.path.join(out, "contact_sheet.png")
    _contact_sheet(sheet, sheet_rows, exposure)
    summary = {
        "dataset": ds.folder,
        "dataset_stats": ds.stats,
        "spp": ds.spec["render"]["spp"],
        "resolution": [ds.cameras[0].width, ds.cameras[0].height],
        "n_items": len(ds),
        "render_s": render_s,
        "total_s": time.perf_counter() - t0,
        "items": items,
        "contact_sheet": sheet,
    }
    io.write_json(os.path.join(out, "summary.json"), summary)
    print(f"ground truth: {len(ds)} items ({ds.stats['rendered']} entries rendered, {ds.stats['cached']} reused) "
          f"in {summary['total_s']:.1f} s")
    print(f"wrote images, contact sheet and summary to {os.path.abspath(out)}")
    return summary


def _contact_sheet(path: str, rows, exposure: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = ["direct", "indirect", "full", "normal"]
    fig, axes = plt.subplots(len(rows), 4, figsize=(10, 2.6 * len(rows)), squeeze=False)
    for r, (stem, direct, indirect, full, normal) in enumerate(rows):
        for c, image in enumerate((direct, indirect, full, normal)):
            ax = axes[r, c]
            ax.axis("off")
            if image is None:
                continue
            shown = image if c == 3 else np.asarray(tonemap(image, exposure))
            ax.imshow(np.clip(shown, 0, 1), interpolation="nearest")
            ax.set_title(f"{stem} {cols[c]}" if c == 0 else cols[c], fontsize=8)
    fig.tight_layout()
    with io.atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=80, format="png")
    plt.close(fig)
