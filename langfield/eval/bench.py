"""Benchmarks: rasterizer backends per training step, and novel-view quality against wall time.

``langfield bench`` measures, on this machine:
1. forward+backward milliseconds of each backend on one scene (median of repeats; the image error of
   each backend against ``torch``);
2. a training curve on the built-in scene (or ``--scene``): novel-view PSNR at checkpoints against
   training wall time and Gaussian count, and from it the time to quality (:func:`time_to_quality`),
   the iterations per second over the run and the process's peak memory.
The JSON keys are fixed by docs/format.md.
"""

from __future__ import annotations

import json
import statistics
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from langfield.camera import Camera
from langfield.eval.evaluate import evaluate
from langfield.io.scene import Scene
from langfield.model import gaussians as G
from langfield.raster import BACKENDS, rasterize
from langfield.training.config import TrainConfig
from langfield.training.loop import LOSS_LOG_EVERY, evaluate_psnr, train
from langfield.training.stages import StageClock
from langfield.training.stopping import PATIENCE


def backend_step_ms(
    camera: Camera,
    bounds: np.ndarray,
    num_gaussians: int = 20000,
    channels: int = 13,
    seed: int = 0,
    repeats: dict[str, int] | None = None,
) -> dict[str, dict[str, float]]:
    """Median forward+backward time of each backend on the same random Gaussians in ``bounds``.

    Gaussians are initialised as training initialises them (uniform in the bounds, scales from
    nearest-neighbour distances, opacity 0.1 raised to a spread of values), with ``channels`` random
    feature channels (13 = RGB + 3 x 3 language latents + depth).
    """
    repeats = repeats or {"torch": 3, "numba": 10}
    splats = G.init_gaussians(bounds, num_gaussians, seed=seed)
    g = torch.Generator().manual_seed(seed)
    base = [
        splats["means"].detach(),
        splats["quats"].detach(),
        G.scales(splats).detach(),
        torch.rand(num_gaussians, generator=g) * 0.8 + 0.1,
        torch.rand(num_gaussians, channels, generator=g),
    ]
    weights = torch.randn(camera.height, camera.width, channels, generator=g)
    results: dict[str, dict[str, float]] = {}
    images: dict[str, torch.Tensor] = {}
    for backend in BACKENDS:
        times, images[backend] = _step_times(base, weights, camera, backend, repeats.get(backend, 3))
        seconds = statistics.median(times)
        results[backend] = {"step_ms": 1000 * seconds}
    for backend in BACKENDS:
        results[backend]["image_max_abs_err"] = float((images[backend] - images["torch"]).abs().max())
    return results


def _step_times(
    base: list[torch.Tensor], weights: torch.Tensor, camera: Camera, backend: str, repeats: int
) -> tuple[list[float], torch.Tensor]:
    """Seconds of each of ``repeats`` forward + backward renders of the Gaussians ``base`` (a first,
    untimed one compiles and warms the caches), and the rendered image. ``weights`` is the image's
    upstream gradient, handed to the backward as it is: the time is the rasterizer's, not a loss's."""
    times = []
    for i in range(repeats + 1):
        leaves = [t.clone().requires_grad_(True) for t in base]
        t0 = time.perf_counter()
        out = rasterize(*leaves, camera, backend=backend)
        torch.autograd.backward(out.image, weights)
        if i > 0:
            times.append(time.perf_counter() - t0)
    return times, out.image.detach()


# Arithmetic of one Gaussian-pixel pair with C channels, counted as the kernels do it: the offset
# and the conic's quadratic form (8), alpha and the transmittance update (4), one multiply-add per
# channel; the backward pass redoes the forward's share and adds the chain rule for each channel and
# the five geometry gradients (means2d, conic, opacity), about twice the forward's count.
def pair_flops(channels: int) -> int:
    """Floating-point operations of one Gaussian-pixel pair, forward + backward (the exp counted as one)."""
    forward = 12 + 2 * channels
    return 3 * forward


