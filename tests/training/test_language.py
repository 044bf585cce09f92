"""The language field: heads, L_LF, geometry detached in the language pass, save/load, decoding."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from langfield import LanguageField, TrainConfig, load_scene, train
from langfield.model.language import language_loss, mask_balance
from langfield.training.aggregate import register_entries
from langfield.training.targets import language_targets

GEOMETRY = ("means", "log_scales", "quats", "opacity_logits")


@pytest.fixture(scope="module")
def scene(room_factory):
    return load_scene(room_factory(48, 36))


@pytest.fixture(scope="module", params=["hashgrid", "per-gaussian"])
def field(request, scene) -> LanguageField:
    cfg = TrainConfig(
        iterations=10, num_gaussians=400, language_features=request.param, autoencoder_iterations=50
    )
    return train(scene, cfg, progress=False)


def test_language_loss_hand_computed():
    rendered = torch.zeros(3, 1, 2, 3)
    target = torch.zeros(3, 1, 2, 3)
    target[0, 0, 0] = torch.tensor([1.0, -2.0, 0.5])  # L1 error 3.5 on the one valid pixel of level 0
    target[1, 0, 1] = torch.tensor([0.1, 0.0, 0.0])  # invalid pixel: ignored
    valid = torch.zeros(3, 1, 2, dtype=torch.bool)
    valid[0, 0, 0] = True
    assert language_loss(rendered, target, valid).item() == pytest.approx(3.5)


def test_language_loss_weighs_pixels_by_their_weight():
    rendered = torch.zeros(3, 1, 3, 3)
    target = torch.zeros(3, 1, 3, 3)
    target[2, 0, :, 0] = torch.tensor([1.0, 2.0, 4.0])  # L1 errors 1, 2, 4 at level 2
    weight = torch.zeros(3, 1, 3)
    weight[2, 0] = torch.tensor([0.5, 0.25, 0.25])
    assert language_loss(rendered, target, weight).item() == pytest.approx((0.5 + 0.5 + 1.0) / 1.0)
    # weights of any scale give the same weighted mean; all-equal weights give the plain mean
    assert language_loss(rendered, target, weight * 1e-4).item() == pytest.approx(2.0)
    assert language_loss(rendered, target, weight > 0).item() == pytest.approx(7.0 / 3.0)


def test_mask_balance_weighs_each_mask_by_its_area_to_a_power():
    seg = torch.full((3, 2, 4), -1, dtype=torch.long)
    seg[0, 0] = torch.tensor([0, 0, 0, 1])  # a mask of 3 pixels and one of 1; the second row has none
    seg[1] = 2  # one mask over the whole view
    plain = mask_balance(seg, 0.0)
    torch.testing.assert_close(plain, (seg >= 0).float())
    even = mask_balance(seg, 1.0)
    torch.testing.assert_close(even[0, 0], torch.tensor([1 / 3, 1 / 3, 1 / 3, 1.0]))
    assert even[0, 0, :3].sum() == pytest.approx(even[0, 0, 3])  # every mask weighs alike
    assert (even[0, 1] == 0).all() and (even[2] == 0).all()  # no mask, no weight
    torch.testing.assert_close(mask_balance(seg, 0.5)[0, 0], torch.tensor([3**-0.5] * 3 + [1.0]))
    # the small mask's error now moves the loss as much as the large mask's
    target = torch.zeros(3, 2, 4, 3)
    target[0, 0, 3, 0] = 1.0  # only the one-pixel mask is wrong
    assert language_loss(torch.zeros_like(target), target, plain).item() == pytest.approx(0.25)
    assert language_loss(torch.zeros_like(target), target, even).item() == pytest.approx(0.5)


def test_training_weighs_l_lf_by_mask_balance(scene, monkeypatch):
    import langfield.training.setup as setup

    seen = []

    def spy(segments, power):
        seen.append(power)
        return mask_balance(segments, power)

    monkeypatch.setattr(setup, "mask_balance", spy)
    cfg = TrainConfig(iterations=2, num_gaussians=200, autoencoder_iterations=5, language_balance=0.75)
    field = train(scene, cfg, progress=False)
    assert seen == [0.75] * len(scene.names("train"))
    assert field.meta["config"]["language_balance"] == 0.75


def test_language_loss_level_without_masks_is_zero_and_finite():
    rendered = torch.randn(3, 4, 5, 3, requires_grad=True)
    loss = language_loss(rendered, torch.zeros(3, 4, 5, 3), torch.zeros(3, 4, 5, dtype=torch.bool))
    loss.backward()
    assert loss.item() == 0.0 and torch.isfinite(rendered.grad).all()


def test_render_gives_latents_and_decode_gives_unit_clip_features(field, scene):
    cam = scene.camera(0)
    with torch.no_grad():
        r = field.render(cam)
        decoded = field.decode(r.latents)
    assert r.latents.shape == (3, cam.height, cam.width, 3)
    assert decoded.shape == (3, cam.height, cam.width, 512)
    assert torch.allclose(decoded.norm(dim=-1), torch.ones(3, cam.height, cam.width), atol=1e-4)


def test_language_loss_moves_no_gaussian(field, scene):
    # L_LF trains only the language grids and MLP_L (or the per-Gaussian latents): geometry detached.
    name = scene.names("train")[0]
    targets = language_targets(scene, TrainConfig(autoencoder_iterations=20), progress=False)
    field.zero_grad(set_to_none=True)
    r = field.render(scene.camera(name))
    language_loss(r.latents, targets.latents[name], targets.valid[name]).backward()
    for key in GEOMETRY:
        grad = field.splats[key].grad
        assert grad is None or torch.count_nonzero(grad) == 0, key
    trained = field.splats["lang"] if "lang" in field.splats else field.language.grid.table
    assert torch.count_nonzero(trained.grad) > 0
    field.zero_grad(set_to_none=True)


def test_save_load_keeps_language(field, scene, tmp_path):
    field.save(tmp_path / "out")
    loaded = LanguageField.load(tmp_path / "out")
    cam = scene.camera(1)
    with torch.no_grad():
        a, b = field.render(cam), loaded.render(cam)
        assert torch.equal(a.latents, b.latents)
        assert torch.equal(field.decode(a.latents), loaded.decode(b.latents))
        assert torch.equal(field.decode_levels(a.latents), loaded.decode_levels(b.latents))
    assert loaded.meta["language"]["features"] == field.meta["language"]["features"]
    assert all(torch.equal(x, y) for x, y in zip(field.codebook, loaded.codebook, strict=True))
    assert loaded.meta["language"]["codebook"] == [len(c) for c in field.codebook]
    assert loaded.language_decode == field.language_decode == "vote"  # the default, recorded
    assert torch.equal(loaded.entries, field.entries) and loaded.meta["language"]["registered"] is True


def test_training_registers_each_gaussian_to_the_masks_of_its_weight(field, scene):
    """The trainer's registration: the training views' target latents, each read as its codebook
    entry (-1 off the masks), then register_entries; recomputed here from the same targets."""
    targets = language_targets(scene, TrainConfig(**field.meta["config"]), progress=False)
    cameras = {n: scene.camera(n) for n in scene.names("train")}
    entries = {}
    for name in cameras:
        index = field.codebook_indices(targets.latents[name])
        entries[name] = torch.where(targets.valid[name], index, -1)
    expected = register_entries(field, cameras, entries, [len(c) for c in field.codebook])
    assert torch.equal(field.entries, expected)
    assert (expected >= 0).float().mean() > 0.5


def test_the_reading_can_be_switched_and_is_saved(field, tmp_path):
    copy = LanguageField(
        field.splats, field.color, dict(field.meta), field.language, field.decoder, field.codebook
    )
    copy.language_decode = "codebook"
    assert copy.language_decode == "codebook" and field.language_decode == "vote"  # meta not shared
    loaded = LanguageField.load(copy.save(tmp_path / "out"))
    assert loaded.language_decode == "codebook"
    with pytest.raises(ValueError, match="language_decode must be one of"):
        copy.language_decode = "mode"
    with pytest.raises(ValueError, match="field.codebook = None"):
        copy.language_decode = "continuous"
    copy.codebook = None  # read continuously from here on, and saved so
    assert copy.language_decode == "continuous"
    with pytest.raises(ValueError, match="'vote' and 'codebook' read through a codebook"):
        copy.language_decode = "vote"
    assert LanguageField.load(copy.save(tmp_path / "plain")).meta["language"]["decode"] == "continuous"


def test_a_field_saved_before_the_vote_reads_the_nearest_entry(field, tmp_path):
    out = field.save(tmp_path / "out")
    meta = json.loads((out / "field.json").read_text())
    del meta["language"]["decode"]  # what fields of before the vote reading wrote
    (out / "field.json").write_text(json.dumps(meta))
    assert LanguageField.load(out).language_decode == "codebook"


def test_language_off_gives_no_latents(scene):
    f = train(scene, TrainConfig(iterations=2, num_gaussians=200, language=False), progress=False)
    assert not f.has_language and f.render(scene.camera(0)).latents is None
    assert f.meta["language"] is None
    with pytest.raises(ValueError, match="no language decoder"):
        f.decode(torch.zeros(1, 3))


def test_language_required_without_caches_names_the_folder(scene, tmp_path):
    import shutil

    copy = tmp_path / "scene"
    shutil.copytree(scene.root, copy)
    shutil.rmtree(copy / "language_features")
    with pytest.raises(ValueError, match="language_features"):
        train(load_scene(copy), TrainConfig(iterations=1, language=True), progress=False)
    plain = train(load_scene(copy), TrainConfig(iterations=1, num_gaussians=100), progress=False)
    assert not plain.has_language  # automatic: no caches, no language


def test_unknown_language_features_mode_is_rejected(scene):
    with pytest.raises(ValueError, match="language_features"):
        train(scene, TrainConfig(iterations=1, language_features="sparse"), progress=False)


@pytest.mark.slow
def test_language_training_fits_the_training_views(scene):
    # The random start fits the training views fastest (the photos' start trades some of that fit for
    # novel views: tests/training/test_initialisation.py); this test is about the language heads, which it
    # trains from the first step (the default starts them after a third of the run).
    cfg = TrainConfig(iterations=300, seed=0, init="random", language_start=0.0)
    f = train(scene, cfg, progress=False)
    from encoders.cache import read_feature_cache

    name = scene.names("train")[0]
    cache = read_feature_cache(*scene.feature_paths(name))
    with torch.no_grad():
        decoded = f.decode(f.render(scene.camera(name)).latents)
    for level in range(3):
        seg = torch.from_numpy(cache.segments[level].astype(np.int64))
        valid = seg >= 0
        target = torch.from_numpy(cache.features)[seg.clamp_min(0)]
        cosine = (decoded[level] * target).sum(-1)[valid].mean().item()
        assert cosine > 0.75, f"level {level}: mean cosine {cosine:.3f}"


def test_eval_reports_feature_cosine_per_level(field, scene):
    from langfield.eval.evaluate import evaluate

    report = evaluate(field, scene)
    assert set(report["feature_cosine"]) == {"subpart", "part", "whole"}
    assert all(-1.0 <= v <= 1.0 for v in report["feature_cosine"].values())


def test_coarser_language_grid_is_recorded_and_reloads(scene, tmp_path):
    cfg = TrainConfig(iterations=2, language_grid_scale=0.25, autoencoder_iterations=5)
    f = train(scene, cfg, progress=False)
    color, lang = f.color.grid.cfg, f.language.grid.cfg
    assert lang.finest_resolution < color.finest_resolution and lang.n_levels < color.n_levels
    assert not f._shared_cells  # its own cell layout: the colour grid's look-up is not reused
    f.save(tmp_path / "f")
    loaded = LanguageField.load(tmp_path / "f")
    assert loaded.language.grid.cfg == lang
    cam = scene.camera(scene.names("test")[0])
    with torch.no_grad():
        assert torch.allclose(loaded.render(cam).latents, f.render(cam).latents, atol=1e-6)


def test_autoencoder_is_trained_once_per_features_and_config():
    from encoders.autoencoder import AutoencoderConfig
    from langfield.training.targets import fit_autoencoder

    rng = np.random.default_rng(0)
    features = rng.normal(size=(40, 512)).astype(np.float32)
    cfg = AutoencoderConfig(iterations=5, seed=0)
    first, stats = fit_autoencoder(features, cfg, progress=False)
    again, stats_again = fit_autoencoder(features.copy(), cfg, progress=False)
    assert "reused" not in stats and stats_again["reused"] == 1.0
    assert stats_again["seconds"] == stats["seconds"]
    assert again is not first
    for a, b in zip(first.state_dict().values(), again.state_dict().values(), strict=True):
        assert torch.equal(a, b)
    with torch.no_grad():  # a caller editing its copy does not reach the next caller's
        next(again.parameters()).add_(1.0)
    third, _ = fit_autoencoder(features, cfg, progress=False)
    assert torch.equal(next(third.parameters()), next(first.parameters()))
    # Other features or another config train again.
    _, other = fit_autoencoder(features[:-1], cfg, progress=False)
    _, longer = fit_autoencoder(features, AutoencoderConfig(iterations=6, seed=0), progress=False)
    assert "reused" not in other and "reused" not in longer


def test_decode_reads_each_latent_at_unit_length(field):
    # A rendered latent is a blend, shorter than the unit latents the decoder was trained on.
    z = torch.nn.functional.normalize(torch.randn(7, 3, generator=torch.Generator().manual_seed(0)), dim=-1)
    with torch.no_grad():
        torch.testing.assert_close(field.decode(0.6 * z), field.decode(z))
        torch.testing.assert_close(field.decode(torch.zeros(2, 3)), field.decoder.decode(torch.zeros(2, 3)))
        assert not torch.allclose(field.decoder.decode(0.6 * z), field.decoder.decode(z), atol=1e-3)


def test_codebook_holds_the_training_masks_latents(field, scene):
    """One unit entry per distinct mask latent of each level, the prototypes LOP groups by."""
    cfg = TrainConfig(iterations=10, num_gaussians=400, autoencoder_iterations=50)
    targets = language_targets(scene, cfg, progress=False)
    for level, entries in enumerate(field.codebook):
        torch.testing.assert_close(entries.norm(dim=-1), torch.ones(len(entries)))
        torch.testing.assert_close(entries, torch.nn.functional.normalize(targets.prototypes[level], dim=-1))


def test_codebook_indices_of_zero_and_unseen_levels(field):
    entries = field.codebook
    latents = torch.stack([entries[level][:2].clone() for level in range(3)])  # [3, 2, 3]
    latents[1, 1] = 0.0  # an empty pixel: no direction
    latents[2] *= 0.4  # a short blend points at the same entry
    index = field.codebook_indices(latents)
    assert index.tolist() == [[0, 1], [0, -1], [0, 1]]
    decoded = field.decode_levels(latents)
    torch.testing.assert_close(decoded[1, 1], field.decode(torch.zeros(3)))
    torch.testing.assert_close(decoded[0, 1], field.decode(entries[0][1]))
    emptied = LanguageField(
        field.splats,
        field.color,
        field.meta,
        field.language,
        field.decoder,
        [entries[0], torch.zeros(0, 3), entries[2]],
    )
    assert (emptied.codebook_indices(latents)[1] == -1).all()
    with pytest.raises(ValueError, match="level first"):
        field.codebook_indices(torch.zeros(2, 5, 3))


def test_codebook_indices_match_the_smallest_angle(field):
    """Latents of any length and direction, float64 too, against a brute-force smallest angle."""
    generator = torch.Generator().manual_seed(3)
    latents = torch.randn(3, 50, 3, generator=generator, dtype=torch.float64) * 3.0
    index = field.codebook_indices(latents)
    for level, entries in enumerate(field.codebook):
        unit = latents[level] / latents[level].norm(dim=-1, keepdim=True)
        angles = torch.arccos((unit @ entries.double().T).clamp(-1, 1))
        assert torch.equal(index[level], angles.argmin(dim=-1))
    tiny = torch.full((3, 1, 3), 1e-7)  # below LATENT_NORM_EPS: no direction
    assert (field.codebook_indices(tiny) == -1).all()


def test_a_codebook_of_zero_or_misshapen_entries_is_refused(field):
    parts = (field.splats, field.color, field.meta, field.language, field.decoder)
    with pytest.raises(ValueError, match="unit latents"):
        LanguageField(*parts, [torch.zeros(2, 3)] * 3)
    with pytest.raises(ValueError, match="unit latents"):
        LanguageField(*parts, [torch.full((1, 3), 0.7)] * 3)
    with pytest.raises(ValueError, match=r"codebook\[0\]: expected \[P, 3\]"):
        LanguageField(*parts, [torch.ones(2, 4)] * 3)
    with pytest.raises(ValueError, match="one entry tensor per level"):
        LanguageField(*parts, field.codebook[:2])
    copy = LanguageField(*parts)
    with pytest.raises(ValueError, match="one entry tensor per level"):
        copy.codebook = []  # the setter checks as the constructor does
    assert copy.codebook is None
    with pytest.raises(ValueError, match="without a language decoder"):
        LanguageField(field.splats, field.color, field.meta, field.language, None, field.codebook)


def test_continuous_reading_keeps_no_codebook(scene, tmp_path):
    cfg = TrainConfig(
        iterations=4, num_gaussians=300, autoencoder_iterations=20, language_decode="continuous"
    )
    f = train(scene, cfg, progress=False)
    assert f.codebook is None and f.meta["language"]["codebook"] is None
    assert f.entries is None and f.meta["language"]["registered"] is False
    loaded = LanguageField.load(f.save(tmp_path / "out"))
    assert loaded.codebook is None
    z = torch.randn(3, 4, 3, generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(loaded.decode_levels(z), loaded.decode(z))
    with pytest.raises(ValueError, match="--language-decode continuous"):
        loaded.codebook_indices(z)
    with pytest.raises(ValueError, match="--language-decode continuous"):
        loaded.codebook_features(0)


def test_a_field_of_format_1_loads_without_a_codebook(scene, tmp_path):
    cfg = TrainConfig(
        iterations=2, num_gaussians=300, autoencoder_iterations=20, language_decode="continuous"
    )
    out = train(scene, cfg, progress=False).save(tmp_path / "out")
    meta = json.loads((out / "field.json").read_text())
    meta["format_version"] = 1
    del meta["language"]["codebook"]  # what version 1 wrote
    (out / "field.json").write_text(json.dumps(meta))
    loaded = LanguageField.load(out)
    assert loaded.codebook is None and loaded.meta["format_version"] == 1


def test_setting_the_codebook_to_none_saves_a_continuous_field(field, tmp_path):
    copy = LanguageField(
        field.splats, field.color, dict(field.meta), field.language, field.decoder, field.codebook
    )
    copy.codebook = None
    loaded = LanguageField.load(copy.save(tmp_path / "out"))
    assert loaded.codebook is None and loaded.meta["language"]["codebook"] is None


def test_the_paper_language_ablation_keeps_the_papers_language_settings():
    from dataclasses import replace

    from langfield.eval.ablate import CASES

    cfg = replace(TrainConfig(), **CASES["paper-language"])
    assert cfg.language_balance == 0.0 and TrainConfig().language_balance > 0.0  # L_LF: pixels alike
    assert cfg.autoencoder_spread == 0.0 and cfg.language_decode == "continuous"
