"""The ``langfield export`` and ``langfield preprocess`` subcommands (real foundation models via ONNX).

``add_parsers(subparsers)`` registers both on the main parser of :mod:`langfield.cli`; each parser's
``func`` takes the parsed arguments and returns the exit status. As in the rest of the CLI, long work
shows a progress bar and ends with a one-line summary, and errors name the file or argument.

    langfield export clip --model ViT-B-16 --checkpoint open_clip_pytorch_model.bin --out models/clip
    langfield export sam --model vit_b --checkpoint sam_vit_b_01ec64.pth --out models/sam
    langfield export depth --checkpoint Depth-Anything-V2-Small-hf --out models/depth
    langfield preprocess data/room --models models
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

__all__ = ["add_parsers", "cmd_export", "cmd_preprocess"]

_SAM_TYPES = ("vit_b", "vit_l", "vit_h")


def add_parsers(subparsers: Any) -> None:
    """Register ``export`` (clip | sam | depth) and ``preprocess`` on the CLI's subparsers."""
    p = subparsers.add_parser(
        "export",
        help="export CLIP, SAM or a depth network to ONNX (needs pip install 'langfield[export]')",
    )
    kinds = p.add_subparsers(dest="kind", required=True)

    k = kinds.add_parser("clip", help="OpenCLIP image and text towers, with the CLIP BPE vocabulary")
    k.add_argument("--model", default="ViT-B-16", help="open_clip architecture (default ViT-B-16)")
    k.add_argument(
        "--checkpoint",
        required=True,
        help="local open_clip checkpoint file, or an open_clip pretrained tag (e.g. laion2b_s34b_b88k, "
        "downloaded by open_clip now)",
    )
    k.add_argument("--out", required=True, help="model folder to write (e.g. models/clip)")
    k.set_defaults(func=cmd_export)

    k = kinds.add_parser("sam", help="segment-anything image encoder and mask decoder")
    k.add_argument("--model", choices=_SAM_TYPES, default="vit_b", help="SAM model type (default vit_b)")
    k.add_argument(
        "--checkpoint", required=True, help="segment-anything checkpoint, e.g. sam_vit_b_01ec64.pth"
    )
    k.add_argument("--out", required=True, help="model folder to write (e.g. models/sam)")
    k.set_defaults(func=cmd_export)

    k = kinds.add_parser("depth", help="a transformers DPT or Depth Anything model (disparity output)")
    source = k.add_mutually_exclusive_group(required=True)
    source.add_argument(
        "--checkpoint",
        help="local transformers model folder (config.json, weights, preprocessor_config.json)",
    )
    source.add_argument(
        "--model",
        help="Hugging Face model id, downloaded by transformers now (e.g. LiheYoung/depth-anything-small-hf)",
    )
    k.add_argument(
        "--input-size",
        type=int,
        nargs="+",
        metavar=("H", "W"),
        default=None,
        help="network input size, H or H W (default: the model's preprocessor size, 518 for Depth Anything)",
    )
    k.add_argument("--out", required=True, help="model folder to write (e.g. models/depth)")
    k.set_defaults(func=cmd_export)

    p = subparsers.add_parser(
        "preprocess", help="write scenes' language_features/ and depths/ with exported models"
    )
    p.add_argument("scenes", nargs="+", metavar="scene", help="scene folder(s)")
    p.add_argument("--models", default=None, help="folder holding clip/, sam/ and depth/ exports")
    p.add_argument("--clip", default=None, help="CLIP model folder (default MODELS/clip)")
    p.add_argument("--sam", default=None, help="SAM model folder (default MODELS/sam)")
    p.add_argument("--depth", default=None, help="depth model folder (default MODELS/depth, if present)")
    p.add_argument(
        "--segmenter",
        choices=["sam", "graph"],
        default="sam",
        help="SAM (default) or the classical graph segmenter, which needs no weights",
    )
    p.add_argument("--overwrite", action="store_true", help="recompute views whose files are already valid")
    p.add_argument(
        "--address",
        default=None,
        help="share the views out to Ray workers (langfield[cluster]): local (a Ray started here), auto "
        "(the cluster this machine is part of) or ray://HOST:10001 (default: no Ray, one view at a time)",
    )
    p.set_defaults(func=cmd_preprocess)