def cpu_peak_gflops(cpuinfo: str | None = None) -> dict[str, Any]:
    """An estimate of this machine's fp32 FMA peak: cores x clock x SIMD lanes x 2 FMA units x 2.

    The lanes are those of one FMA unit: 16 with AVX-512, 8 with AVX2, else 4, from /proc/cpuinfo's
    flags (or ``cpuinfo``'s text), halved where the units are narrower than the instructions (see
    :func:`fma_lanes`). The clock is its "cpu MHz" (the base clock a VM reports; boost clocks are
    higher), the cores those this process may run on. Two FMA units per core is an assumption (true of
    current x86 server cores).
    """
    import os

    if cpuinfo is None:
        cpuinfo = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").exists() else ""
    lines = cpuinfo.splitlines()
    mhz = [float(ln.split(":", 1)[1]) for ln in lines if ln.startswith("cpu MHz")]
    lanes, why = fma_lanes(cpuinfo)
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    ghz = (max(mhz) / 1000.0) if mhz else None
    peak = cores * ghz * lanes * 2 * 2 if ghz else None
    return {"cores": cores, "ghz": ghz, "fp32_lanes": lanes, "lanes_why": why, "fma_units": 2, "gflops": peak}


def cpuinfo_field(cpuinfo: str, name: str) -> str:
    """The first value of ``name`` in /proc/cpuinfo's text (its first CPU's), "" where there is none."""
    return next(
        (ln.split(":", 1)[1].strip() for ln in cpuinfo.splitlines() if ln.split(":")[0].strip() == name),
        "",
    )


def fma_lanes(cpuinfo: str) -> tuple[int, str]:
    """fp32 lanes of one FMA unit from /proc/cpuinfo's text, and why, in a few words.

    The widest instructions the flags name, except on two AMD families whose FMA units are half as
    wide as those instructions, each instruction passing through a unit in two halves: Zen and Zen+
    (family 23, models below 48: 128-bit units under AVX2; AMD's Software Optimization Guide for
    family 17h) and Zen 4 (family 25 with AVX-512: 256-bit units; A. Yee, "Zen4's AVX512 Teardown",
    numberworld.org, 2022). On the first, a packed 256-bit FMA chain measured 1.2 FMAs per cycle of
    the 2.0 GHz /proc/cpuinfo reports (about 1 per cycle of its boost clock), not 2.
    """

    def field(name: str) -> str:
        return cpuinfo_field(cpuinfo, name)

    flags = set(field("flags").split())
    amd = field("vendor_id") == "AuthenticAMD"
    family = int(field("cpu family")) if field("cpu family").isdigit() else -1
    model = int(field("model")) if field("model").isdigit() else -1
    if "avx512f" in flags:
        return (8, "AVX-512 on 256-bit units (AMD Zen 4)") if amd and family == 25 else (16, "AVX-512")
    if "avx2" in flags:
        return (
            (4, "AVX2 on 128-bit units (AMD Zen, Zen+)")
            if amd and family == 23 and model < 48
            else (8, "AVX2")
        )
    return 4, "SSE"


