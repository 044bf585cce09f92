"""langfield: open-vocabulary 3D language fields from three posed photos (SOVGaussian) on the CPU."""

from langfield.camera import Camera

__all__ = ["Camera"]
__version__ = "0.1.0"