def cmd_export(args: argparse.Namespace) -> int:
    """``langfield export clip|sam|depth``: one model folder, then a one-line summary."""
    out = Path(args.out)
    t0 = time.perf_counter()
    try:
        if args.kind == "clip":
            from encoders.export.clip import export_clip

            print(f"exporting OpenCLIP {args.model} ({args.checkpoint}) to {out} ...", flush=True)
            export_clip(out, args.model, pretrained=args.checkpoint)
        elif args.kind == "sam":
            from encoders.export.sam import export_sam

            print(f"exporting SAM {args.model} ({args.checkpoint}) to {out} ...", flush=True)
            export_sam(out, checkpoint=args.checkpoint, model_type=args.model)
        else:
            from encoders.export.depth import export_depth

            size = args.input_size
            if size is not None and len(size) not in (1, 2):
                raise ValueError(f"--input-size takes H or H W, got {len(size)} numbers")
            source = args.checkpoint or args.model
            print(f"exporting depth model {source} to {out} ...", flush=True)
            export_depth(
                out,
                checkpoint=args.checkpoint,
                model_id=args.model,
                input_size=None if size is None else (size[0], size[-1]),
            )
    except ImportError as err:
        return _fail(args, err)
    from encoders.manifest import read_manifest

    manifest = read_manifest(out, args.kind)
    files = ", ".join(f"{p.name} {p.stat().st_size / 1e6:.0f} MB" for p in manifest["files"].values())
    check = manifest.get("check") if isinstance(manifest.get("check"), dict) else {}
    errors = [v for k, v in check.items() if k.endswith("err") and isinstance(v, (int, float))]
    err = f"; max |ONNX - PyTorch| {max(errors):.1e} on the export inputs" if errors else ""
    seconds = time.perf_counter() - t0
    print(f"exported {args.kind} {manifest['model']} in {seconds:.0f} s to {out} ({files}){err}")
    return 0


def cmd_preprocess(args: argparse.Namespace) -> int:
    """``langfield preprocess SCENE...``: language features and depth priors of every view."""
    from functools import partial

    from langfield.io.preprocess import load_models, preprocess_scene

    if args.address is not None:
        from langfield.cluster import require_ray

        try:
            require_ray()
        except RuntimeError as err:
            return _fail(args, err)
    for scene in args.scenes:
        if not Path(scene).is_dir():
            raise ValueError(f"{scene}: no such scene folder")
    choice = {"clip": args.clip, "sam": args.sam, "depth": args.depth, "segmenter": args.segmenter}
    try:
        models = load_models(args.models, **choice)
    except ImportError as err:
        return _fail(args, err)
    used = ", ".join(f"{role} {src}" for role, src in models.sources.items())
    no_depth = "" if models.depth is not None else "; no depth model, so no depths/"
    print(f"models: {used}{no_depth}", flush=True)
    if args.address is None:
        reports = [
            preprocess_scene(s, models.segmenter, models.encoder, models.depth, overwrite=args.overwrite)
            for s in args.scenes
        ]
    else:
        from langfield.io.preprocess_ray import preprocess_on_ray

        address = None if args.address == "local" else args.address
        make = partial(load_models, args.models, **choice)
        reports = preprocess_on_ray(args.scenes, models, make, address=address, overwrite=args.overwrite)
    for report in reports:
        print(report.summary())
    return 0


def _fail(args: argparse.Namespace, err: Exception) -> int:
    """A missing optional package: one line naming it, exit status 2 (as cli.main does for bad input)."""
    print(f"langfield {args.command}: error: {err}", file=sys.stderr)
    return 2