def tile_pairs(offsets: torch.Tensor, width: int, height: int) -> int:
    """Gaussian-pixel pairs the compositor visits: each tile's list length x its pixel count."""
    from langfield.raster.binning import TILE_SIZE

    tiles_x = -(-width // TILE_SIZE)
    tiles_y = -(-height // TILE_SIZE)
    tx = torch.arange(tiles_x)
    ty = torch.arange(tiles_y)
    w = torch.clamp(width - tx * TILE_SIZE, max=TILE_SIZE)
    h = torch.clamp(height - ty * TILE_SIZE, max=TILE_SIZE)
    pixels = (h[:, None] * w[None, :]).reshape(-1)
    counts = (offsets[1:] - offsets[:-1]).reshape(-1)
    return int((counts * pixels).sum())


def raster_throughput(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    camera: Camera,
    channels: int = 13,
    backend: str = "numba",
    repeats: int = 15,
    seed: int = 0,
) -> dict[str, Any]:
    """Forward + backward of :func:`rasterize` on these Gaussians with ``channels`` random feature
    channels: Gaussian-pixel pairs per second beside :func:`cpu_peak_gflops`.

    Pairs are those in the tile lists (:func:`tile_pairs`); a pixel whose transmittance is spent stops
    early, so the kernels evaluate at most that many. The time is the median of ``repeats`` steps (a
    step takes about 80 ms on fern; on a shared 2-core machine single steps vary by a fifth).
    ``fraction_of_peak`` is the pairs' arithmetic (:func:`pair_flops`) per second over the FMA peak:
    how far the kernels are from the machine.
    """
    from langfield.raster.binning_cpu import bin_gaussians_cpu
    from langfield.raster.projection_cpu import project_gaussians_cpu

    with torch.no_grad():
        projected = project_gaussians_cpu(
            means, quats, scales, camera.world_to_camera(), camera.intrinsics(), camera.width, camera.height
        )
        offsets, _ = bin_gaussians_cpu(
            projected.means2d,
            projected.radii,
            projected.conics,
            opacities,
            projected.depths,
            camera.width,
            camera.height,
        )
    pairs = tile_pairs(offsets, camera.width, camera.height)
    g = torch.Generator().manual_seed(seed)
    feats = torch.rand(means.shape[0], channels, generator=g)
    weights = torch.randn(camera.height, camera.width, channels, generator=g)
    base = [t.detach() for t in (means, quats, scales, opacities.reshape(-1), feats)]
    times, _ = _step_times(base, weights, camera, backend, repeats)
    seconds = statistics.median(times)
    peak = cpu_peak_gflops()
    rate = pairs / seconds if seconds > 0 else None
    achieved = rate * pair_flops(channels) / 1e9 if rate else None
    return {
        "backend": backend,
        "num_gaussians": int(means.shape[0]),
        "width": camera.width,
        "height": camera.height,
        "channels": channels,
        "pairs": pairs,
        "step_ms": 1000 * seconds,
        "step_ms_range": [1000 * min(times), 1000 * max(times)],
        "steps": len(times),
        "pairs_per_second": rate,
        "flops_per_pair": pair_flops(channels),
        "achieved_gflops": achieved,
        "peak": peak,
        "fraction_of_peak": achieved / peak["gflops"] if achieved and peak["gflops"] else None,
    }


def training_curve(
    scene: Scene,
    iterations: int | None,
    every: int,
    seed: int = 0,
    backend: str = "auto",
    settings: Mapping[str, Any] | None = None,
) -> list[dict]:
    """Trains once (TrainConfig's defaults, but for ``settings``) and records novel-view PSNR, mIoU
    (labelled scenes) and Gaussian count.

    A point every ``every`` iterations and at the end; evaluation time is not training time. The
    last point also carries the query latency (see :func:`query_latency`) and the run's seconds per
    training stage (:class:`~langfield.training.stages.StageClock`'s report).
    """
    points: list[dict[str, Any]] = []
    labelled = any(scene.segmentations(n) for n in scene.names("test"))

    def record(step: int, seconds: float, field) -> None:
        point: dict[str, Any] = {"seconds": seconds, "iterations": step, "mIoU": None, "mAcc": None}
        if labelled and field.has_language:
            report = evaluate(field, scene)
            point.update(PSNR=report["PSNR"], mIoU=report["mIoU"], mAcc=report["mAcc"])
        else:
            point["PSNR"] = evaluate_psnr(field, scene)
        point["num_gaussians"] = field.num_gaussians
        points.append(point)

    clock = StageClock()
    field = train(
        scene,
        TrainConfig(**{"backend": backend, **(settings or {}), "iterations": iterations, "seed": seed}),
        progress=True,
        callback=record,
        callback_every=every,
        clock=clock,
    )
    last = points[-1]
    last["stages"] = clock.report()
    last["stopped"] = field.meta.get("stopped")
    if labelled and field.has_language:
        last["query_ms_per_view"] = query_latency(field, scene)
    sp = field.splats  # the rasterizer on the Gaussians training ended with
    last["raster"] = raster_throughput(
        sp["means"], sp["quats"], G.scales(sp), G.opacities(sp), scene.cameras("train")[0]
    )
    return points


def time_to_quality(points: list[dict], tolerance_db: float = 0.3) -> dict[str, Any] | None:
    """Training time until novel-view PSNR first comes within ``tolerance_db`` of the run's last point.

    The last point stands for the converged run, so the figure is as good as the run is long: a curve
    still rising at its end understates the time. Also the iterations per second over the whole run.
    None for a curve without PSNR.

    Returns:
        {"reference_PSNR", "tolerance_dB", "seconds", "iterations", "iterations_per_second"}.
    """
    scored = [p for p in points if p.get("PSNR") is not None]
    if not scored:
        return None
    reference = scored[-1]["PSNR"]
    first = next(p for p in scored if p["PSNR"] >= reference - tolerance_db)
    last = points[-1]
    return {
        "reference_PSNR": reference,
        "tolerance_dB": tolerance_db,
        "seconds": first["seconds"],
        "iterations": first["iterations"],
        "iterations_per_second": last["iterations"] / last["seconds"] if last["seconds"] > 0 else None,
    }


def format_stop(stopped: dict[str, Any]) -> str:
    """Why training stopped (field.json's ``stopped``), in words."""
    n, length = stopped["iteration"], stopped["length"]
    if stopped["reason"] != "plateau":
        whose = "forced" if stopped["reason"] == "forced" else "scene's"
        return f"trained the {whose} length, {n} iterations"
    gains = ", ".join(f"{t} {100 * v['gain']:.2f} %" for t, v in stopped["terms"].items())
    return (
        f"stopped at {n} of {length} iterations: the last {PATIENCE * LOSS_LOG_EVERY} bettered the best "
        f"fitting loss by {gains} "
        f"(under {100 * stopped['tolerance']:g} %)"
    )


def peak_memory_mib() -> float:
    """The process's peak resident memory so far, MiB (Linux's ru_maxrss is in KiB)."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def query_latency(field, scene: Scene, repeats: int = 3) -> dict[str, float]:
    """Median milliseconds of one phrase's relevance + mask on a test view, once the field is loaded.

    The first view of the first query builds what queries share (reported as ``first_view_ms``): the
    codebook entries' relevancy, or for a continuous field the decoder lattice; after that every view
    costs a render of the latent channels and a look-up.
    """
    phrases = sorted({p for n in scene.names("test") for p in scene.segmentations(n)})
    cams = scene.cameras("test")
    t0 = time.perf_counter()
    q = field.query(phrases[0], scene=scene)
    q.mask(cams[0])
    first = time.perf_counter() - t0
    times = []
    with torch.no_grad():
        for _ in range(repeats):
            for cam in cams:
                t0 = time.perf_counter()
                q.mask(cam)
                times.append(time.perf_counter() - t0)
    return {"ms": 1000 * statistics.median(times), "first_view_ms": 1000 * first, "width": cams[0].width}


def language_overhead(
    scene: Scene, iterations: int = 100, seed: int = 0, repeats: int = 3
) -> dict[str, float | list[float]]:
    """Milliseconds per training iteration with and without the language field, same scene and length.

    The two runs alternate ``repeats`` times; ``ratio`` is the median of the pairs' ratios (each pair
    runs back to back, so it sees one state of a shared machine, where single runs swing by 15-20 %),
    ``ratios`` lists them all so the spread is in the report, and the ms figures are medians. The
    autoencoder's one-off training is reported apart (it runs once per scene, before the loop).
    """
    times: dict[str, list[float]] = {"rgb_only": [], "with_language": []}
    result: dict[str, float | list[float]] = {}
    for _ in range(max(1, repeats)):
        for name, language in (("rgb_only", False), ("with_language", True)):
            cfg = TrainConfig(iterations=iterations, seed=seed, language=language)
            field = train(scene, cfg, progress=False)
            times[name].append(1000 * field.meta.train_seconds / iterations)
            if language and field.meta.language:
                result["autoencoder_seconds"] = field.meta.language["autoencoder_stats"]["seconds"]
    for name, values in times.items():
        result[f"{name}_ms_per_iteration"] = float(np.median(values))
    # Each pair ran back to back, so its ratio sees one machine state; the median pair is the figure.
    result["ratios"] = [
        round(b / a, 3) for a, b in zip(times["rgb_only"], times["with_language"], strict=True)
    ]
    result["ratio"] = float(np.median(result["ratios"]))
    result["iterations"] = iterations
    return result


def lad_lop_overhead(scene: Scene, iterations: int = 1000, seed: int = 0) -> dict[str, float]:
    """Milliseconds per iteration of the full method against the same run without L_D and LOP.

    Averaged over a whole run of ``iterations`` (LOP fires every 1000 by default, so a run of 1000
    includes one round); both runs train the language field.
    """
    result: dict[str, float] = {}
    for name, extra in (("plain", {"depth": False, "lop": False}), ("lad_lop", {})):
        field = train(scene, TrainConfig(iterations=iterations, seed=seed, **extra), progress=False)
        result[f"{name}_ms_per_iteration"] = 1000 * field.meta.train_seconds / iterations
        if name == "lad_lop":
            result["lop_removed"] = field.meta.lop_removed
            result["depth"] = field.meta.depth is not None
    result["ratio"] = result["lad_lop_ms_per_iteration"] / result["plain_ms_per_iteration"]
    return result


def plot_curve(curves: dict[str, list[dict]] | list[dict], path: Path) -> None:
    """Novel-view PSNR and mIoU against training seconds and against Gaussian count, one PNG.

    ``curves``: {label: points} (one line per resolution), or one list of points.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if isinstance(curves, list):
        curves = {"": curves}
    fig, axes = plt.subplots(2, 2, figsize=(9, 6.5))
    for label, points in curves.items():
        secs = [p["seconds"] for p in points]
        gauss = [p["num_gaussians"] for p in points]
        for row, key in enumerate(("PSNR", "mIoU")):
            values = [p.get(key) for p in points]
            if any(v is None for v in values):
                continue
            axes[row, 0].plot(secs, values, "o-", label=label or None)
            axes[row, 1].plot(gauss, values, "o-", label=label or None)
    axes[0, 0].set_ylabel("novel-view PSNR (dB)")
    axes[1, 0].set_ylabel("novel-view mIoU")
    axes[1, 0].set_xlabel("training wall time (s)")
    axes[1, 1].set_xlabel("Gaussians")
    for ax in axes.flat:
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0] and len(curves) > 1:
            ax.legend(fontsize=8)
    fig.suptitle("langfield: quality against training time")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def format_table(result: dict) -> str:
    """Human-readable tables of a bench result."""
    lines = [
        f"rasterizer, {result['width']}x{result['height']}, {result['num_gaussians']} Gaussians, "
        f"{result['channels']} channels (forward+backward, median):"
    ]
    ref = result["backends"]["torch"]["step_ms"]
    for name, r in result["backends"].items():
        lines.append(
            f"  {name:6s} {r['step_ms']:9.1f} ms   {ref / r['step_ms']:6.1f}x vs torch   "
            f"max |image - torch| {r['image_max_abs_err']:.2e}"
        )
    lo = result.get("language_overhead")
    if lo:
        lines.append(
            f"training iteration: {lo['rgb_only_ms_per_iteration']:.0f} ms RGB only, "
            f"{lo['with_language_ms_per_iteration']:.0f} ms with the language field "
            f"(+{100 * (lo['ratio'] - 1):.0f} %, median of {len(lo.get('ratios', [1]))} interleaved pairs: "
            f"{', '.join(f'+{100 * (r - 1):.0f}' for r in lo.get('ratios', []))} %); "
            f"autoencoder once per scene {lo.get('autoencoder_seconds', 0):.1f} s"
        )
    oh = result.get("lad_lop_overhead")
    if oh:
        lines.append(
            f"training iteration: {oh['plain_ms_per_iteration']:.0f} ms without L_D and LOP, "
            f"{oh['lad_lop_ms_per_iteration']:.0f} ms with both (+{100 * (oh['ratio'] - 1):.0f} %, "
            f"LOP removed {oh['lop_removed']} Gaussians)"
        )
    for label, points in (result.get("curves") or {"": result.get("curve") or []}).items():
        if not points:
            continue
        changed = ", ".join(f"{k}={v}" for k, v in (result.get("settings") or {}).items())
        how = f"seed {result.get('seed', 0)}, " + (f"defaults but {changed}" if changed else "defaults")
        lines.append(f"training curve (novel views){' at ' + label if label else ''}, {how}:")
        lines.append("  iterations   seconds    PSNR    mIoU   Gaussians")
        for p in points:
            psnr_txt = f"{p['PSNR']:7.2f}" if p.get("PSNR") is not None else "    n/a"
            miou_txt = f"{p['mIoU']:7.3f}" if p.get("mIoU") is not None else "    n/a"
            lines.append(
                f"  {p['iterations']:10d} {p['seconds']:9.1f} {psnr_txt} {miou_txt} {p['num_gaussians']:11d}"
            )
        quality = (result.get("time_to_quality") or {}).get(label)
        if quality:
            lines.append(
                f"  within {quality['tolerance_dB']} dB of the last point "
                f"({quality['reference_PSNR']:.2f} dB) "
                f"after {quality['seconds']:.1f} s ({quality['iterations']} iterations); "
                f"{quality['iterations_per_second']:.2f} iterations/s over the run"
            )
        stopped = points[-1].get("stopped")
        if stopped:
            lines.append(f"  {format_stop(stopped)}")
        stages = points[-1].get("stages")
        if stages and stages["seconds"] > 0:
            lines.append(format_stages(stages))
        raster = points[-1].get("raster")
        if raster:
            lines.append(format_throughput(raster))
        latency = points[-1].get("query_ms_per_view")
        if latency:
            lines.append(
                f"  query (relevance + mask, one phrase) at {latency['width']} px wide: "
                f"{latency['ms']:.0f} ms per view "
                f"(first view, shared tables included: {latency['first_view_ms']:.0f} ms)"
            )
    if result.get("peak_memory_mib"):
        lines.append(f"peak memory over the training runs: {result['peak_memory_mib']:.0f} MiB")
    return "\n".join(lines)


