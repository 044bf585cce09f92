"""langfield: open-vocabulary 3D language fields from three posed photos (SOVGaussian) on the CPU.

>>> import langfield
>>> scene = langfield.load_scene("scene/")                        # doctest: +SKIP
>>> field = langfield.train(scene, langfield.TrainConfig(iterations=2000))   # doctest: +SKIP
"""

import os as _os

# The fast backend's numba kernels and PyTorch's OpenMP threads share the machine's cores. OpenMP's
# default is to spin after every parallel region, so torch's idle threads took the cores from numba's
# workers and every torch op after a kernel waited for a time slice (a 20k-Gaussian step: 47 -> 39 ms,
# a training iteration much more). Passive waiting parks them. It only takes effect if torch is not
# imported yet; a user's own OMP_WAIT_POLICY wins.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from langfield.camera import Camera
from langfield.eval.evaluate import evaluate
from langfield.field import LanguageField, Render
from langfield.io.scene import Scene, SceneError, load_scene
from langfield.training.config import TrainConfig
from langfield.training.loop import train

__all__ = [
    "Camera",
    "LanguageField",
    "Render",
    "Scene",
    "SceneError",
    "TrainConfig",
    "evaluate",
    "load_scene",
    "train",
]
__version__ = "0.1.0"

# Submodules a user reaches as attributes (`langfield.synthetic.make_room(...)`), imported on first use:
# open3d (synthetic) and the rest are not paid for by `import langfield`.
# The ablation, the benchmark and the geometric scores keep the short names they had before the
# subpackages (docs/layout.md).
_LAZY_SUBMODULES = {
    "ablate": "langfield.eval.ablate",
    "capture": "langfield.capture",
    "bench": "langfield.eval.bench",
    "geometry_eval": "langfield.eval.geometry",
    "query": "langfield.query",
    "synthetic": "langfield.synthetic",
}


def __getattr__(name: str):
    if name in _LAZY_SUBMODULES:
        import importlib

        return importlib.import_module(_LAZY_SUBMODULES[name])
    raise AttributeError(f"module 'langfield' has no attribute {name!r}")
