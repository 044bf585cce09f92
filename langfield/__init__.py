"""langfield: open-vocabulary 3D language fields from three posed photos (SOVGaussian) on the CPU.

>>> import langfield
>>> scene = langfield.load_scene("scene/")                        # doctest: +SKIP
>>> field = langfield.train(scene, langfield.TrainConfig(iterations=2000))   # doctest: +SKIP
"""

from langfield.camera import Camera
from langfield.evaluate import evaluate
from langfield.field import LanguageField, Render
from langfield.scene import Scene, SceneError, load_scene
from langfield.trainer import TrainConfig, train

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