def format_stages(report: dict) -> str:
    """One line: the training run's seconds per stage, largest first, with their shares."""
    parts = sorted(report["stages"].items(), key=lambda kv: -kv[1]["seconds"])
    text = ", ".join(f"{name} {v['seconds']:.1f} s ({100 * v['share']:.0f} %)" for name, v in parts)
    return f"  where the {report['seconds']:.1f} s of {report['iterations']} iterations went: {text}"


def format_throughput(r: dict) -> str:
    """One line: the rasterizer's pairs per second on the trained Gaussians against the FMA peak."""
    peak = r["peak"]
    peak_txt = (
        f"{peak['gflops']:.0f} GFLOP/s fp32 FMA peak ({peak['cores']} cores x {peak['ghz']:.2f} GHz x "
        f"{peak['fp32_lanes']} lanes ({peak['lanes_why']}) x {peak['fma_units']} FMA units x 2)"
        if peak["gflops"]
        else "no FMA peak estimate (no clock in /proc/cpuinfo)"
    )
    frac = f", {100 * r['fraction_of_peak']:.1f} % of the peak" if r.get("fraction_of_peak") else ""
    return (
        f"  rasterizer ({r['backend']}, forward+backward) on the {r['num_gaussians']} trained Gaussians at "
        f"{r['width']}x{r['height']}: {r['pairs'] / 1e6:.1f} M Gaussian-pixel pairs in {r['step_ms']:.0f} ms "
        f"{_step_spread(r)}"
        f"= {r['pairs_per_second'] / 1e6:.1f} M pairs/s x {r['flops_per_pair']} FLOP = "
        f"{r['achieved_gflops']:.1f} GFLOP/s against {peak_txt}{frac}"
    )


