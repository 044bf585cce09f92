"""Tests of LanguageField (field.py): save / load, gaussians.ply, atomic writes and render()."""

from __future__ import annotations

import json
import os
import struct

import numpy as np
import pytest
import torch
from safetensors import safe_open
from safetensors.torch import load_file

from langfield import Camera, LanguageField, TrainConfig, load_scene, train
from langfield.field import FORMAT_VERSION
from langfield.io.ply import SH_C0, read_gaussian_ply

N = 500
FIELD_FILES = ("field.safetensors", "field.json", "gaussians.ply", "text_embeddings.npz")  # room: a table


@pytest.fixture(scope="module")
def scene(room_factory):
    return load_scene(room_factory(64, 48))


@pytest.fixture(scope="module")
def field(scene) -> LanguageField:
    return train(scene, TrainConfig(iterations=20, num_gaussians=N, seed=0), progress=False)


@pytest.fixture
def saved(field, tmp_path):
    return field.save(tmp_path / "out")


def _json_normalised(value):
    return json.loads(json.dumps(value))


# ---------------------------------------------------------------- round trip


def test_round_trip_gives_identical_tensors(field, saved) -> None:
    loaded = LanguageField.load(saved)
    before, after = field.state_tensors(), loaded.state_tensors()
    assert before.keys() == after.keys()
    for key in before:
        assert after[key].dtype == before[key].dtype, key
        assert torch.equal(after[key], before[key]), key
    assert loaded.num_gaussians == field.num_gaussians == N
    assert all(isinstance(p, torch.nn.Parameter) for p in loaded.splats.values())


def test_registered_entries_survive_save_and_select_and_are_checked(field, saved) -> None:
    assert field.entries is not None and field.entries.shape == (N, 3) and (field.entries >= 0).any()
    loaded = LanguageField.load(saved)
    assert torch.equal(loaded.entries, field.entries)
    assert json.loads((saved / "field.json").read_text())["language"]["registered"] is True
    index = torch.tensor([3, 0, 5])
    assert torch.equal(field.select(index).entries, field.entries[index])
    with torch.no_grad():
        own = field.codebook_indices(field.gaussian_latents().transpose(0, 1))
    registered = field.entries.T
    assert torch.equal(field.gaussian_entries(), torch.where(registered >= 0, registered, own))
    copy = LanguageField(
        field.splats, field.color, dict(field.meta), field.language, field.decoder, field.codebook
    )
    assert copy.entries is None and torch.equal(copy.gaussian_entries(), own)
    with pytest.raises(ValueError, match="expected long"):
        copy.entries = field.entries.float()
    with pytest.raises(ValueError, match="expected long"):
        copy.entries = field.entries[:-1]
    bad = field.entries.clone()
    bad[0, 2] = len(field.codebook[2])
    with pytest.raises(ValueError, match="level 2 holds indices outside"):
        copy.entries = bad
    copy.entries = field.entries
    copy.codebook = None  # the entries index the codebook: they go with it
    assert copy.entries is None
    with pytest.raises(ValueError, match="without a codebook"):
        copy.entries = field.entries


def test_a_field_saved_before_registration_loads_without_entries(field, tmp_path) -> None:
    copy = LanguageField(
        field.splats, field.color, dict(field.meta), field.language, field.decoder, field.codebook
    )
    out = copy.save(tmp_path / "old")
    meta = json.loads((out / "field.json").read_text())
    meta["format_version"] = 2
    for key in ("registered", "decode"):  # what version 2 wrote
        del meta["language"][key]
    (out / "field.json").write_text(json.dumps(meta))
    loaded = LanguageField.load(out)
    assert loaded.entries is None and loaded.language_decode == "codebook"


def test_round_trip_gives_identical_render(field, saved, scene) -> None:
    loaded = LanguageField.load(saved)
    cam = scene.camera(scene.names("test")[0])
    with torch.no_grad():
        a, b = field.render(cam), loaded.render(cam)
    for name in ("rgb", "depth", "alpha"):
        diff = (getattr(a, name) - getattr(b, name)).abs().max().item()
        assert diff < 1e-6, name


def test_a_colour_without_the_view_direction_is_saved_and_loaded(scene, tmp_path) -> None:
    fld = train(scene, TrainConfig(iterations=2, num_gaussians=N, seed=0, color_freqs=-1), progress=False)
    loaded = LanguageField.load(fld.save(tmp_path / "no_direction"))
    assert loaded.meta["color_field"]["n_freqs"] == -1
    cam = scene.camera(scene.names("test")[0])
    with torch.no_grad():
        assert (fld.render(cam).rgb - loaded.render(cam).rgb).abs().max() < 1e-6


