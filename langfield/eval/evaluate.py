"""Evaluation of a trained field on a scene's test views: ``langfield.evaluate(field, scene)``.

The report's top-level keys are fixed by docs/format.md ("Evaluation report"). Text queries are scored as
LangSplat scores them (``eval/evaluate_iou_loc.py``): for every test view and every phrase of its
``segmentations/`` folder, the IoU of the query's mask with the ground truth and the localization hit,
from relevancy maps of exactly decoded rendered latents (a field with a codebook: the entries its
pixels read, ``field.read_entries``, as queries read them; else ``field.decode``; no lattice), pixels the
field leaves empty
taken out as queries do (:func:`langfield.query.fill_empty`); mIoU and mAcc are their means over all
(view, phrase) pairs (:func:`querying.evaluation.summarize_queries`). Metrics the scene or
the field cannot provide (no labels, no feature cache, no language) are ``null``.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from encoders.cache import read_feature_cache
from encoders.protocols import LEVELS, TextEncoder
from encoders.text_table import UnknownPhraseError
from langfield.atomic import atomic_path, check_writable_file
from langfield.eval.geometry import selection_scores
from langfield.eval.view_classes import by_class, classify_views
from langfield.field import LanguageField
from langfield.io.scene import Scene
from langfield.query import Query, fill_empty, make_query, text_encoder_for
from querying.evaluation import query_record, summarize_queries
from querying.metrics import psnr, ssim
from querying.relevancy import relevancy, relevancy_mask
from querying.visualize import contact_sheet, heatmap_overlay, mask_overlay

# Ground truth outline colour in the query pictures (the prediction is querying.visualize's MASK_COLOR).
GT_COLOR = (40, 220, 40)


def evaluate(
    field: LanguageField,
    scene: Scene,
    split: str = "test",
    save_dir: str | Path | None = None,
    text_encoder: TextEncoder | str | Path | None = None,
    oracle: bool = False,
) -> dict:
    """Renders every view of ``split`` and scores it against the scene's images and text labels.

    Args:
        field: a trained field.
        scene: the scene it was trained on (any resolution; the test cameras are rendered as given).
        split: which views to score.
        save_dir: if given, rendered RGB and depth PNGs are written there, and per labelled view a
            contact sheet of the queries (``<view>_queries.png``: heat maps, then masks with the ground
            truth outlined).
        text_encoder: embeds the labels' phrases (see :func:`langfield.query.text_encoder_for`); default
            the field's own.
        oracle: also score the same queries on each view's own mask features (its feature cache), as
            if the field rendered them perfectly: the ceiling of the query pipeline (report key
            ``oracle``: its mIoU and mAcc, and the field's mIoU as a fraction of the oracle's).

    Returns:
        The docs/format.md report as a dict; ``views[i]["queries"]`` is ``{phrase: {"iou", "hit"}}``, and
        with ``oracle`` ``views[i]["oracle_queries"]`` the same on the true features.

    Raises:
        ValueError: a labelled phrase the text encoder does not know (the message names it); with
            ``oracle``, a field without language or a labelled view without a feature cache.
    """
    save = Path(save_dir) if save_dir is not None else None
    names = scene.names(split)
    if oracle:
        check_oracle(field, scene, names)
    labels = {name: scene.segmentations(name) for name in names} if field.decoder is not None else {}
    query = _label_query(field, labels, text_encoder, scene)
    # Before any render: an object name the text encoder lacks stops the evaluation at once.
    selection = selection_scores(field, scene, text_encoder=text_encoder) if query is not None else None
    views, cosines = _score_views(field, scene, names, labels, query, oracle, save)
    m = field.meta
    summary = summarize_queries(q for v in views for q in v["queries"].values())
    oracle_records = [q for v in views for q in v.get("oracle_queries", {}).values()]

    def mean(key: str) -> float | None:
        values = [v[key] for v in views if key in v]
        return float(np.mean(values)) if values else None

    return {
        "PSNR": mean("PSNR"),
        "SSIM": mean("SSIM"),
        "masked_PSNR": mean("masked_PSNR"),
        "masked_SSIM": mean("masked_SSIM"),
        "mIoU": summary["mIoU"],
        "mAcc": summary["mAcc"],
        "train_seconds": m.train_seconds,
        "iterations": m.iterations,
        "iterations_per_second": m.iterations_per_second,
        "num_gaussians": field.num_gaussians,
        "field_bytes": field.field_bytes(),
        "backend": m.backend,
        "feature_cosine": _level_means(cosines),
        "oracle": _oracle_summary(summary, oracle_records) if oracle else None,
        "selection_3d": selection,
        "by_view_class": by_class(views) if views and "view_class" in views[0] else None,
        "views": views,
    }


def _score_views(
    field: LanguageField,
    scene: Scene,
    names: list[str],
    labels: dict,
    query: Query | None,
    oracle: bool,
    save: Path | None,
) -> tuple[list[dict[str, Any]], list[list[float]]]:
    """Every view of :func:`evaluate`: the records, each with its view class, and the feature cosines;
    with ``save``, the contact sheet of the renders."""
    views: list[dict[str, Any]] = []
    cosines: list[list[float]] = []
    sheet_tiles: list[np.ndarray] = []
    sheet_labels: list[str] = []
    with torch.no_grad():
        for name in names:
            record, cosine, tiles = _score_view(field, scene, name, labels.get(name), query, oracle, save)
            views.append(record)
            if cosine is not None:
                cosines.append(cosine)
            sheet_tiles += tiles
            sheet_labels += [f"{name} {record['PSNR']:.2f} dB", "depth", "ground truth"] if tiles else []
    if save is not None and views:
        write_contact_sheet(save / "views_sheet.png", sheet_tiles, sheet_labels, columns=3)
    if views and scene.names("train"):
        classes = classify_views(scene.cameras("train"), [scene.camera(n) for n in names])
        for record in views:
            record["view_class"] = classes[record["name"]]
    return views, cosines


def _score_view(
    field: LanguageField,
    scene: Scene,
    name: str,
    labels: dict | None,
    query: Query | None,
    oracle: bool,
    save: Path | None,
) -> tuple[dict[str, Any], list[float] | None, list[np.ndarray]]:
    """One view of :func:`evaluate`: its record (image scores, ``queries``, ``oracle_queries`` with
    ``oracle``), its per-level feature cosine (None without a feature cache) and, with ``save``, its
    contact-sheet tiles (its PNGs and query sheet written)."""
    camera = scene.camera(name)
    out = field.render(camera)
    target = torch.from_numpy(scene.image(name))
    has_cache = out.latents is not None and scene.feature_paths(name) is not None
    scored = query is not None and out.latents is not None and bool(labels)
    # The codebook entries the pixels read, as queries read them (by vote or nearest).
    entries = (
        field.read_entries(camera, out.latents, out.alpha)
        if (has_cache or scored) and field.codebook is not None
        else None
    )
    truth = true_features(scene, name) if has_cache else None  # read once per view
    cosine = None
    if truth is not None:
        decoded = field.decode_levels(out.latents) if entries is None else field.decode_entries(entries)
        cosine = feature_cosine(decoded, truth)
    queries, extra = {}, {}
    if scored:
        phrases = query.phrases
        maps = query.relevancy_maps(out.latents, exact=True) if entries is None else query.entry_maps(entries)
        maps = fill_empty(maps, out.alpha)  # [P, 3, H, W]
        queries = score_queries(maps, phrases, labels)
        if save is not None:
            write_query_sheet(save, name, out.rgb, maps, phrases, labels, queries)
        if oracle:  # check_oracle made sure every labelled view has its cache
            true_maps = relevancy(truth, query.phrase_embeddings, query.canonical_embeddings)
            true_maps = fill_empty(true_maps, masked_pixels(truth).float())
            extra["oracle_queries"] = score_queries(true_maps, phrases, labels)
    record = {"name": name, "PSNR": psnr(out.rgb, target), "SSIM": ssim(out.rgb, target)}
    object_mask = scene.object_mask(name)
    if object_mask is not None:
        record.update(masked_scores(out.rgb, target, torch.from_numpy(object_mask)))
    tiles: list[np.ndarray] = []
    if save is not None:
        write_render_pngs(save, name, out.rgb.numpy(), out.depth.numpy(), out.alpha.numpy())
        tiles = _view_tiles(out, target)
    return {**record, "queries": queries, **extra}, cosine, tiles


def check_oracle(field: LanguageField, scene: Scene, names: list[str]) -> None:
    """Refuses an oracle evaluation before any work: it needs the field's language and, for every
    labelled view of ``names``, the view's feature cache."""
    if field.decoder is None:
        raise ValueError("--oracle: the field has no language (trained without feature caches)")
    for name in names:
        if scene.segmentations(name) and scene.feature_paths(name) is None:
            raise ValueError(
                f"{scene.root}/language_features/{name}_f.npy: missing; --oracle scores each labelled "
                f"view on its own mask features"
            )