def _step_spread(r: dict) -> str:
    """The steps' count and spread, where the record has them (older bench.json files do not)."""
    if not r.get("step_ms_range"):
        return ""
    lo, hi = r["step_ms_range"]
    return f"(median of {r['steps']} steps, {lo:.0f}-{hi:.0f} ms) "


def run_bench(
    scene: Scene,
    *,
    iterations: int | None,
    every: int,
    num_gaussians: int = 20000,
    channels: int = 13,
    json_path: Path | None = None,
    plot_path: Path | None = None,
    seed: int = 0,
    overhead_iterations: int = 1000,
    language_iterations: int = 100,
    language_repeats: int = 3,
    extra_scenes: dict[str, Scene] | None = None,
    settings: Mapping[str, Any] | None = None,
) -> dict:
    """Runs both benchmarks on ``scene``; writes JSON and the plot where asked. ``settings``: TrainConfig
    settings of the curves' runs (recorded in the result; the other timed runs keep the defaults).

    The training curves run first: after the backend timing has allocated and freed the reference
    rasterizer's large blocks, glibc's allocator serves the training's tensors more slowly (fern: 1.54
    -> 2.23 s per iteration in one process), and the curve should show what ``langfield train`` sees.
    """
    camera = scene.cameras("train")[0]
    bounds = np.asarray(scene.bounds())
    settings = dict(settings or {})
    result: dict[str, Any] = {"seed": seed, "settings": settings}
    scenes = {f"{camera.width}x{camera.height}": scene, **(extra_scenes or {})}  # other resolutions last
    result["curves"] = {
        label: training_curve(s, iterations, every, seed, settings=settings) if iterations != 0 else []
        for label, s in scenes.items()
    }
    result["curve"] = next(iter(result["curves"].values()))
    result["time_to_quality"] = {label: time_to_quality(points) for label, points in result["curves"].items()}
    has_language = all(scene.feature_paths(n) is not None for n in scene.names("train"))
    result["language_overhead"] = (
        language_overhead(scene, language_iterations, seed, language_repeats)
        if has_language and language_iterations > 0
        else None
    )
    has_depth = all(scene.depth(n) is not None for n in scene.names("train"))
    result["lad_lop_overhead"] = (
        lad_lop_overhead(scene, overhead_iterations, seed)
        if has_language and has_depth and overhead_iterations > 0
        else None
    )
    result["peak_memory_mib"] = peak_memory_mib()  # of the training runs: the timing below is apart
    result.update(
        backends=backend_step_ms(camera, bounds, num_gaussians, channels, seed),
        width=camera.width,
        height=camera.height,
        num_gaussians=num_gaussians,
        channels=channels,
        threads=torch.get_num_threads(),
    )
    if json_path is not None:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(result, indent=2))
    if plot_path is not None and result["curve"]:
        plot_curve(result["curves"], plot_path)
    return result
