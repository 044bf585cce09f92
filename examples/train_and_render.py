"""Train on the built-in synthetic scene's 3 views and render a pose that no photo was taken from.

python examples/train_and_render.py [OUT_DIR]
"""

import sys
from pathlib import Path

import cv2
import numpy as np
import torch

import langfield
from langfield.synthetic import make_room

out = Path(sys.argv[1] if len(sys.argv) > 1 else "example_out")
scene = langfield.load_scene(make_room(out / "scene", width=160, height=120))
field = langfield.train(scene, langfield.TrainConfig(iterations=1000, seed=0))
field.save(out / "field")

camera = langfield.Camera.look_at(eye=(0.8, -1.8, 1.3), target=(0.0, 0.8, 0.5), width=160, height=120)
with torch.no_grad():
    render = field.render(camera)
rgb = (render.rgb.clamp(0, 1).numpy()[..., ::-1] * 255).astype(np.uint8)
cv2.imwrite(str(out / "free_view.png"), rgb)
print(f"{field.num_gaussians} Gaussians; free view written to {out / 'free_view.png'}")
