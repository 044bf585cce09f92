"""Evaluation of a trained field on a scene's test views: ``langfield.evaluate(field, scene)``.

The report's top-level keys are fixed by FORMAT.md ("Evaluation report"). Metrics that need a later
stage (mIoU, mAcc, feature cosine) are ``null`` until the field can provide them.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from encoders.cache import read_feature_cache
from encoders.protocols import LEVELS
from langfield.field import LanguageField
from langfield.scene import Scene
from querying.metrics import psnr, ssim


def evaluate(
    field: LanguageField, scene: Scene, split: str = "test", save_dir: str | Path | None = None
) -> dict:
    """Renders every view of ``split`` and scores it against the scene's images.

    Args:
        field: a trained field.
        scene: the scene it was trained on (any resolution; the test cameras are rendered as given).
        split: which views to score.
        save_dir: if given, rendered RGB and depth PNGs are written there.

    Returns:
        The FORMAT.md report as a dict.
    """
    views: list[dict[str, Any]] = []
    cosines: list[list[float]] = []
    save = Path(save_dir) if save_dir is not None else None
    with torch.no_grad():
        for name in scene.names(split):
            out = field.render(scene.camera(name))
            target = torch.from_numpy(scene.image(name))
            if out.latents is not None and scene.feature_paths(name) is not None:
                cosines.append(feature_cosine(field, out.latents, scene, name))
            views.append(
                {"name": name, "PSNR": psnr(out.rgb, target), "SSIM": ssim(out.rgb, target), "queries": {}}
            )
            if save is not None:
                write_render_pngs(save, name, out.rgb.numpy(), out.depth.numpy(), out.alpha.numpy())
    m = field.meta

    def mean(key: str) -> float | None:
        return float(np.mean([v[key] for v in views])) if views else None

    return {
        "PSNR": mean("PSNR"),
        "SSIM": mean("SSIM"),
        "mIoU": None,
        "mAcc": None,
        "train_seconds": m.get("train_seconds"),
        "iterations": m.get("iterations"),
        "iterations_per_second": m.get("iterations_per_second"),
        "num_gaussians": field.num_gaussians,
        "field_bytes": field.field_bytes(),
        "backend": m.get("backend"),
        "feature_cosine": _level_means(cosines),
        "views": views,
    }


def _level_means(rows: list[list[float]]) -> dict[str, float | None] | None:
    """Mean of each level over views, ignoring views without masks at that level (None if none has)."""
    if not rows:
        return None
    table = np.asarray(rows, dtype=np.float64)
    means = {}
    for i, level in enumerate(LEVELS):
        col = table[:, i][np.isfinite(table[:, i])]
        means[level] = float(col.mean()) if col.size else None
    return means


def feature_cosine(field: LanguageField, latents: torch.Tensor, scene: Scene, name: str) -> list[float]:
    """Per level, the mean cosine between decoded rendered latents and the view's mask features.

    Args:
        latents: [3, H, W, 3] rendered latents of view ``name``.

    Returns:
        Three numbers (subpart, part, whole), averaged over the pixels that have a mask at that level;
        NaN for a level without masks.
    """
    cam = scene.camera(name)
    cache = read_feature_cache(*scene.feature_paths(name), expected_hw=(cam.height, cam.width))
    decoded = field.decode(latents)  # [3, H, W, 512]
    features = torch.from_numpy(cache.features)
    result = []
    for level in range(len(LEVELS)):
        seg = torch.from_numpy(cache.segments[level].astype(np.int64))
        valid = seg >= 0
        if not valid.any():
            result.append(float("nan"))
            continue
        cos = (decoded[level] * features[seg.clamp_min(0)]).sum(-1)
        result.append(float(cos[valid].mean()))
    return result


def depth_to_png(depth: np.ndarray, alpha: np.ndarray | None = None) -> np.ndarray:
    """Colour-mapped 8-bit BGR picture of a depth map, near = bright, normalised over covered pixels."""
    valid = np.isfinite(depth) & ((alpha > 0.5) if alpha is not None else (depth > 0))
    d = depth / np.maximum(alpha, 1e-6) if alpha is not None else depth
    lo, hi = np.percentile(d[valid], [1, 99]) if valid.any() else (0.0, 1.0)
    norm = np.clip((d - lo) / max(hi - lo, 1e-8), 0, 1)
    img = cv2.applyColorMap(((1 - norm) * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    img[~valid] = 0
    return img


def write_render_pngs(folder: Path, name: str, rgb: np.ndarray, depth: np.ndarray, alpha: np.ndarray) -> None:
    """Writes ``<name>_rgb.png`` and ``<name>_depth.png`` into ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    bgr = (np.clip(rgb, 0, 1)[..., ::-1] * 255 + 0.5).astype(np.uint8)
    cv2.imwrite(str(folder / f"{name}_rgb.png"), bgr)
    cv2.imwrite(str(folder / f"{name}_depth.png"), depth_to_png(depth, alpha))


def write_report(report: dict, json_path: str | Path, pictures: str | Path | None = None) -> Path:
    """Writes the JSON report and a Markdown summary beside it; returns the Markdown path."""
    json_path = Path(json_path)
    json_path.parent.mkdir(parents=True, exist_ok=True)
    tmp = json_path.with_name(json_path.name + ".tmp")
    tmp.write_text(json.dumps(report, indent=2))
    tmp.replace(json_path)
    md = json_path.with_suffix(".md")
    lines = ["# langfield evaluation", ""]

    def fmt(v: Any, digits: int = 3) -> str:
        return "n/a" if v is None else (f"{v:.{digits}f}" if isinstance(v, float) else str(v))

    lines += [
        "| PSNR | SSIM | mIoU | mAcc | train s | iterations | it/s | Gaussians | field bytes | backend |",
        "|---|---|---|---|---|---|---|---|---|---|",
        "| "
        + " | ".join(
            fmt(report[k], 2 if k in ("PSNR", "train_seconds", "iterations_per_second") else 3)
            for k in (
                "PSNR",
                "SSIM",
                "mIoU",
                "mAcc",
                "train_seconds",
                "iterations",
                "iterations_per_second",
                "num_gaussians",
                "field_bytes",
                "backend",
            )
        )
        + " |",
        "",
        "| view | PSNR | SSIM |",
        "|---|---|---|",
    ]
    lines += [f"| {v['name']} | {v['PSNR']:.2f} | {v['SSIM']:.3f} |" for v in report["views"]]
    if pictures is not None:
        rel = Path(pictures).resolve()
        lines += ["", "## Renders (RGB, depth)", ""]
        for v in report["views"]:
            for kind in ("rgb", "depth"):
                p = rel / f"{v['name']}_{kind}.png"
                if p.exists():
                    lines.append(f"![{v['name']} {kind}]({_relative(p, md.parent)})")
    md.write_text("\n".join(lines) + "\n")
    return md


def _relative(path: Path, start: Path) -> str:
    try:
        return str(path.relative_to(start.resolve()))
    except ValueError:
        return str(path)
