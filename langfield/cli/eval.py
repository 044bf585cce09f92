"""``langfield eval``: the report of a trained field on its scene's test views."""

from __future__ import annotations

import argparse

from langfield.cli.common import load_field_and_scene


def cmd_eval(args: argparse.Namespace) -> int:
    from langfield.atomic import check_writable_file, check_writable_folder
    from langfield.eval.evaluate import evaluate, write_report

    json_path = check_writable_file(args.json, "--json report")
    check_writable_file(json_path.with_suffix(".md"), "Markdown summary")
    pictures = check_writable_folder(json_path.parent / (json_path.stem + "_renders"), "pictures")
    field, scene = load_field_and_scene(args.out, args.scene)
    if args.language_decode is not None:
        if field.codebook is None:
            raise ValueError(f"--language-decode {args.language_decode}: {args.out} has no codebook")
        field.language_decode = args.language_decode  # this evaluation only; the folder is unchanged
    report = evaluate(field, scene, split=args.split, save_dir=pictures, oracle=args.oracle)
    md = write_report(report, json_path, pictures)
    psnr_txt = (
        f"PSNR {report['PSNR']:.2f} dB, SSIM {report['SSIM']:.3f}"
        if report["PSNR"] is not None
        else f"no {args.split} views"
    )
    if report.get("masked_PSNR") is not None:
        psnr_txt += f" (object masks: {report['masked_PSNR']:.2f} dB, SSIM {report['masked_SSIM']:.3f})"
    query_txt = (
        f", mIoU {report['mIoU']:.3f}, mAcc {report['mAcc']:.3f}" if report.get("mIoU") is not None else ""
    )
    oracle = report.get("oracle")
    if oracle and oracle["mIoU"] is not None:
        ratio = "" if oracle["ratio"] is None else f", {oracle['ratio']:.2f} of it"
        query_txt += f" (oracle on the true features: mIoU {oracle['mIoU']:.3f}{ratio})"
    selection = report.get("selection_3d")
    if selection and selection["precision"] is not None:
        query_txt += (
            f", 3D selection precision {selection['precision']:.3f} "
            f"(on surfaces {selection['surface_precision']:.3f}) recall {selection['recall']:.3f}"
        )
    print(
        f"{len(report['views'])} {args.split} views: {psnr_txt}{query_txt}{_cosine_text(report)}; "
        f"{report['num_gaussians']} Gaussians, "
        f"{report['field_bytes'] / 1e6:.1f} MB; report {json_path} and {md}"
    )
    return 0


def _cosine_text(report: dict) -> str:
    cos = report.get("feature_cosine")
    if not cos or any(v is None for v in cos.values()):
        return ""
    return ", feature cosine " + " / ".join(f"{v:.3f}" for v in cos.values()) + " (" + "/".join(cos) + ")"


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Registers ``langfield eval``."""
    p = sub.add_parser("eval", help="score a trained field on the scene's test views")
    p.add_argument("out", help="folder of a trained field")
    p.add_argument("scene", nargs="?", default=None, help="scene folder (default: the one in field.json)")
    p.add_argument("--json", required=True, help="report path; a Markdown summary is written beside it")
    p.add_argument(
        "--split", choices=["test", "train"], default="test", help="views to score (default: the test views)"
    )
    p.add_argument(
        "--oracle",
        action="store_true",
        help="also score the queries on each view's own mask features (its feature cache): the query "
        "pipeline's ceiling, beside the field's mIoU and their ratio",
    )
    p.add_argument(
        "--language-decode",
        choices=["vote", "codebook"],
        default=None,
        help="read a field with a codebook this way (by vote, or as the nearest entry) instead of as its "
        "field.json records; the reading changes nothing trained",
    )
    p.set_defaults(func=cmd_eval)