def true_features(scene: Scene, name: str) -> torch.Tensor:
    """[3, H, W, 512] view ``name``'s mask features per level (subpart, part, whole) from its feature
    cache: each pixel carries its mask's feature; zero where the level has no mask (as a LangSplat
    feature cache leaves such pixels). Pixels without a mask at any level count as empty in the oracle
    (:func:`langfield.query.fill_empty`), as the pixels a field leaves empty do."""
    cam = scene.camera(name)
    cache = read_feature_cache(*scene.feature_paths(name), expected_hw=(cam.height, cam.width))
    features = torch.from_numpy(cache.features).float()
    out = torch.zeros(len(LEVELS), *cache.segments[0].shape, features.shape[-1])
    for level in range(len(LEVELS)):
        seg = torch.from_numpy(cache.segments[level].astype(np.int64))
        valid = seg >= 0
        out[level][valid] = features[seg[valid]]
    return out


def masked_pixels(truth: torch.Tensor) -> torch.Tensor:
    """[H, W] bool: the pixels of :func:`true_features` with a mask at some level, those a perfect
    field covers (cache rows are unit vectors, so a masked pixel is never zero)."""
    return (truth != 0).any(-1).any(0)


def _oracle_summary(
    field_summary: dict[str, float | None], records: list[dict[str, float | bool]]
) -> dict[str, float | None]:
    """The oracle's mIoU and mAcc and the field's mIoU as a fraction of the oracle's."""
    summary = summarize_queries(records)
    ratio = None
    if field_summary["mIoU"] is not None and summary["mIoU"]:
        ratio = field_summary["mIoU"] / summary["mIoU"]
    return {**summary, "ratio": ratio}


