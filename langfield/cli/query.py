"""``langfield query OUT "phrase" [...] [--views test] --save DIR``: pictures and the 3D selection.

For every phrase and view, DIR receives ``<view>_<phrase>_heat.png`` (the normalised relevancy over the
render, turbo colour map) and ``<view>_<phrase>_mask.png`` (binary, 255 inside); ``contact_sheet.png``
shows every view (heat maps and mask overlays, one row per view); ``<phrase>.ply`` is the selected
Gaussians as a standard 3DGS PLY. A phrase the text encoder does not know is an error (exit 2, the
message names the phrase and the table); a phrase found nowhere is said so, and no empty mask or
PLY is written for it.
"""

from __future__ import annotations

import argparse
import re
import sys
import time

from encoders.text_table import UnknownPhraseError

SPLITS = ("train", "test", "all")


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Registers ``query`` on the ``langfield`` command's subparsers."""
    p = subparsers.add_parser("query", help="text query of a trained field: heat maps, masks, 3D selection")
    p.add_argument("out", help="folder of a trained field")
    p.add_argument("phrases", nargs="+", help="one or more phrases, e.g. 'sofa' 'lamp'")
    p.add_argument(
        "--views",
        default="test",
        help="train, test, all, or comma-separated view names or indices (default: test)",
    )
    p.add_argument("--save", required=True, help="folder for the PNGs, the contact sheet and the PLYs")
    p.add_argument("--scene", default=None, help="scene folder (default: the one recorded in field.json)")
    p.add_argument(
        "--text-encoder",
        default=None,
        help="a text_embeddings.npz or a CLIP model folder (default: the field's own, see field.json)",
    )
    p.add_argument(
        "--exact",
        action="store_true",
        help="decode every pixel (slow) instead of the decoder lattice (a field with a codebook: the same)",
    )
    p.set_defaults(func=cmd_query)
    return p


def _file_stem(text: str) -> str:
    """A phrase as a file-name part: letters, digits, '-', '_' and '.'; anything else becomes '_'."""
    return re.sub(r"[^\w.-]+", "_", text.strip()).strip("_") or "phrase"


def _view_keys(text: str) -> list[str | int] | str:
    if text in SPLITS:
        return text
    return [int(v) if v.strip().isdigit() else v.strip() for v in text.split(",") if v.strip()]


def cmd_query(args: argparse.Namespace) -> int:
    import cv2
    import numpy as np
    import torch

    from langfield.atomic import check_writable_folder
    from langfield.field import LanguageField
    from langfield.query import MATCH_RELEVANCY, EmptySelectionError, make_query
    from querying.visualize import contact_sheet, heatmap_overlay, mask_overlay

    save = check_writable_folder(args.save, "--save")
    field = LanguageField.load(args.out)
    scene = field.trained_scene(args.scene, remedy="pass --scene")
    keys = _view_keys(args.views)
    names = scene.names(keys) if isinstance(keys, str) else [scene.camera(k).name for k in keys]
    if not names:
        raise ValueError(f"{scene.root}: no {args.views} views to query")
    try:
        query = make_query(field, list(args.phrases), args.text_encoder, scene=scene)
    except UnknownPhraseError as err:
        print(f"langfield query: error: {err}", file=sys.stderr)
        return 2
    save.mkdir(parents=True, exist_ok=True)
    stems = [_file_stem(p) for p in query.phrases]
    tiles, labels = [], []
    found_views = {p: 0 for p in query.phrases}
    seconds = []
    for name in names:
        t0 = time.perf_counter()
        view = query.view(name, exact=args.exact)
        seconds.append(time.perf_counter() - t0)
        with torch.no_grad():
            rgb = field.render(scene.camera(name)).rgb
        for i, phrase in enumerate(query.phrases):
            if not bool(view.found[i]):
                print(
                    f"{phrase!r}: no match in view {name} (best relevancy {float(view.score[i]):.2f}, "
                    f"not above {MATCH_RELEVANCY}: no closer to it than to the canonical phrases)"
                )
                tiles += [rgb, rgb]
                labels += [f"{name} {phrase}", "no match"]
                continue
            found_views[phrase] += 1
            heat = heatmap_overlay(rgb, view.normalized[i])
            cv2.imwrite(str(save / f"{name}_{stems[i]}_heat.png"), cv2.cvtColor(heat, cv2.COLOR_RGB2BGR))
            cv2.imwrite(
                str(save / f"{name}_{stems[i]}_mask.png"), view.mask[i].numpy().astype(np.uint8) * 255
            )
            tiles += [heat, mask_overlay(rgb, view.mask[i])]
            labels += [f"{name} {phrase}", f"level {int(view.level[i])}, rel {float(view.score[i]):.2f}"]
    sheet = contact_sheet(tiles, labels, columns=2 * len(query.phrases))
    cv2.imwrite(str(save / "contact_sheet.png"), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
    selected = []
    for i, phrase in enumerate(query.phrases):
        try:
            path = query[i].export_ply(save / f"{stems[i]}.ply")
        except EmptySelectionError:
            print(f"{phrase!r}: no Gaussian matches, so no {stems[i]}.ply")
            continue
        selected.append(f"{phrase!r} {len(query[i].gaussians().indices)} ({path.name})")
    ms = 1000 * float(np.median(seconds))
    found = ", ".join(f"{p!r} in {n}/{len(names)} views" for p, n in found_views.items())
    print(
        f"queried {len(names)} views, {ms:.0f} ms/view (median): found {found}; "
        f"Gaussians selected of {field.num_gaussians}: {'; '.join(selected) or 'none'}; pictures in {save}"
    )
    return 0