@pytest.mark.parametrize("fused", [False, True])
def test_grid_features_follow_an_optimizer_step(scene, fused: bool) -> None:
    """The colour grid read at the means sees an optimizer step, also PyTorch's fused Adam, which writes
    without bumping the tensor's version counter: nothing of an earlier read is reused."""
    fld = train(scene, TrainConfig(iterations=1, num_gaussians=N, seed=0), progress=False)
    means = fld.splats["means"]
    before = fld.grid_features().features.detach()
    opt = torch.optim.Adam([means], lr=0.05, fused=fused)  # moves many means into other fine cells
    means.grad = torch.randn(means.shape, generator=torch.Generator().manual_seed(0))
    opt.step()
    after = fld.grid_features().features.detach()
    grid = fld.color.grid
    grid.backend = "torch"
    fresh = grid.interpolate(*grid.corners(means.detach())).detach()
    assert not torch.allclose(before, fresh)  # the step did change the features
    torch.testing.assert_close(after, fresh, atol=1e-6, rtol=1e-5)


def test_round_trip_preserves_meta(field, saved) -> None:
    loaded = LanguageField.load(saved)
    expected = _json_normalised(field.meta)
    for key, value in expected.items():
        assert loaded.meta[key] == value, key
    assert loaded.meta["format_version"] == FORMAT_VERSION
    assert loaded.meta["num_gaussians"] == N


def test_resaving_a_loaded_field_writes_the_same_tensors(saved, tmp_path) -> None:
    again = LanguageField.load(saved).save(tmp_path / "again")
    first = json.loads((saved / "field.json").read_text())
    second = json.loads((again / "field.json").read_text())
    assert first["tensors_sha256"] == second["tensors_sha256"]


def test_field_json_records_the_contract_keys(field, saved, scene) -> None:
    meta = json.loads((saved / "field.json").read_text())
    for key in ("format_version", "num_gaussians", "config", "bounds", "train_views", "color_field"):
        assert key in meta, key
    assert meta["format_version"] == FORMAT_VERSION
    assert meta["num_gaussians"] == N
    assert meta["config"]["num_gaussians"] == N and meta["config"]["iterations"] == 20
    assert np.asarray(meta["bounds"]).shape == (2, 3)
    assert meta["train_views"] == scene.names("train")
    assert set(meta["color_field"]) >= {"grid", "center", "half_extent", "hidden", "n_freqs"}


def test_tensors_file_is_plain_safetensors(field, saved) -> None:
    path = saved / "field.safetensors"
    raw = path.read_bytes()
    # safetensors: u64 little-endian header length, then a JSON header; no pickle, no zip.
    (header_len,) = struct.unpack("<Q", raw[:8])
    header = json.loads(raw[8 : 8 + header_len])
    assert "splats.means" in header
    assert not raw.startswith(b"PK") and not raw.startswith(b"\x80")
    with safe_open(str(path), framework="pt") as f:
        assert set(f.keys()) == set(field.state_tensors())
    tensors = load_file(str(path))
    assert torch.equal(tensors["splats.means"], field.splats["means"].detach())


# ---------------------------------------------------------------- gaussians.ply


def test_ply_has_the_3dgs_properties(saved) -> None:
    ply = read_gaussian_ply(saved / "gaussians.ply")
    names = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"]
    names += [f"f_rest_{i}" for i in range(45)]
    names += [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)]
    for name in names:
        assert name in ply, name
        assert ply[name].shape == (N,), name
        assert np.isfinite(ply[name]).all(), name


def test_ply_values_match_the_field(field, saved) -> None:
    ply = read_gaussian_ply(saved / "gaussians.ply")
    means = np.stack([ply["x"], ply["y"], ply["z"]], axis=1)
    np.testing.assert_array_equal(means, field.splats["means"].detach().numpy())
    log_scales = np.stack([ply[f"scale_{i}"] for i in range(3)], axis=1)
    np.testing.assert_array_equal(log_scales, field.splats["log_scales"].detach().numpy())
    np.testing.assert_array_equal(ply["opacity"], field.splats["opacity_logits"].detach().numpy()[:, 0])
    rgb = 0.5 + SH_C0 * np.stack([ply[f"f_dc_{i}"] for i in range(3)], axis=1)
    assert rgb.min() >= -1e-5 and rgb.max() <= 1 + 1e-5
    with torch.no_grad():
        baked = field.color.bake_dc(field.splats["means"]).numpy()
    np.testing.assert_allclose(rgb, baked, atol=1e-5)
    assert all((ply[f"f_rest_{i}"] == 0).all() for i in range(45))
    quats = np.stack([ply[f"rot_{i}"] for i in range(4)], axis=1)
    np.testing.assert_allclose(np.linalg.norm(quats, axis=1), 1.0, atol=1e-5)