def masked_scores(rgb: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> dict[str, float]:
    """PSNR and SSIM with the background removed from both images (the DTU protocol of RegNeRF and
    DNGaussian: both set to black outside the object mask, then scored over the whole image).

    Args:
        rgb, target: [H, W, 3] images; mask: [H, W] bool object mask.
    """
    keep = mask.to(rgb.dtype)[..., None]
    return {"masked_PSNR": psnr(rgb * keep, target * keep), "masked_SSIM": ssim(rgb * keep, target * keep)}


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


def _label_query(
    field: LanguageField,
    labels: dict[str, dict[str, np.ndarray]],
    text_encoder: TextEncoder | str | Path | None,
    scene: Scene,
) -> Query | None:
    """The query of every labelled phrase (the same scoring as ``field.query``), or None when the
    scene has no labels or no text encoder can be found (with a warning)."""
    phrases = sorted({phrase for masks in labels.values() for phrase in masks})
    if not phrases:
        return None
    try:
        encoder = text_encoder_for(field, text_encoder)
    except ValueError as err:
        warnings.warn(
            f"{scene.root}/segmentations: text queries not scored (mIoU, mAcc null): {err}", stacklevel=3
        )
        return None
    try:
        return make_query(field, phrases, encoder, scene=scene)
    except UnknownPhraseError as err:
        raise ValueError(f"{scene.root}/segmentations: a labelled phrase has no embedding: {err}") from err


def score_queries(
    maps: torch.Tensor, phrases: list[str], labels: dict[str, np.ndarray]
) -> dict[str, dict[str, float | bool]]:
    """``{phrase: {"iou", "hit"}}`` of one view (docs/format.md).

    Args:
        maps: [P, 3, H, W] relevancy of every phrase of ``phrases`` in the view.
        phrases: the phrases of ``maps``' rows.
        labels: {phrase: [H, W] bool ground-truth mask} of the view.
    """
    return {
        phrase: query_record(maps[phrases.index(phrase)], torch.from_numpy(gt))
        for phrase, gt in sorted(labels.items())
    }


def write_query_sheet(
    folder: Path,
    name: str,
    rgb: torch.Tensor,
    maps: torch.Tensor,
    phrases: list[str],
    labels: dict[str, np.ndarray],
    queries: dict[str, dict[str, float | bool]],
) -> Path:
    """``<name>_queries.png``: per labelled phrase, its heat map (top row) and its mask with the ground
    truth outlined in green (bottom row), labelled with the IoU and whether localization hit."""
    folder.mkdir(parents=True, exist_ok=True)
    order = sorted(labels)
    result = relevancy_mask(maps[[phrases.index(p) for p in order]])
    heats, masks, captions = [], [], []
    for i, phrase in enumerate(order):
        heats.append(heatmap_overlay(rgb, result.normalized[i]))
        outlined = mask_overlay(rgb, labels[phrase], color=GT_COLOR, alpha=0.0)
        masks.append(mask_overlay(outlined, result.mask[i]))
        record = queries[phrase]
        captions.append(f"IoU {record['iou']:.2f} {'hit' if record['hit'] else 'miss'}")
    sheet = contact_sheet(heats + masks, order + captions, columns=len(order))
    path = folder / f"{name}_queries.png"
    cv2.imwrite(str(path), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
    return path


def feature_cosine(decoded: torch.Tensor, truth: torch.Tensor) -> list[float]:
    """Per level, the mean cosine between decoded rendered latents and the view's mask features.

    Args:
        decoded: [3, H, W, 512] decoded rendered latents of a view (``field.decode_levels(latents)``).
        truth: [3, H, W, 512] the view's mask features (:func:`true_features`), zero without a mask.

    Returns:
        Three numbers (subpart, part, whole), averaged over the pixels that have a mask at that level;
        NaN for a level without masks.
    """
    result = []
    for level in range(len(LEVELS)):
        valid = (truth[level] != 0).any(-1)
        if not valid.any():
            result.append(float("nan"))
            continue
        cos = (decoded[level] * truth[level]).sum(-1)
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


def _view_tiles(out, target: torch.Tensor) -> list[np.ndarray]:
    """The render, its depth and the ground truth of one view, as uint8 RGB tiles."""
    as_uint8 = lambda image: (np.clip(np.asarray(image), 0, 1) * 255 + 0.5).astype(np.uint8)  # noqa: E731
    depth = cv2.cvtColor(depth_to_png(out.depth.numpy(), out.alpha.numpy()), cv2.COLOR_BGR2RGB)
    return [as_uint8(out.rgb), depth, as_uint8(target)]


def write_contact_sheet(path: Path, tiles: list[np.ndarray], labels: list[str], columns: int) -> Path:
    """A labelled grid of RGB tiles as a PNG (``querying.visualize.contact_sheet``)."""
    sheet = contact_sheet(tiles, labels, columns=columns)
    ok, encoded = cv2.imencode(".png", cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
    if not ok:
        raise ValueError(f"{path}: OpenCV could not encode the contact sheet")
    with atomic_path(path) as tmp:
        tmp.write_bytes(encoded.tobytes())
    return path


def write_render_pngs(folder: Path, name: str, rgb: np.ndarray, depth: np.ndarray, alpha: np.ndarray) -> None:
    """Writes ``<name>_rgb.png`` and ``<name>_depth.png`` into ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    bgr = (np.clip(rgb, 0, 1)[..., ::-1] * 255 + 0.5).astype(np.uint8)
    cv2.imwrite(str(folder / f"{name}_rgb.png"), bgr)
    cv2.imwrite(str(folder / f"{name}_depth.png"), depth_to_png(depth, alpha))


def _class_lines(classes: dict | None) -> list[str]:
    """The summary's table of PSNR per view class (near a training view, between them, beyond them)."""
    if not classes:
        return []
    lines = ["| view class | views | PSNR | SSIM | masked PSNR |", "|---|---|---|---|---|"]
    for kind, c in classes.items():
        scores = f"{_fmt(c['PSNR'], 2)} | {_fmt(c['SSIM'])} | {_fmt(c['masked_PSNR'], 2)}"
        lines.append(f"| {kind} | {c['views']} | {scores} |")
    return lines + [""]


def write_report(report: dict, json_path: str | Path, pictures: str | Path | None = None) -> Path:
    """Writes the JSON report and a Markdown summary beside it; returns the Markdown path."""
    json_path = check_writable_file(json_path, "report")
    md = check_writable_file(json_path.with_suffix(".md"), "summary")
    with atomic_path(json_path) as tmp:
        tmp.write_text(json.dumps(report, indent=2))
    lines = ["# langfield evaluation", ""]
    lines += [
        "| PSNR | SSIM | mIoU | mAcc | train s | iterations | it/s | Gaussians | field bytes | backend |",
        "|---|---|---|---|---|---|---|---|---|---|",
        "| "
        + " | ".join(
            _fmt(report[k], 2 if k in ("PSNR", "train_seconds", "iterations_per_second") else 3)
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
    ]
    lines += _oracle_and_selection_lines(report)
    lines += _class_lines(report.get("by_view_class"))
    lines += [
        "| view | class | PSNR | SSIM | mIoU | mAcc |",
        "|---|---|---|---|---|---|",
    ]
    for v in report["views"]:
        per_view = summarize_queries(v["queries"].values())
        kind = v.get("view_class", {}).get("class", "n/a")
        lines.append(
            f"| {v['name']} | {kind} | {v['PSNR']:.2f} | {v['SSIM']:.3f} | "
            f"{_fmt(per_view['mIoU'])} | {_fmt(per_view['mAcc'])} |"
        )
    lines += _phrase_table(report["views"])
    if pictures is not None:
        lines += _picture_lines(report, Path(pictures), md.parent)
    with atomic_path(md) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    return md


def _fmt(v: Any, digits: int = 3) -> str:
    return "n/a" if v is None else (f"{v:.{digits}f}" if isinstance(v, float) else str(v))


def _oracle_and_selection_lines(report: dict) -> list[str]:
    lines: list[str] = []
    oracle = report.get("oracle")
    if oracle:
        lines += [
            "Oracle (the same queries on each view's own mask features, the query pipeline's ceiling): "
            f"mIoU {_fmt(oracle['mIoU'])}, mAcc {_fmt(oracle['mAcc'])}; the field reaches "
            f"{_fmt(oracle['ratio'], 2)} of its mIoU.",
            "",
        ]
    selection = report.get("selection_3d")
    if selection and selection["precision"] is not None:
        lines += [
            f"3D selection (`field.query(o).gaussians()` against each object's surface, within "
            f"{selection['tolerance']:.3f}): precision {_fmt(selection['precision'])}, recall "
            f"{_fmt(selection['recall'])}; precision among the selected Gaussians that lie on a surface "
            f"{_fmt(selection['surface_precision'])} ({_fmt(selection['off_surface'])} of all Gaussians "
            "lie on none).",
            "",
            "| object | precision | recall | surface precision | selected | the object's Gaussians |",
            "|---|---|---|---|---|---|",
        ]
        lines += [
            f"| {name} | {_fmt(o['precision'])} | {_fmt(o['recall'])} | {_fmt(o['surface_precision'])} "
            f"| {o['selected']} | {o['gaussians']} |"
            for name, o in selection["objects"].items()
        ]
        lines.append("")
    return lines


def _picture_lines(report: dict, pictures: Path, where: Path) -> list[str]:
    """Markdown image links to the renders and query sheets in ``pictures``, relative to ``where``."""
    lines: list[str] = []
    rel = pictures.resolve()
    lines += ["", "## Renders (RGB, depth)", ""]
    sheet = rel / "views_sheet.png"
    if sheet.exists():
        lines += [f"![every view: render, depth, ground truth]({_relative(sheet, where)})", ""]
    for v in report["views"]:
        for kind in ("rgb", "depth"):
            p = rel / f"{v['name']}_{kind}.png"
            if p.exists():
                lines.append(f"![{v['name']} {kind}]({_relative(p, where)})")
    sheets = [(v["name"], rel / f"{v['name']}_queries.png") for v in report["views"]]
    sheets = [(name, p) for name, p in sheets if p.exists()]
    if sheets:
        lines += ["", "## Text queries (heat maps; masks, ground truth outlined in green)", ""]
        lines += [f"![{name} queries]({_relative(p, where)})" for name, p in sheets]
    return lines


def _phrase_table(views: list[dict[str, Any]]) -> list[str]:
    """Markdown rows of each labelled phrase's mean IoU and hit rate over the views that label it."""
    phrases = sorted({phrase for v in views for phrase in v["queries"]})
    if not phrases:
        return []
    lines = ["", "| phrase | views | mIoU | mAcc |", "|---|---|---|---|"]
    for phrase in phrases:
        records = [v["queries"][phrase] for v in views if phrase in v["queries"]]
        summary = summarize_queries(records)
        lines.append(f"| {phrase} | {len(records)} | {summary['mIoU']:.3f} | {summary['mAcc']:.3f} |")
    return lines


def _relative(path: Path, start: Path) -> str:
    try:
        return str(path.relative_to(start.resolve()))
    except ValueError:
        return str(path)
