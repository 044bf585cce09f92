"""The CPU kernels' one-time compilation: said when it happens, and done ahead by ``make install``.

numba compiles the rasterizer's and the hash grid's kernels the first time a process calls them and
keeps the machine code on disk (``cache=True``, in ``__pycache__`` beside the sources); later processes
load it in well under a second. The first compilation takes about a minute on two cores, which a user
would otherwise see as an unexplained pause in their first ``langfield train``. :func:`notice_once`
prints one line before it; :func:`main` (run by ``make install``) compiles every kernel on a tiny
input so that the first real run starts at once.
"""

from __future__ import annotations

import sys
import time

__all__ = ["main", "notice_once", "uncompiled_kernels", "warm_up"]

_noticed = False


def _dispatchers() -> dict[str, object]:
    """Every disk-cached numba kernel of langfield, by qualified name."""
    from numba.core.registry import CPUDispatcher

    import langfield.hashgrid_cpu as hashgrid
    import langfield.raster.cpu_backend as backend
    import langfield.raster.cpu_geometry as geometry

    found = {}
    for module in (geometry, backend, hashgrid):
        for name, value in vars(module).items():
            if isinstance(value, CPUDispatcher) and value._cache.__class__.__name__ == "FunctionCache":
                found[f"{module.__name__}.{name}"] = value
    return found


def uncompiled_kernels() -> list[str]:
    """The kernels with no machine code on disk for their current source (compiled on first call).

    Reads numba's cache index (a private interface: if it changes, every kernel is reported cached and
    only the notice is lost, never a result).
    """
    missing = []
    for name, dispatcher in _dispatchers().items():
        try:
            if not dispatcher.signatures and not dispatcher._cache._cache_file._load_index():
                missing.append(name)
        except Exception:  # noqa: BLE001 - see the docstring: a changed numba internal is not an error
            continue
    return missing


def notice_once() -> None:
    """Prints one line to stderr, once per process, if the CPU kernels are about to be compiled."""
    global _noticed
    if _noticed:
        return
    _noticed = True
    missing = uncompiled_kernels()
    if missing:
        print(
            f"langfield: compiling {len(missing)} CPU kernels, once (up to a minute; later runs load them)",
            file=sys.stderr,
            flush=True,
        )


def warm_up() -> float:
    """Compiles (or loads) every kernel by rendering a few Gaussians forward and backward with the
    ``cpu`` backend and a hash-grid colour field, as training does. Returns the seconds it took."""
    import torch

    from langfield.camera import Camera
    from langfield.fields import ColorField
    from langfield.hashgrid import HashGridConfig
    from langfield.raster import rasterize

    t0 = time.perf_counter()
    notice_once()
    generator = torch.Generator().manual_seed(0)
    n = 64
    means = (torch.rand(n, 3, generator=generator) - 0.5).requires_grad_(True)
    quats = torch.randn(n, 4, generator=generator).requires_grad_(True)
    scales = torch.full((n, 3), 0.05).requires_grad_(True)
    opacities = torch.full((n,), 0.5).requires_grad_(True)
    color = ColorField(HashGridConfig(n_levels=2, log2_table_size=8), torch.zeros(3), 1.0)
    features = color(means, torch.nn.functional.normalize(means, dim=-1))
    camera = Camera.look_at(eye=(0, -2, 0.5), target=(0, 0, 0), width=32, height=24)
    out = rasterize(means, quats, scales, opacities, features, camera, backend="cpu")
    (out.image.sum() + out.alpha.sum()).backward()
    return time.perf_counter() - t0


def main() -> None:
    """``make install``'s warm-up: compiles what is not cached and says how long it took."""
    todo = len(uncompiled_kernels())
    seconds = warm_up()
    left = uncompiled_kernels()
    state = "all cached" if not left else f"still not cached: {', '.join(left)}"
    print(f"langfield kernels: {todo} compiled, {seconds:.1f} s; {state}")