# ---------------------------------------------------------------- atomic, consistent writes


@pytest.mark.parametrize("damage", ["flip_byte", "truncate"])
def test_corrupt_tensors_file_is_rejected_naming_it(saved, damage) -> None:
    path = saved / "field.safetensors"
    raw = bytearray(path.read_bytes())
    if damage == "flip_byte":
        raw[-5] ^= 0xFF
    else:
        raw = raw[: len(raw) // 2]
    path.write_bytes(bytes(raw))
    with pytest.raises(ValueError, match="field.safetensors") as err:
        LanguageField.load(saved)
    assert "checksum" in str(err.value)


@pytest.mark.slow
def test_tensors_of_another_save_are_rejected(field, saved, scene, tmp_path) -> None:
    # What an interrupted save leaves behind: new tensors renamed into place, the old field.json.
    other = train(scene, TrainConfig(iterations=0, num_gaussians=300, seed=1), progress=False)
    other.save(tmp_path / "other")
    os.replace(tmp_path / "other" / "field.safetensors", saved / "field.safetensors")
    with pytest.raises(ValueError, match="field.safetensors"):
        LanguageField.load(saved)


@pytest.mark.parametrize("missing", ["field.json", "field.safetensors"])
def test_missing_file_raises_file_not_found_naming_it(saved, missing) -> None:
    (saved / missing).unlink()
    with pytest.raises(FileNotFoundError, match=missing):
        LanguageField.load(saved)


def test_malformed_field_json_raises_value_error_naming_it(saved) -> None:
    (saved / "field.json").write_text("{ not json")
    with pytest.raises(ValueError, match="field.json"):
        LanguageField.load(saved)


def test_unknown_format_version_is_rejected(saved) -> None:
    meta = json.loads((saved / "field.json").read_text())
    meta["format_version"] = FORMAT_VERSION + 1
    (saved / "field.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="format_version"):
        LanguageField.load(saved)


def test_save_over_an_older_field_overwrites_it_cleanly(field, scene, tmp_path) -> None:
    out = tmp_path / "out"
    older = train(scene, TrainConfig(iterations=0, num_gaussians=300, seed=1), progress=False)
    older.save(out)
    with pytest.raises(FileExistsError, match="--force"):
        field.save(out)
    field.save(out, overwrite=True)
    loaded = LanguageField.load(out)
    assert loaded.num_gaussians == N
    assert torch.equal(loaded.splats["means"], field.splats["means"].detach())
    assert read_gaussian_ply(out / "gaussians.ply")["x"].shape == (N,)
    assert sorted(p.name for p in out.iterdir()) == sorted(FIELD_FILES)


def test_save_leaves_no_temporary_files(saved) -> None:
    assert sorted(p.name for p in saved.iterdir()) == sorted(FIELD_FILES)
    assert not list(saved.glob("*.tmp"))


# ---------------------------------------------------------------- render()


def test_render_shapes_and_ranges(field, scene) -> None:
    cam = scene.camera(scene.names("test")[0])
    with torch.no_grad():
        r = field.render(cam)
    h, w = cam.height, cam.width
    assert r.rgb.shape == (h, w, 3) and r.depth.shape == (h, w) and r.alpha.shape == (h, w)
    assert r.depth_hard is None
    for t in (r.rgb, r.depth, r.alpha):
        assert torch.isfinite(t).all()
    assert r.rgb.min() >= -1e-5 and r.rgb.max() <= 1 + 1e-5
    assert r.alpha.min() >= -1e-6 and r.alpha.max() <= 1 + 1e-6
    assert r.depth.min() >= 0
    assert r.alpha.max() > 0.1  # the scene's own views see the Gaussians
    assert r.means2d.shape == (N, 2) and r.radii.shape[0] == N


@pytest.mark.parametrize("backend", ["torch", "numba"])
def test_hard_depth_gradient_moves_only_the_means(field, scene, backend) -> None:
    cam = scene.camera(scene.names("train")[0])
    field.zero_grad(set_to_none=True)
    r = field.render(cam, backend=backend, hard_depth=True)
    assert r.depth_hard is not None and r.depth_hard.shape == (cam.height, cam.width)
    assert torch.isfinite(r.depth_hard).all() and r.depth_hard.min() >= 0
    r.depth_hard.sum().backward()
    grads = {k: p.grad for k, p in field.splats.items()}
    field.zero_grad(set_to_none=True)
    assert grads["means"] is not None
    assert torch.isfinite(grads["means"]).all() and grads["means"].abs().sum() > 0
    # Eq. 7: scales and rotations detached, opacity the constant mu.
    for name in ("log_scales", "quats", "opacity_logits"):
        assert grads[name] is None or not grads[name].any(), name


def _spread_reference(field: LanguageField, cam: Camera, backend: str) -> torch.Tensor:
    """1/2 sum_ij w_i w_j (d_i - d_j)^2 per pixel, from every Gaussian's own blending weight w_i (one
    one-hot channel each, all passing gradient to the geometry), in float64."""
    from langfield.model import gaussians as G
    from langfield.raster import rasterize

    splats = field.splats
    n = field.num_gaussians
    weights = rasterize(
        splats["means"], splats["quats"], G.scales(splats), G.opacities(splats).reshape(-1),
        torch.eye(n), cam, backend=backend, geometry_channels=n,
    ).image.double()  # fmt: skip
    d = (splats["means"].double() - torch.as_tensor(cam.center)).norm(dim=-1)
    d = d - d.detach().mean()
    a, first, second = weights.sum(-1), weights @ d, weights @ (d * d)
    pixels = torch.randperm(cam.height * cam.width, generator=torch.Generator().manual_seed(0))[:16]
    w = weights.reshape(-1, n)[pixels]  # the pairwise sum itself, on a few pixels
    pairwise = 0.5 * (w[:, :, None] * w[:, None, :] * (d[:, None] - d[None, :]) ** 2).sum((1, 2))
    moments = a * second - first * first
    torch.testing.assert_close(moments.reshape(-1)[pixels], pairwise, rtol=1e-9, atol=1e-12)
    return moments


@pytest.mark.parametrize("backend", ["torch", "numba"])
def test_depth_spread_is_the_pairwise_spread_of_the_blending_weights(field, scene, backend) -> None:
    cam = scene.camera(scene.names("train")[0])
    grads = []
    cotangent = torch.rand(cam.height, cam.width, generator=torch.Generator().manual_seed(1))
    for reference in (False, True):
        field.zero_grad(set_to_none=True)
        if reference:
            spread = _spread_reference(field, cam, backend)
        else:
            r = field.render(cam, backend=backend, depth_spread=True)
            assert field.render(cam, backend=backend).depth_spread is None  # only when asked for
            spread = r.depth_spread
            assert spread.shape == (cam.height, cam.width) and spread.min() >= 0
        (spread * cotangent).sum().backward()
        grads.append({k: p.grad.clone() for k, p in field.splats.items() if p.grad is not None})
        grads[-1]["value"] = spread.detach().double()
    field.zero_grad(set_to_none=True)
    scale = float(grads[1]["value"].max())
    assert scale > 0  # the view blends Gaussians at several depths
    torch.testing.assert_close(grads[0]["value"], grads[1]["value"], rtol=0, atol=2e-4 * scale)
    for name in ("means", "quats", "log_scales", "opacity_logits"):
        g = grads[1][name].float()
        assert g.abs().sum() > 0, name
        torch.testing.assert_close(grads[0][name], g, rtol=0, atol=2e-3 * float(g.abs().max())), name


def test_depth_spread_of_an_empty_view_and_of_one_depth_is_zero(field, scene, saved) -> None:
    away = Camera.look_at(eye=(0, 0, 50), target=(0, 0, 100), width=20, height=15)  # sees nothing
    empty = field.render(away, depth_spread=True)
    assert torch.equal(empty.depth_spread, torch.zeros(15, 20)) and torch.isfinite(empty.depth).all()
    cam = scene.camera(scene.names("train")[0])
    shell = LanguageField.load(saved)
    with torch.no_grad():  # every Gaussian 2 m from the camera, where it was seen
        center = torch.as_tensor(cam.center, dtype=torch.float32)
        offset = shell.splats["means"] - center
        shell.splats["means"].copy_(center + 2.0 * offset / offset.norm(dim=-1, keepdim=True))
        r = shell.render(cam, depth_spread=True)
    assert r.alpha.max() > 0.5 and float(r.depth_spread.max()) < 1e-5
    with torch.no_grad():
        single = field.select(torch.arange(1)).render(cam, depth_spread=True)
    assert float(single.depth_spread.abs().max()) < 1e-6


def test_render_from_a_free_camera(field) -> None:
    cam = Camera.look_at(eye=(2, -2, 1.5), target=(0, 0, 0.5), width=40, height=30)
    with torch.no_grad():
        r = field.render(cam)
    assert r.rgb.shape == (30, 40, 3) and r.depth.shape == (30, 40) and r.alpha.shape == (30, 40)
    assert torch.isfinite(r.rgb).all() and torch.isfinite(r.depth).all()
    assert r.alpha.max() > 0


def test_a_second_render_of_moved_gaussians_looks_their_cells_up_again(scene, saved) -> None:
    moved = LanguageField.load(saved)
    cam = scene.cameras("test")[0]
    moved.render(cam)
    with torch.no_grad():
        moved.splats["means"].add_(0.05)  # an in-place step, as the optimizer's
    again = moved.render(cam)
    fresh = LanguageField.load(saved)
    with torch.no_grad():
        fresh.splats["means"].add_(0.05)
    torch.testing.assert_close(again.rgb, fresh.render(cam).rgb, rtol=0, atol=0)
    assert moved.render(cam).rgb.equal(again.rgb)  # unchanged means: the same render


def test_shared_grid_features_give_the_same_renders_and_gradients(scene, saved) -> None:
    # Two views rendered from one grid read: same images, same gradients as two separate reads.
    cams = [scene.camera(n) for n in scene.names("train")[:2]]
    grads, images = [], []
    for shared in (False, True):
        field = LanguageField.load(saved).requires_grad_(True)
        grid = field.grid_features() if shared else None
        outs = [field.render(cam, grid=grid) for cam in cams]
        sum(o.rgb.square().sum() + o.depth.sum() + o.latents.square().sum() for o in outs).backward()
        images.append([o.rgb.detach() for o in outs])
        grads.append({name: p.grad.clone() for name, p in field.named_parameters() if p.grad is not None})
    for a, b in zip(*images, strict=True):
        assert torch.equal(a, b)
    assert grads[0].keys() == grads[1].keys() and "color.grid.table" in grads[0]
    for name in grads[0]:
        # Summation order only: the tolerance scales with the largest gradient (a means gradient of
        # about 500 differs by 3e-5 where the grid's rows are summed in another order).
        scale = float(grads[0][name].abs().max())
        assert torch.allclose(grads[0][name], grads[1][name], rtol=1e-5, atol=1e-6 * scale + 1e-7), name


def test_meta_is_typed_and_written_back_key_for_key(field, saved) -> None:
    """field.meta is a FieldMeta whatever it is given; its properties read what field.json holds, with
    the defaults of a partial file decided in one place; saving writes the same keys in the same order."""
    from langfield.io.field_meta import FieldMeta

    loaded = LanguageField.load(saved)
    assert isinstance(field.meta, FieldMeta) and isinstance(loaded.meta, FieldMeta)
    assert np.array_equal(loaded.meta.bounds, np.asarray(field.meta["bounds"], dtype=np.float64))
    assert np.allclose(loaded.meta.centre, loaded.meta.bounds.mean(axis=0))  # the grid's centre
    assert loaded.meta.backend == field.meta["backend"]
    assert loaded.meta.iterations == field.meta["iterations"] and loaded.meta.train_seconds > 0
    assert loaded.meta.tensors_sha256 == json.loads((saved / "field.json").read_text())["tensors_sha256"]
    written = list(json.loads((saved / "field.json").read_text()))
    assert [k for k in written if k in field.meta] == [k for k in field.meta if k in written]
    field2 = LanguageField(field.splats, field.color, {"bounds": [[0, 0, 0], [1, 1, 1]]})
    assert isinstance(field2.meta, FieldMeta)
    assert field2.meta.backend == "auto" and field2.meta.background == [0.0, 0.0, 0.0]
    assert field2.meta.scene is None and field2.meta.scene_args == {} and field2.meta.language is None
    assert field2.meta.lop_removed == 0 and field2.meta.train_seconds is None
    field2.meta["lop"] = [{"removed": 3}, {"removed": 4}]
    assert field2.meta.lop_removed == 7
