"""``langfield ablate SCENE``: the paper's Table 3 cases on one scene, same seed and budget, one table.

Cases (each a :class:`~langfield.training.config.TrainConfig` change from the full method):

- ``full``: hash-grid language features, LAD (eq. 6-11) and LOP (eq. 14-16);
- ``no-lop``: without language-guided outlier pruning;
- ``no-lad``: the plain global depth loss only (no per-mask normalisation);
- ``no-depth``: without L_D;
- ``per-gaussian``: one learnable latent per Gaussian instead of the hash grid (LangSplat's way);
- ``paper-language``: the paper's autoencoder (eq. 2 alone, no spread term), its L_LF (every pixel
  alike, no mask balance) and its reading of a rendered latent (decoded as it is, no codebook);
- ``no-opacity-reg`` (not in the default set): without the L1 opacity penalty (``lambda_opacity=0``);
- ``baseline`` (not in the default set): per-Gaussian latents, no L_D, no LOP: LangSplat's way with
  the sparse-view training, the reference the full method is measured against.

The sparse-view switches (:mod:`langfield.training.regularisers`,
:mod:`langfield.training.start`), each one change from the defaults:

- ``random-init``, ``sfm-init``, ``depth-init``: another start than the default's (``init="auto"``:
  the depth prior where every training view has one, else the plane-sweep points); ``mean-sweep``:
  the sweep's score the mean over the other views rather than the best one's; ``fronto-sweep``: the
  sweep's planes fronto-parallel only (not also tilted);
- ``no-dropout``: without Gaussian dropout; ``no-virtual``: without the virtual-view consistency term;
  ``no-random-background``: the scene's own background colour in every iteration;
  ``no-empty-space``: no use of the empty space the photos show (alpha, a black backdrop);
  ``no-opacity-decay``: without Binocular-guided 3DGS's opacity decay;
- ``opacity-noise`` (off by default): Co-Adaptation's opacity noise at s = 0.2;
- ``orbit``, ``orbit-wide``: the virtual camera orbits the rendered depth instead of shifting, at the
  default baseline and at 0.3 (views beyond the training cameras); ``both-motions``: it orbits or
  shifts, at random;
- ``direction-frequencies``: the colour MLP with NeRF's 4 frequencies of the view direction (the
  default takes the direction alone); ``no-direction``: without the direction (a colour the same from
  every side);
- ``depth-baseline``: the virtual camera's shift a tenth of the rendered depth, not sized by the
  training cameras' spacing where that is longer; ``virtual-occlusion``: the shifted view's occluded
  pixels left out of the virtual-view term;
- ``anisotropy``, ``smooth`` (off by default, measured without effect): with the anisotropy penalty,
  with edge-aware depth smoothness; ``stereo`` (off by default): the start's stereo depth on the
  rendered depth at weight 1.

Cases that would train ``full`` again are skipped with a warning: those that need what a scene lacks
(language features, depth priors, an opaque background), and those equal to the base settings.
``GEOMETRY_CASES`` are the sparse-view set.

Each row: mIoU / mAcc (where the scene has labels and querying can score them), PSNR and SSIM on test
views (masked PSNR where the scene has object masks), aligned depth error and floaters (scenes with
ground truth), the training views' depth agreement (:func:`~langfield.eval.geometry.depth_agreement`),
training seconds and Gaussians.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import replace
from pathlib import Path
from typing import Any

from langfield.atomic import atomic_path, check_writable_file
from langfield.eval.evaluate import evaluate
from langfield.eval.geometry import count_floaters, depth_agreement, depth_errors
from langfield.eval.view_classes import VIEW_CLASSES
from langfield.field import check_output_folder
from langfield.io.scene import Scene
from langfield.training.config import TrainConfig
from langfield.training.loop import train
from langfield.training.targets import check_inputs, empty_space

CASES: dict[str, dict[str, Any]] = {
    "full": {},
    "no-lop": {"lop": False},
    "no-lad": {"lad": False},
    "no-depth": {"depth": False},
    "per-gaussian": {"language_features": "per-gaussian"},
    "paper-language": {"autoencoder_spread": 0.0, "language_balance": 0.0, "language_decode": "continuous"},
    "no-opacity-reg": {"lambda_opacity": 0.0},
    "baseline": {"language_features": "per-gaussian", "depth": False, "lop": False},
    "random-init": {"init": "random"},
    "sfm-init": {"init": "sfm"},
    "depth-init": {"init": "depth"},
    "mean-sweep": {"init_sweep": "mean"},
    "fronto-sweep": {"init_planes": "fronto"},
    "no-dropout": {"drop_gamma": 0.0},
    "opacity-noise": {"opacity_noise": 0.2},
    "orbit": {"virtual_motion": "orbit"},
    "orbit-wide": {"virtual_motion": "orbit", "virtual_baseline": 0.3},
    "both-motions": {"virtual_motion": "both"},
    "direction-frequencies": {"color_freqs": 4},
    "no-direction": {"color_freqs": -1},
    "depth-baseline": {"virtual_spacing": 0.0},
    "virtual-occlusion": {"virtual_occlusion": True},
    "no-virtual": {"lambda_virtual": 0.0},
    "no-random-background": {"random_background": False},
    "no-empty-space": {"dark_backdrop": False, "lambda_empty": 0.0},
    "no-opacity-decay": {"opacity_decay": 1.0},
    "anisotropy": {"lambda_anisotropy": 0.01},
    "smooth": {"lambda_smooth": 0.1},
    "carve": {"carve_free_space": True},
    "visibility": {"lambda_visibility": 0.5},
    "crossview": {"lambda_crossview": 0.2},
    "co-training": {"co_train": True},
    "stereo": {"lambda_stereo": 1.0},
    "full-resolution": {"half_resolution_until": 0.0},
    "virtual-every-step": {"virtual_every": 1},
    "half-size-virtual": {"virtual_resolution": 0.5},
}
LANGUAGE_CASES = ("no-lop", "per-gaussian", "paper-language", "baseline")
DEPTH_CASES = ("no-lad", "no-depth", "depth-init")
EMPTY_CASES = ("no-empty-space",)  # only scenes whose photos show empty space (alpha, a black backdrop)
# The sparse-view set: each of the geometry switches off in turn.
GEOMETRY_CASES = (
    "full",
    "random-init",
    "no-dropout",
    "no-virtual",
    "no-random-background",
    "no-empty-space",
    "no-opacity-decay",
)
DEFAULT_CASES = (
    "full",
    "no-lop",
    "no-lad",
    "no-depth",
    "per-gaussian",
    "paper-language",
    *GEOMETRY_CASES[1:],
)


def run_case(
    scene: Scene, cfg: TrainConfig, out: Path | None = None, progress: bool = True, overwrite: bool = False
) -> dict:
    """Trains one configuration and returns its table row (and saves the field to ``out`` if given)."""
    if out is not None:
        check_output_folder(out, overwrite)
    field = train(scene, cfg, progress=progress)
    if out is not None:
        field.save(out, overwrite=overwrite)
    report = evaluate(field, scene)
    depth = depth_errors(field, scene)
    floaters = count_floaters(field, scene)
    agreement = depth_agreement(field, scene)
    return {
        "mIoU": report.get("mIoU"),
        "mAcc": report.get("mAcc"),
        "PSNR": report["PSNR"],
        "SSIM": report["SSIM"],
        "masked_PSNR": report.get("masked_PSNR"),
        **class_psnr(report),
        "depth_abs_rel": None if depth is None else depth["abs_rel"],
        "floaters": None if floaters is None else floaters["floaters"],
        "depth_agreement": None if agreement is None else agreement["agreement"],
        "train_seconds": field.meta.train_seconds,
        "iterations": field.meta.iterations,
        "ms_per_iteration": 1000 * field.meta.train_seconds / max(field.meta.iterations, 1),
        "num_gaussians": field.num_gaussians,
        "lop_removed": field.meta.lop_removed,
    }


def class_psnr(report: dict) -> dict[str, float | None]:
    """``PSNR_near``, ``PSNR_between``, ``PSNR_beyond``: the mean PSNR of each view class
    (:mod:`langfield.eval.view_classes`), masked where the scene has object masks (as its headline)."""
    classes = report.get("by_view_class") or {}
    key = "masked_PSNR" if report.get("masked_PSNR") is not None else "PSNR"
    return {f"PSNR_{kind}": classes.get(kind, {}).get(key) for kind in VIEW_CLASSES}


def run_ablation(
    scene: Scene,
    base: TrainConfig,
    cases: tuple[str, ...] = DEFAULT_CASES,
    out_dir: str | Path | None = None,
    progress: bool = True,
    overwrite: bool = False,
) -> dict[str, dict]:
    """Runs ``cases`` with ``base``'s seed and budget; returns {case: row}; writes ablation.json/.md.

    Every case's settings, the scene's files and the output folders are checked before the first
    case trains; a case folder that holds a field is an error unless ``overwrite``.
    """
    unknown = [c for c in cases if c not in CASES]
    if unknown:
        raise ValueError(f"unknown ablation case(s) {unknown}; choose from {', '.join(CASES)}")
    out = Path(out_dir) if out_dir is not None else None
    names = scene.names("train")
    has_language = base.language is not False and all(scene.feature_paths(n) is not None for n in names)
    has_depth = base.depth is not False and all(scene.depth_path(n) is not None for n in names)
    # A case that would train `full` again: it needs what the scene lacks (language features, depth
    # priors, empty space in its photos), or it changes nothing from `base`.
    shows_empty_space = empty_space(scene, base)[1] is not None
    skipped = [
        c
        for c in cases
        if (c in LANGUAGE_CASES and not has_language)
        or (c in DEPTH_CASES and not has_depth)
        or (c in EMPTY_CASES and not shows_empty_space)
        or (c != "full" and replace(base, **CASES[c]) == base)
    ]
    if skipped:
        warnings.warn(
            f"{scene.root}: cases {skipped} would train full again here (the scene lacks language "
            "features, depth priors or empty space in its photos, or the base settings already have them); "
            "skipped",
            stacklevel=2,
        )
    cases = tuple(c for c in cases if c not in skipped)
    configs = {case: replace(base, **CASES[case]) for case in cases}
    if out is not None:
        for name in ("ablation.json", "ablation.md"):
            check_writable_file(out / name, "table")
        for case in cases:
            check_output_folder(out / case, overwrite)
    check_inputs(scene, base, progress=progress)
    rows: dict[str, dict] = {}
    for case, cfg in configs.items():
        rows[case] = run_case(scene, cfg, None if out is None else out / case, progress, overwrite)
        if out is not None:  # written after every case: an interrupted run keeps what it measured
            write_table(rows, out, base)
    return rows


def format_table(rows: dict[str, dict]) -> str:
    """A Markdown table of the rows."""

    def fmt(v: Any, digits: int) -> str:
        return "n/a" if v is None else f"{v:.{digits}f}" if isinstance(v, float) else str(v)

    head = (
        "| case | mIoU | mAcc | PSNR | SSIM | masked PSNR | depth AbsRel | floaters | depth agreement "
        "| Gaussians | s | ms/it |"
    )
    lines = [head, "|" + "---|" * 12]
    for case, r in rows.items():
        lines.append(
            f"| {case} | {fmt(r['mIoU'], 3)} | {fmt(r['mAcc'], 3)} | {fmt(r['PSNR'], 2)} | "
            f"{fmt(r['SSIM'], 3)} | {fmt(r.get('masked_PSNR'), 2)} | {fmt(r['depth_abs_rel'], 4)} | "
            f"{fmt(r['floaters'], 0)} | {fmt(r.get('depth_agreement'), 3)} | "
            f"{r['num_gaussians']} | {r['train_seconds']:.0f} | {r['ms_per_iteration']:.0f} |"
        )
    return "\n".join(lines)


def write_table(rows: dict[str, dict], out: Path, base: TrainConfig) -> None:
    lengths = sorted({r["iterations"] for r in rows.values() if "iterations" in r})
    iterations = base.iterations
    if iterations is None and len(lengths) == 1:  # scene-sized: every case ran the same length
        iterations = lengths[0]
    meta = {"iterations": iterations, "seed": base.seed, "rows": rows}
    with atomic_path(out / "ablation.json") as tmp:
        tmp.write_text(json.dumps(meta, indent=2) + "\n")
    with atomic_path(out / "ablation.md") as tmp:
        sized = "" if base.iterations is not None else ", sized by the scene"
        title = f"# Ablation ({iterations} iterations{sized}, seed {base.seed})"
        tmp.write_text(f"{title}\n\n{format_table(rows)}\n")
