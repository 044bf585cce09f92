"""langfield: open-vocabulary 3D language fields from three posed photos (SOVGaussian) on the CPU.

>>> import langfield
>>> scene = langfield.load_scene("scene/")                        # doctest: +SKIP
>>> field = langfield.train(scene, langfield.TrainConfig(iterations=2000))   # doctest: +SKIP
"""

import os as _os

# The fast backend's numba kernels and PyTorch's OpenMP threads share the machine's cores. GNU libgomp's
# default spin after each parallel region (300,000 rounds) kept torch's idle threads on the cores that
# numba's workers wanted; no spin at all (OMP_WAIT_POLICY=PASSIVE) puts them to sleep and wakes them
# through the kernel for each of a step's hundreds of small ops, which cost more than the ops. A short
# spin keeps them awake between one op and the next and asleep through a kernel (docs/decisions.md);
# libgomp spins as GOMP_SPINCOUNT says under the ACTIVE policy only where it is the policy named (left
# unnamed, the built-in scene trained no faster). It only takes effect if torch is not imported yet; a
# user's own setting of either variable wins.
if "OMP_WAIT_POLICY" not in _os.environ and "GOMP_SPINCOUNT" not in _os.environ:
    _os.environ["OMP_WAIT_POLICY"] = "ACTIVE"
    _os.environ["GOMP_SPINCOUNT"] = "3000"

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
