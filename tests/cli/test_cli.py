"""Tests of the ``langfield`` command (langfield/cli/), called in-process through ``main``."""

from __future__ import annotations

import contextlib
import io
import json
import math
import re
import shutil
import subprocess

import cv2
import numpy as np
import pytest
import torch

from langfield import LanguageField, load_scene
from langfield.cli import main
from langfield.cli.demo import DEMO_FRAMES
from langfield.viewer.browser import browser_missing
from langfield.viewer.video import read_video

W, H = 64, 48
REPORT_KEYS = {
    "PSNR",
    "SSIM",
    "masked_PSNR",
    "masked_SSIM",
    "mIoU",
    "mAcc",
    "train_seconds",
    "iterations",
    "iterations_per_second",
    "num_gaussians",
    "field_bytes",
    "backend",
    "feature_cosine",
    "oracle",
    "selection_3d",
    "by_view_class",
    "views",
}


@pytest.fixture(scope="module")
def scene_dir(room_factory):
    return room_factory(W, H)


@pytest.fixture(scope="module")
def trained(scene_dir, tmp_path_factory):
    """(field folder, exit status, stdout) of one `langfield train` run."""
    out = tmp_path_factory.mktemp("trained") / "out"
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        code = main(
            ["train", str(scene_dir), "--out", str(out), "--iterations", "30", "--num-gaussians", "500"]
        )
    return out, code, stdout.getvalue()


# ---------------------------------------------------------------- train / render / eval


def test_train_writes_the_field_and_a_summary(trained) -> None:
    out, code, stdout = trained
    assert code == 0
    for name in ("field.safetensors", "field.json", "gaussians.ply"):
        assert (out / name).is_file(), name
    lines = stdout.strip().splitlines()
    assert len(lines) == 1
    assert "PSNR" in lines[0] and "Gaussians" in lines[0]
    field = LanguageField.load(out)
    assert re.search(rf"\b{field.num_gaussians} Gaussians", lines[0])
    assert field.meta["config"]["iterations"] == 30 and field.meta["num_gaussians_init"] == 500


def test_render_writes_rgb_and_depth_for_every_test_view(trained, scene_dir, tmp_path, capsys) -> None:
    out, _, _ = trained
    save = tmp_path / "renders"
    assert main(["render", str(out), "--split", "test", "--save", str(save)]) == 0
    names = load_scene(scene_dir).names("test")
    assert names
    expected = {f"{n}_{kind}.png" for n in names for kind in ("rgb", "depth")}
    assert {p.name for p in save.iterdir()} == expected
    for name in expected:
        image = cv2.imread(str(save / name), cv2.IMREAD_UNCHANGED)
        assert image is not None and image.shape == (H, W, 3), name
    assert f"rendered {len(names)} test views" in capsys.readouterr().out


def test_eval_writes_the_format_report(trained, scene_dir, tmp_path, capsys) -> None:
    out, _, _ = trained
    report_path = tmp_path / "R.json"
    assert main(["eval", str(out), str(scene_dir), "--json", str(report_path)]) == 0
    report = json.loads(report_path.read_text())
    assert set(report) == REPORT_KEYS
    names = load_scene(scene_dir).names("test")
    assert [v["name"] for v in report["views"]] == names
    for view in report["views"]:
        assert set(view) >= {"name", "PSNR", "SSIM", "queries"}
        assert math.isfinite(view["PSNR"]) and -1 <= view["SSIM"] <= 1
    assert report["PSNR"] == pytest.approx(sum(v["PSNR"] for v in report["views"]) / len(names))
    assert report["iterations"] == 30
    field = LanguageField.load(out)
    assert report["num_gaussians"] == field.num_gaussians
    assert report["field_bytes"] == field.field_bytes() > 0
    assert 0 <= report["mIoU"] <= 1 and 0 <= report["mAcc"] <= 1  # the room is labelled
    assert all(set(q) == {"iou", "hit"} for v in report["views"] for q in v["queries"].values())
    assert set(report["feature_cosine"]) == {"subpart", "part", "whole"}  # the scene has feature caches
    md = report_path.with_suffix(".md")
    assert md.is_file() and "PSNR" in md.read_text()
    assert "PSNR" in capsys.readouterr().out


