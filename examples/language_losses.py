"""Where a trained field's novel-view mIoU is lost: each stage of the language pipeline swapped for its
ground truth on a synthetic scene (one that make_room wrote: it knows its objects' surfaces).

python examples/language_losses.py FIELD_DIR [SCENE] [--json OUT.json] [--split train]

Rows, from the field as trained to the query pipeline's ceiling:
- field: the field's rendered latents, read as the field records (what `langfield eval` scores); then
  the same latents decoded as they are (the paper's reading), read as their nearest codebook entries,
  and read by vote among the entries of the Gaussians at each pixel (langfield.model.reading);
- aggregated latents, trained geometry: every Gaussian's latents the rendering-weighted mean of the
  training views' mask latents (langfield.training.aggregate, no training), rendered with the trained
  Gaussians;
- field, best level: the same relevancy maps, each query given the level whose mask scores best
  instead of the automatic choice;
- true latents, trained geometry: every Gaussian carries the autoencoded features of the object whose
  surface is nearest to it (at each level), rendered with the trained Gaussians; the autoencoder is
  refitted as training fits it (same seed and iterations);
- true features through the autoencoder: each test view's own mask features encoded and decoded (and
  with every latent turned 5 or 10 degrees in a random direction: how far off a rendered latent may be);
- oracle: each test view's own mask features (`langfield eval --oracle`).
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np
import open3d as o3d
import torch

from encoders.protocols import LEVELS
from langfield import LanguageField, TrainConfig, load_scene
from langfield.eval.evaluate import masked_pixels, score_queries, true_features
from langfield.query import fill_empty, text_encoder_for
from langfield.training.aggregate import aggregate_latents, with_latents
from langfield.training.targets import language_targets
from querying.evaluation import mask_iou, summarize_queries
from querying.relevancy import CANONICAL_PHRASES, relevancy, relevancy_mask


def nearest_primitive(scene_dir, points: np.ndarray) -> list[dict]:
    """Each point's nearest primitive record of ``gt/primitives.json``."""
    records = json.loads((scene_dir / "gt" / "primitives.json").read_text())
    mesh = o3d.io.read_triangle_mesh(str(scene_dir / "gt" / "mesh.ply"))
    raycaster = o3d.t.geometry.RaycastingScene()
    raycaster.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    hit = raycaster.compute_closest_points(o3d.core.Tensor(points.astype(np.float32)))
    triangle = hit["primitive_ids"].numpy()
    starts = np.array([r["triangles"][0] for r in records])
    return [records[i] for i in np.searchsorted(starts, triangle, side="right") - 1]


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("field")
    parser.add_argument("scene", nargs="?", default=None)
    parser.add_argument("--json", default=None)
    parser.add_argument(
        "--split", default="test", choices=["test", "train"], help="views scored (default test)"
    )
    args = parser.parse_args(argv)
    field = LanguageField.load(args.field)
    scene = load_scene(args.scene or field.meta["scene"], **(field.meta.get("scene_args") or {}))
    names = scene.names(args.split)
    labels = {name: scene.segmentations(name) for name in names}
    phrases = sorted({p for masks in labels.values() for p in masks})
    encoder = text_encoder_for(field)
    rows = torch.from_numpy(np.asarray(encoder.encode_text(phrases + list(CANONICAL_PHRASES)))).float()
    phrase_emb, canonical_emb = rows[: len(phrases)], rows[len(phrases) :]

    def score(features_and_alpha, best_level: bool = False) -> dict:
        records = []
        for name in names:
            features, alpha = features_and_alpha(name)
            maps = fill_empty(relevancy(features, phrase_emb, canonical_emb), alpha)
            if not best_level:
                records += score_queries(maps, phrases, labels[name]).values()
                continue
            for phrase, gt in sorted(labels[name].items()):
                m = maps[phrases.index(phrase)]
                ious = [
                    mask_iou(relevancy_mask(m[lv : lv + 1]).mask, torch.from_numpy(gt)) for lv in range(3)
                ]
                records.append({"iou": max(ious), "hit": True})
        return summarize_queries(records)

    rendered = {}
    with torch.no_grad():
        for name in names:
            out = field.render(scene.camera(name))
            rendered[name] = (out.latents, out.alpha)

    # The autoencoder, refitted as training fitted it (its decoder is compared with the saved one).
    saved = field.meta["config"]
    # A field trained before the spread term existed (no key in its config) was trained without it.
    cfg = TrainConfig(
        seed=saved["seed"],
        autoencoder_iterations=saved["autoencoder_iterations"],
        autoencoder_spread=saved.get("autoencoder_spread", 0.0),
    )
    targets = language_targets(scene, cfg, progress=False)
    # Both readings of the same rendered latents; the codebook is the training masks' latents (the
    # field's own, or the refitted autoencoder's for a field trained without one).
    codebook = field.codebook or [torch.nn.functional.normalize(p, dim=-1) for p in targets.prototypes]
    readers = {}
    for decode in ("continuous", "codebook", "vote"):
        reader = LanguageField(
            field.splats,
            field.color,
            dict(field.meta),
            field.language,
            field.decoder,
            None if decode == "continuous" else codebook,
        )
        if decode == "vote":
            reader.language_decode = "vote"
            with torch.no_grad():
                readers[decode] = {
                    n: (reader.decode_entries(reader.read_entries(scene.camera(n), z, alpha)), alpha)
                    for n, (z, alpha) in rendered.items()
                }
        else:
            readers[decode] = {n: (reader.decode_levels(z), alpha) for n, (z, alpha) in rendered.items()}
    renders = readers[field.language_decode]  # what eval scores
    autoencoder = targets.autoencoder
    refit, own = autoencoder.decoder.state_dict(), field.decoder.decoder.state_dict()
    diff = max(float((refit[k] - own[k]).abs().max()) for k in own)
    generator = torch.Generator().manual_seed(0)

    def through_autoencoder(name, degrees: float = 0.0):
        """The view's features encoded, each latent turned by ``degrees`` in a random direction, decoded."""
        features = true_features(scene, name)
        valid = (features != 0).any(-1, keepdim=True)
        with torch.no_grad():
            z = autoencoder.encode(features)
            side = torch.randn(z.shape, generator=generator)
            side = torch.nn.functional.normalize(side - (side * z).sum(-1, keepdim=True) * z, dim=-1)
            turn = np.deg2rad(degrees)
            decoded = autoencoder.decode(z * np.cos(turn) + side * np.sin(turn)) * valid
        return decoded, masked_pixels(features).float()

    # True per-Gaussian latents: the nearest primitive's labels, their concept vectors (the phrase table
    # holds each label's), autoencoded.
    means = field.splats["means"].detach().numpy()
    owners = nearest_primitive(scene.root, means)
    label_rows = {}
    table = np.load(scene.root / "text_embeddings.npz")
    with torch.no_grad():
        for label in {r["labels"][lv] for r in owners for lv in LEVELS}:
            label_rows[label] = autoencoder.encode(torch.from_numpy(table[label]).float()[None])[0]
        latents = torch.stack([torch.stack([label_rows[r["labels"][lv]] for lv in LEVELS]) for r in owners])
    true_field = with_latents(field, latents)

    def true_latents(name):
        with torch.no_grad():
            out = true_field.render(scene.camera(name))
            return true_field.decode_levels(out.latents), out.alpha

    train_names = scene.names("train")
    t0 = time.perf_counter()
    aggregated, _ = aggregate_latents(
        field, {n: scene.camera(n) for n in train_names}, targets.latents, targets.valid
    )
    aggregate_seconds = time.perf_counter() - t0
    aggregated_field = with_latents(field, aggregated)

    def aggregated_latents(name):
        with torch.no_grad():
            out = aggregated_field.render(scene.camera(name))
            return aggregated_field.decode_levels(out.latents), out.alpha

    def oracle_features(name):
        truth = true_features(scene, name)
        return truth, masked_pixels(truth).float()

    table_rows = {
        "field": score(lambda n: renders[n]),
        "field, rendered latents decoded as they are (continuous, the paper)": score(
            lambda n: readers["continuous"][n]
        ),
        "field, rendered latents read as their nearest codebook entry": score(
            lambda n: readers["codebook"][n]
        ),
        "field, read by vote among the Gaussians' codebook entries": score(lambda n: readers["vote"][n]),
        f"aggregated latents, trained geometry ({aggregate_seconds:.1f} s)": score(aggregated_latents),
        "field, best level": score(lambda n: renders[n], best_level=True),
        "true latents, trained geometry": score(true_latents),
        "true features through the autoencoder, latents turned 10 degrees": score(
            lambda n: through_autoencoder(n, 10.0)
        ),
        "true features through the autoencoder, latents turned 5 degrees": score(
            lambda n: through_autoencoder(n, 5.0)
        ),
        "true features through the autoencoder": score(through_autoencoder),
        "oracle": score(oracle_features),
    }
    print(f"refitted decoder vs the field's: max weight difference {diff}")
    print("| pipeline | mIoU | mAcc |\n|---|---|---|")
    for key, r in table_rows.items():
        acc = "" if "best level" in key else f"{r['mAcc']:.3f}"
        print(f"| {key} | {r['mIoU']:.3f} | {acc} |")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"decoder_difference": diff, "rows": table_rows}, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
