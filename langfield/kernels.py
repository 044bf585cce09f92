"""The CPU kernels' one-time compilation: said when it happens, and done ahead by ``make install``.

numba compiles the rasterizer's and the hash grid's kernels the first time a process calls them and
keeps the machine code on disk (``cache=True``, in ``__pycache__`` beside the sources); later processes
load it in well under a second. The first compilation takes about two minutes on two cores, which a user
would otherwise see as an unexplained pause in their first ``langfield train``. :func:`notice_once`
prints one line before it; :func:`langfield.cli.warmup.main` (run by ``make install``) compiles every
kernel on a tiny input so that the first real run starts at once.

Where a run finds kernels uncompiled (a checkout without ``make install``, an edited kernel, a new
``NUMBA_CACHE_DIR``), :func:`notice_once` compiles them in a child process and this process then loads
them from disk, as every later run does. Compiled in the process that uses them, numba's fastmath
kernels are not the machine code it writes to disk: a 60-iteration room run trained to other bits on
its first run than on its second (the compositing's second stream differed in 1,061 of 4,800 pixels, by
up to 2.4e-7, on the first call). Compiling in the child makes the first run train the field every
later run trains.

A leaf module: the rasterizer and the hash grid call :func:`notice_once`, so it finds the kernel
modules by name (:data:`KERNEL_MODULES`) rather than importing them.
"""

from __future__ import annotations

import importlib
import os
import subprocess
import sys

__all__ = [
    "BACKENDS",
    "BACKEND_ALIASES",
    "COMPILE_HERE",
    "KERNEL_MODULES",
    "configure_numba",
    "notice_once",
    "resolve_backend",
    "reuse_freed_memory",
    "uncompiled_kernels",
]

# The backends, for the rasterizer (langfield.raster.kernels) and the hash grid alike: "torch" the
# PyTorch references, "numba" the numba kernels; "auto" chooses "numba". Both run on the CPU, so the
# numba backend is named for what it is; "cpu", its earlier name, is still accepted (and fields saved
# with it still load).
BACKENDS: tuple[str, ...] = ("torch", "numba")
BACKEND_ALIASES: dict[str, str] = {"cpu": "numba"}
_aliases_noticed: set[str] = set()


def resolve_backend(backend: str) -> str:
    """The concrete backend name for ``backend`` ("auto" -> "numba"; the alias "cpu" -> "numba", said
    once per process on stderr)."""
    if backend == "auto":
        return "numba"
    if backend in BACKEND_ALIASES:
        if backend not in _aliases_noticed:
            _aliases_noticed.add(backend)
            print(
                f"langfield: backend {backend!r} is now called {BACKEND_ALIASES[backend]!r}",
                file=sys.stderr,
                flush=True,
            )
        return BACKEND_ALIASES[backend]
    if backend not in BACKENDS:
        raise ValueError(f"unknown rasterizer backend {backend!r}; choose from auto, {', '.join(BACKENDS)}")
    return backend


# The modules whose numba kernels are cached on disk.
KERNEL_MODULES = (
    "langfield.raster.projection_cpu",
    "langfield.raster.binning_cpu",
    "langfield.raster.composite_cpu",
    "langfield.model.hashgrid_cpu",
    "langfield.training.ssim_cpu",
)

_noticed = False


def configure_numba() -> None:
    """numba's settings for the kernels; every kernel module calls it before defining its kernels.

    - The workqueue threading layer unless the user set NUMBA_THREADING_LAYER: numba's OpenMP layer
      keeps its threads spinning after each kernel, and they fight PyTorch's own OpenMP threads for the
      2 cores: every torch op right after a kernel ran ~50x slower. The workqueue layer parks its threads.
    - LLVM's SLP vectoriser on unless the user set NUMBA_SLP_VECTORIZE (numba leaves it off). The
      rasterizer's loops over a row's 16 pixels are unrolled in full before the loop vectoriser runs,
      so only SLP packs them into vector instructions; without it they ran as 16 scalar operations
      each (fern's forward: 97 ms against 29 ms with it and one per-pixel array per tile, see
      ``composite_cpu._F_ROWS``). numba reads the setting when it compiles, not at import.
    """
    import numba

    if "NUMBA_THREADING_LAYER" not in os.environ:
        numba.config.THREADING_LAYER = "workqueue"
    if "NUMBA_SLP_VECTORIZE" not in os.environ:
        numba.config.SLP_VECTORIZE = 1


_MALLOC_SET = False
# glibc's mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3


def reuse_freed_memory() -> bool:
    """Asks glibc's malloc to keep freed memory for the next allocation; True if it took.

    A training step allocates and frees the same large tensors every iteration (the hash grid's corner
    rows alone are 48 MB for 50k Gaussians). Above its mmap threshold (at most 32 MB by default) glibc
    maps every such block afresh and returns it on free, so each step pays a page fault per 4 KB page
    it touches: about 12,000 faults and 10 % of a fern step (208 -> 186 ms at 50k Gaussians, measured
    with the faults counted per step). Raising the mmap and trim thresholds keeps the blocks in the heap
    for reuse; the process's memory then stays at its peak until it exits, which a training run reaches
    anyway. Once per process; a C library without ``mallopt`` (not glibc) is left alone. Set
    ``LANGFIELD_MALLOC=system`` to keep glibc's defaults.
    """
    global _MALLOC_SET
    if _MALLOC_SET or os.environ.get("LANGFIELD_MALLOC") == "system":
        return _MALLOC_SET
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        ok = libc.mallopt(_M_MMAP_THRESHOLD, 1 << 30) == 1
        ok = ok and libc.mallopt(_M_TRIM_THRESHOLD, (1 << 31) - 1) == 1
    except (OSError, AttributeError):
        ok = False
    _MALLOC_SET = ok
    return ok


def _dispatchers() -> dict[str, object]:
    """Every disk-cached numba kernel of langfield, by qualified name."""
    from numba.core.registry import CPUDispatcher

    found = {}
    for module in map(importlib.import_module, KERNEL_MODULES):
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


# Compile in this process rather than in a child: set by ``make install``'s warm-up ("1") and, for the
# child that compiles for a run, to "child" (which says nothing: the run has said it).
COMPILE_HERE = "LANGFIELD_COMPILE_HERE"


def notice_once() -> None:
    """Once per process, before the first kernel runs: if kernels have no machine code on disk, says so
    in one line on stderr and compiles them in a child process (the module's docstring says why), so that
    this process loads them from disk. Where the child fails or cannot write numba's cache, this process
    compiles them itself, as numba would, and says so."""
    global _noticed
    if _noticed:
        return
    _noticed = True
    here = os.environ.get(COMPILE_HERE)
    missing = uncompiled_kernels()
    if not missing or here == "child":
        return
    print(
        f"langfield: compiling {len(missing)} CPU kernels, once (about two minutes on two cores; "
        "later runs load them)",
        file=sys.stderr,
        flush=True,
    )
    if here:
        return
    code = "from langfield.cli.warmup import warm_up; warm_up()"
    env = {**os.environ, COMPILE_HERE: "child"}
    child = subprocess.run([sys.executable, "-c", code], env=env, check=False)
    left = uncompiled_kernels()
    if child.returncode != 0 or left:
        print(
            f"langfield: {len(left)} CPU kernels were not cached by a separate compile "
            f"(exit {child.returncode}); compiling them in this process, whose last bits may differ "
            "from a later run's",
            file=sys.stderr,
            flush=True,
        )