def test_eval_scores_the_training_views_on_request(trained, scene_dir, tmp_path, capsys) -> None:
    out, _, _ = trained
    report_path = tmp_path / "T.json"
    assert main(["eval", str(out), "--json", str(report_path), "--split", "train"]) == 0
    report = json.loads(report_path.read_text())
    assert [v["name"] for v in report["views"]] == load_scene(scene_dir).names("train")
    assert "train views" in capsys.readouterr().out


def test_eval_oracle_prints_the_ceiling_and_refuses_a_scene_without_caches(
    trained, scene_dir, tmp_path, capsys
) -> None:
    out, _, _ = trained
    assert main(["eval", str(out), "--json", str(tmp_path / "o.json"), "--oracle"]) == 0
    report = json.loads((tmp_path / "o.json").read_text())
    assert 0 < report["oracle"]["mIoU"] <= 1
    assert report["oracle"]["ratio"] == pytest.approx(report["mIoU"] / report["oracle"]["mIoU"])
    assert f"oracle on the true features: mIoU {report['oracle']['mIoU']:.3f}" in capsys.readouterr().out
    bare = tmp_path / "room"
    shutil.copytree(scene_dir, bare, ignore=shutil.ignore_patterns("test_000_*.npy"))
    code = main(["eval", str(out), str(bare), "--json", str(tmp_path / "b.json"), "--oracle"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "test_000_f.npy: missing; --oracle" in err[0]
    assert not (tmp_path / "b.json").exists()


def test_eval_reads_the_field_another_way_on_request(trained, scene_dir, tmp_path, capsys) -> None:
    from langfield.eval.evaluate import evaluate

    out, _, _ = trained
    before = (out / "field.json").read_bytes()
    args = ["eval", str(out), "--json", str(tmp_path / "c.json"), "--language-decode", "codebook"]
    assert main(args) == 0
    field = LanguageField.load(out)
    assert field.language_decode == "vote"
    field.language_decode = "codebook"
    expected = evaluate(field, load_scene(scene_dir))
    assert json.loads((tmp_path / "c.json").read_text())["mIoU"] == pytest.approx(expected["mIoU"])
    assert (out / "field.json").read_bytes() == before  # the folder keeps its own reading
    plain = LanguageField.load(out)
    plain.codebook = None
    plain.save(tmp_path / "plain")
    capsys.readouterr()
    args = ["eval", str(tmp_path / "plain"), str(scene_dir), "--json", str(tmp_path / "p.json")]
    assert main([*args, "--language-decode", "vote"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--language-decode vote" in err[0] and "no codebook" in err[0]
    assert not (tmp_path / "p.json").exists()


def test_eval_finds_the_scene_recorded_in_field_json(trained, tmp_path) -> None:
    out, _, _ = trained
    assert main(["eval", str(out), "--json", str(tmp_path / "r.json")]) == 0
    assert set(json.loads((tmp_path / "r.json").read_text())) == REPORT_KEYS


def test_field_trained_from_a_relative_scene_path_renders_from_another_folder(
    scene_dir, tmp_path, monkeypatch
) -> None:
    out = tmp_path / "out"
    monkeypatch.chdir(scene_dir.parent)
    args = ["train", scene_dir.name, "--out", str(out), "--iterations", "1", "--num-gaussians", "300"]
    assert main(args) == 0
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    assert main(["render", str(out), "--save", str(tmp_path / "renders")]) == 0


def test_train_bounds_flag_is_used(scene_dir, tmp_path) -> None:
    out = tmp_path / "out"
    args = ["train", str(scene_dir), "--out", str(out), "--iterations", "1", "--num-gaussians", "300"]
    assert main([*args, "--bounds=-1,-1,0,1,1,1.5"]) == 0
    assert LanguageField.load(out).meta["bounds"] == [[-1, -1, 0], [1, 1, 1.5]]


def test_train_bounds_flag_accepts_a_negative_first_value_as_documented(scene_dir, tmp_path) -> None:
    out = tmp_path / "out"
    args = ["train", str(scene_dir), "--out", str(out), "--iterations", "1", "--num-gaussians", "300"]
    assert main([*args, "--bounds", "-1,-1,0,1,1,1.5"]) == 0
    assert LanguageField.load(out).meta["bounds"] == [[-1, -1, 0], [1, 1, 1.5]]


def test_train_lambda_opacity_flag_reaches_the_config(scene_dir, tmp_path, capsys) -> None:
    out = tmp_path / "out"
    args = ["train", str(scene_dir), "--out", str(out), "--iterations", "1", "--num-gaussians", "300"]
    assert main([*args, "--lambda-opacity", "0"]) == 0
    assert LanguageField.load(out).meta["config"]["lambda_opacity"] == 0.0
    assert main([*args, "--lambda-opacity", "-1"]) == 2
    assert "lambda_opacity" in capsys.readouterr().err
    assert LanguageField.load(out).meta["config"]["lambda_opacity"] == 0.0  # the earlier field is kept


def test_train_language_decode_flag_reaches_the_field(scene_dir, tmp_path) -> None:
    args = ["train", str(scene_dir), "--iterations", "1", "--num-gaussians", "300"]
    assert main([*args, "--out", str(tmp_path / "a"), "--language-decode", "continuous"]) == 0
    assert main([*args, "--out", str(tmp_path / "b")]) == 0
    assert main([*args, "--out", str(tmp_path / "c"), "--language-decode", "codebook"]) == 0
    plain, default = LanguageField.load(tmp_path / "a"), LanguageField.load(tmp_path / "b")
    nearest = LanguageField.load(tmp_path / "c")
    assert plain.meta["config"]["language_decode"] == "continuous" and plain.codebook is None
    assert plain.language_decode == "continuous"
    assert default.meta["config"]["language_decode"] == "vote" and default.codebook is not None
    assert default.language_decode == "vote"
    assert nearest.language_decode == "codebook" and nearest.codebook is not None


# ---------------------------------------------------------------- bench / demo


def test_bench_takes_the_training_settings_for_its_curve(scene_dir, tmp_path, monkeypatch, capsys) -> None:
    import langfield.eval.bench as bench

    seen = {}
    monkeypatch.setattr(bench, "run_bench", lambda scene, **kw: seen.update(kw) or {})
    monkeypatch.setattr(bench, "format_table", lambda result: "")
    base = ["bench", "--scene", str(scene_dir), "--out", str(tmp_path / "b"), "--iterations", "0"]
    with contextlib.suppress(KeyError):  # the stand-in result has no backends to print
        main([*base, "--seed", "2", "--half-resolution-until", "0.2", "--num-gaussians", "300"])
    assert seen["settings"] == {"half_resolution_until": 0.2} and seen["seed"] == 2
    assert seen["num_gaussians"] == 300 and seen["iterations"] == 0  # bench's own flags of those names
    seen.clear()
    assert main([*base, "--drop-gamma", "-1"]) == 2 and not seen  # refused before any work
    assert "--drop-gamma" in capsys.readouterr().err


@pytest.mark.slow
def test_bench_writes_json_and_plot(scene_dir, tmp_path, capsys, monkeypatch) -> None:
    import langfield.eval.bench as bench

    configs = []
    train = bench.train
    spy = lambda scene, cfg, **kw: configs.append(cfg) or train(scene, cfg, **kw)  # noqa: E731
    monkeypatch.setattr(bench, "train", spy)
    out = tmp_path / "bench"
    json_path = out / "b.json"
    args = ["bench", "--scene", str(scene_dir), "--iterations", "20", "--every", "10", "--seed", "1"]
    args += ["--half-resolution-until", "0.5"]
    args += ["--num-gaussians", "300", "--out", str(out), "--json", str(json_path)]
    args += ["--overhead-iterations", "12", "--also-resolution", "2"]
    args += ["--language-iterations", "6", "--language-repeats", "1"]
    assert main(args) == 0
    result = json.loads(json_path.read_text())
    language = result["language_overhead"]
    assert language["iterations"] == 6 and len(language["ratios"]) == 1
    assert language["rgb_only_ms_per_iteration"] > 0 and language["ratio"] > 0
    overhead = result["lad_lop_overhead"]
    assert overhead["depth"] and overhead["plain_ms_per_iteration"] > 0 and overhead["ratio"] > 0
    assert set(result["backends"]) == {"torch", "numba"}
    for name, b in result["backends"].items():
        assert b["step_ms"] > 0, name
        assert b["image_max_abs_err"] <= 1e-4, name
    assert result["backends"]["torch"]["image_max_abs_err"] == 0
    assert (result["width"], result["height"]) == (W, H)
    assert result["num_gaussians"] == 300 and result["channels"] == 13
    assert [p["iterations"] for p in result["curve"]] == [10, 20]
    for point in result["curve"]:
        assert set(point) >= {"seconds", "iterations", "PSNR", "mIoU", "num_gaussians"}
        assert point["seconds"] > 0 and math.isfinite(point["PSNR"]) and point["num_gaussians"] > 0
    assert result["curve"][0]["seconds"] <= result["curve"][1]["seconds"]
    assert json_path.with_suffix(".png").is_file()
    assert list(result["curves"]) == [f"{W}x{H}", f"{W // 2}x{H // 2}"]
    assert all(0 <= p["mIoU"] <= 1 for c in result["curves"].values() for p in c)  # the room is labelled
    assert result["curve"][-1]["query_ms_per_view"]["ms"] > 0
    # The settings reach the curves' runs (both resolutions), and the others keep the defaults.
    assert result["settings"] == {"half_resolution_until": 0.5} and result["seed"] == 1
    assert [c.half_resolution_until for c in configs[:2]] == [0.5, 0.5]
    assert all(c.half_resolution_until == 0.33 and c.seed == 1 for c in configs[2:]) and configs[2:]
    stages = result["curve"][-1]["stages"]  # the curve's run, timed per stage
    assert stages["iterations"] == 20 and stages["stages"]["render"]["seconds"] > 0
    assert sum(v["share"] for v in stages["stages"].values()) == pytest.approx(1.0)
    quality = result["time_to_quality"][f"{W}x{H}"]
    assert quality["reference_PSNR"] == result["curve"][-1]["PSNR"] and quality["iterations"] in (10, 20)
    assert quality["iterations_per_second"] == pytest.approx(20 / result["curve"][-1]["seconds"])
    assert result["peak_memory_mib"] > 50
    raster = result["curve"][-1]["raster"]
    assert raster["num_gaussians"] == result["curve"][-1]["num_gaussians"] and raster["pairs"] > 0
    assert raster["pairs_per_second"] == pytest.approx(raster["pairs"] / (raster["step_ms"] / 1000))
    assert result["curve"][-1]["stopped"] == {"reason": "forced", "iteration": 20, "length": 20}
    printed = capsys.readouterr().out
    assert "faster than torch" in printed and "within 0.3 dB of the last point" in printed
    assert "seed 1, defaults but half_resolution_until=0.5" in printed
    assert "Gaussian-pixel pairs" in printed and "iterations went: " in printed
    assert "(median of 15 steps, " in printed
    assert "trained the forced length, 20 iterations" in printed


def test_bench_says_why_training_stopped() -> None:
    from langfield.eval.bench import format_stop

    color = {"best_before": 0.0667, "best_recent": 0.06604, "gain": 0.0099}
    plateau = {"reason": "plateau", "iteration": 1200, "length": 1500, "tolerance": 0.01}
    plateau["terms"] = {"color": color}
    text = format_stop(plateau)
    assert text.startswith("stopped at 1200 of 1500 iterations") and "color 0.99 %" in text
    assert "under 1 %" in text
    assert format_stop({"reason": "length", "iteration": 1500, "length": 1500}) == (
        "trained the scene's length, 1500 iterations"
    )


def test_time_to_quality_is_the_first_point_within_the_tolerance_of_the_last() -> None:
    from langfield.eval.bench import time_to_quality

    curve = [
        {"seconds": 10.0, "iterations": 100, "PSNR": 15.0},
        {"seconds": 20.0, "iterations": 200, "PSNR": 19.8},  # within 0.3 dB of 20.0
        {"seconds": 30.0, "iterations": 300, "PSNR": 20.4},  # above the last: a peak, then a fall
        {"seconds": 40.0, "iterations": 400, "PSNR": 20.0},
    ]
    quality = time_to_quality(curve)
    assert (quality["seconds"], quality["iterations"], quality["reference_PSNR"]) == (20.0, 200, 20.0)
    assert quality["iterations_per_second"] == 10.0
    assert time_to_quality(curve, tolerance_db=0.0)["iterations"] == 300
    assert time_to_quality(curve[:1])["iterations"] == 100  # one point: its own reference
    assert time_to_quality([{"seconds": 1.0, "iterations": 5, "PSNR": None}]) is None
    assert time_to_quality([]) is None


def test_tile_pairs_counts_each_tiles_list_times_its_pixels() -> None:
    from langfield.eval.bench import tile_pairs

    # 20x20 pixels: tiles of 16x16, 4x16, 16x4 and 4x4 pixels holding 1, 0, 2 and 3 Gaussians.
    offsets = torch.tensor([0, 1, 1, 3, 6])
    assert tile_pairs(offsets, 20, 20) == 256 + 0 + 2 * 64 + 3 * 16


def test_raster_throughput_counts_the_pairs_the_reference_binning_lists() -> None:
    from langfield.camera import Camera
    from langfield.eval.bench import cpu_peak_gflops, pair_flops, raster_throughput, tile_pairs
    from langfield.model import gaussians as G
    from langfield.raster.binning import bin_gaussians
    from langfield.raster.projection import project_gaussians

    cam = Camera.look_at((0, 0, 3), (0, 0, 0), (0, 1, 0), width=40, height=28)
    sp = G.init_gaussians(np.array([[-1.0, -1, -1], [1, 1, 1]]), 200, seed=0)
    means, quats, scales, opac = sp["means"], sp["quats"], G.scales(sp), G.opacities(sp)
    r = raster_throughput(means, quats, scales, opac, cam, channels=5, repeats=3)
    assert r["steps"] == 3 and r["step_ms_range"][0] <= r["step_ms"] <= r["step_ms_range"][1]
    with torch.no_grad():
        pr = project_gaussians(means, quats, scales, cam.world_to_camera(), cam.intrinsics(), 40, 28)
        offsets, _ = bin_gaussians(pr.means2d, pr.radii, pr.conics, opac.reshape(-1), pr.depths, 40, 28)
    assert r["pairs"] == tile_pairs(offsets, 40, 28) > 0
    assert r["flops_per_pair"] == pair_flops(5) and r["achieved_gflops"] > 0
    peak = cpu_peak_gflops()
    if peak["gflops"] is not None:
        assert peak["gflops"] == pytest.approx(peak["cores"] * peak["ghz"] * peak["fp32_lanes"] * 4)
        assert r["fraction_of_peak"] == pytest.approx(r["achieved_gflops"] / peak["gflops"])


def _cpuinfo(vendor: str, family: int, model: int, flags: str) -> str:
    return (
        f"processor\t: 0\nvendor_id\t: {vendor}\ncpu family\t: {family}\nmodel\t\t: {model}\n"
        f"model name\t: Some CPU\ncpu MHz\t\t: 2000.000\nflags\t\t: fpu sse2 {flags}\n"
    )


@pytest.mark.parametrize(
    ("vendor", "family", "model", "flags", "lanes"),
    [
        ("AuthenticAMD", 23, 1, "avx avx2 fma", 4),  # Zen (EPYC 7001): 128-bit FMA units
        ("AuthenticAMD", 23, 49, "avx avx2 fma", 8),  # Zen 2 (EPYC 7002): 256-bit units
        ("AuthenticAMD", 25, 1, "avx avx2 fma", 8),  # Zen 3
        ("AuthenticAMD", 25, 17, "avx avx2 fma avx512f", 8),  # Zen 4: AVX-512 in two 256-bit halves
        ("GenuineIntel", 6, 143, "avx avx2 fma avx512f", 16),
        ("GenuineIntel", 6, 85, "avx avx2 fma", 8),
        ("GenuineIntel", 6, 85, "", 4),
    ],
)
def test_fma_peak_counts_the_lanes_of_the_units_not_of_the_instructions(vendor, family, model, flags, lanes):
    from langfield.eval.bench import cpu_peak_gflops

    peak = cpu_peak_gflops(_cpuinfo(vendor, family, model, flags))
    assert peak["fp32_lanes"] == lanes and peak["ghz"] == 2.0
    assert peak["gflops"] == pytest.approx(peak["cores"] * 2.0 * lanes * 4)


@pytest.mark.slow
def test_demo_writes_report_renders_and_field(tmp_path, capsys) -> None:
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--iterations", "20", "--width", "48", "--height", "36"]) == 0
    assert (out / "queries" / "contact_sheet.png").is_file()
    printed = capsys.readouterr().out
    assert "PSNR" in printed and "mIoU" in printed
    report = json.loads((out / "report.json").read_text())
    assert set(report) == REPORT_KEYS and report["iterations"] == 20
    assert (out / "report.md").is_file()
    field = LanguageField.load(out / "field")
    assert field.num_gaussians == report["num_gaussians"]
    names = [v["name"] for v in report["views"]]
    assert names
    for name in names:
        rgb = cv2.imread(str(out / "renders" / f"{name}_rgb.png"))
        assert rgb is not None and rgb.shape == (36, 48, 3)
        assert (out / "renders" / f"{name}_depth.png").is_file()
    frames = read_video(out / "orbit_sofa.mp4")
    assert len(frames) == DEMO_FRAMES and frames[0].shape == (36, 96, 3)  # the render, the heat map
    assert cv2.imread(str(out / "orbit_frame.png")).shape == (36, 96, 3)
    assert (out / "viewer.jpg").is_file() == (browser_missing() is None), printed
    assert f"langfield view {out / 'field'}" in printed


# ---------------------------------------------------------------- bad input


def test_demo_refuses_a_negative_layout_before_writing(tmp_path, capsys) -> None:
    assert main(["demo", "--out", str(tmp_path / "demo"), "--layout", "-1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--layout" in err[0]
    assert not (tmp_path / "demo").exists()


def test_missing_scene_folder_exits_2_naming_it(tmp_path, capsys) -> None:
    missing = tmp_path / "no_such_scene"
    assert main(["train", str(missing), "--out", str(tmp_path / "out"), "--iterations", "1"]) == 2
    err = capsys.readouterr().err
    assert str(missing) in err and err.count("\n") == 1
    assert not (tmp_path / "out").exists()


def test_scene_with_a_missing_image_exits_2_naming_it(scene_dir, tmp_path, capsys) -> None:
    broken = tmp_path / "broken"
    shutil.copytree(scene_dir / "images", broken / "images")
    shutil.copy(scene_dir / "transforms.json", broken / "transforms.json")
    (broken / "images" / "train_001.png").unlink()
    assert main(["train", str(broken), "--out", str(tmp_path / "out"), "--iterations", "1"]) == 2
    err = capsys.readouterr().err
    assert "train_001.png" in err and err.count("\n") == 1


@pytest.mark.parametrize("command", ["eval", "render"])
def test_folder_without_a_field_exits_2_naming_it(scene_dir, tmp_path, capsys, command) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    if command == "eval":
        args = ["eval", str(empty), str(scene_dir), "--json", str(tmp_path / "r.json")]
    else:
        args = ["render", str(empty), "--save", str(tmp_path / "r"), "--scene", str(scene_dir)]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert str(empty / "field.json") in err
    assert not (tmp_path / "r.json").exists()


def test_bounds_with_three_numbers_is_an_argparse_error(scene_dir, tmp_path, capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["train", str(scene_dir), "--out", str(tmp_path / "out"), "--bounds", "1,2,3"])
    assert exc.value.code == 2
    assert "--bounds" in capsys.readouterr().err


def test_empty_bounds_box_exits_2(scene_dir, tmp_path, capsys) -> None:
    args = ["train", str(scene_dir), "--out", str(tmp_path / "out"), "--iterations", "1"]
    assert main([*args, "--bounds", "1,0,0,-1,1,1"]) == 2
    assert "bounds" in capsys.readouterr().err


def test_unknown_command_is_an_argparse_error(capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["fly"])
    assert exc.value.code == 2


@pytest.mark.skipif(shutil.which("langfield") is None, reason="console script not installed")
def test_console_script_smoke() -> None:
    exe = shutil.which("langfield")
    done = subprocess.run([exe, "--help"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0
    for command in ("train", "render", "eval", "bench", "demo", "query", "view"):
        assert command in done.stdout
