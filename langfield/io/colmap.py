"""Reading COLMAP sparse models: cameras and image poses, binary or text.

Follows the layout documented at https://colmap.github.io/format.html (binary files are little
endian). Only what a scene needs is read: intrinsics and poses. The 2D keypoints in `images.*` are
skipped and `points3D.*` is not read. :func:`read_colmap` turns a model beside `images/` into a scene
layout.

Example:
    >>> found = find_model(Path("scene"))  # doctest: +SKIP
    >>> cameras, images = read_cameras(found[0]), read_images(found[1])  # doctest: +SKIP
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from langfield.camera import Camera
from langfield.constants import IMAGES_DIR
from langfield.io.layout import GL_TO_CV, Distortion, Frame, Layout, SceneError, depth_kind, unique_names

# model id -> (name, number of parameters), as COLMAP numbers them.
CAMERA_MODELS: dict[int, tuple[str, int]] = {
    0: ("SIMPLE_PINHOLE", 3),
    1: ("PINHOLE", 4),
    2: ("SIMPLE_RADIAL", 4),
    3: ("RADIAL", 5),
    4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8),
    6: ("FULL_OPENCV", 12),
    7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5),
    10: ("THIN_PRISM_FISHEYE", 12),
}
_PARAMS_BY_NAME = {name: n for name, n in CAMERA_MODELS.values()}
_MODEL_DIRS = ("sparse/0", "sparse")


class ColmapError(ValueError):
    """A COLMAP model file that cannot be read; the message names the file."""


@dataclass(frozen=True)
class ColmapCamera:
    """One entry of `cameras.bin|txt`.

    Attributes:
        id: CAMERA_ID.
        model: model name, e.g. "PINHOLE".
        width, height: image size in pixels.
        params: the model's parameters in COLMAP's order (e.g. fx fy cx cy for PINHOLE).
    """

    id: int
    model: str
    width: int
    height: int
    params: tuple[float, ...]


@dataclass(frozen=True)
class ColmapImage:
    """One entry of `images.bin|txt`: a world-to-camera pose in the OpenCV convention.

    Attributes:
        id: IMAGE_ID.
        qvec: [4] rotation quaternion (qw, qx, qy, qz).
        tvec: [3] translation.
        camera_id: the CAMERA_ID of its intrinsics.
        name: image file name relative to the images folder.
    """

    id: int
    qvec: tuple[float, float, float, float]
    tvec: tuple[float, float, float]
    camera_id: int
    name: str

    def world_to_camera(self) -> np.ndarray:
        """[4, 4] world-to-camera matrix, OpenCV convention (x right, y down, z forward)."""
        w2c = np.eye(4)
        w2c[:3, :3] = qvec_to_rotmat(self.qvec)
        w2c[:3, 3] = self.tvec
        return w2c


def qvec_to_rotmat(qvec: tuple[float, float, float, float] | np.ndarray) -> np.ndarray:
    """[3, 3] rotation of a quaternion (qw, qx, qy, qz); it need not be normalised."""
    q = np.asarray(qvec, dtype=np.float64)
    norm = np.linalg.norm(q)
    if not np.isfinite(norm) or norm < 1e-12:
        raise ValueError(f"quaternion {tuple(q)} cannot be normalised")
    w, x, y, z = q / norm
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def find_model(root: Path) -> tuple[Path, Path] | None:
    """The (cameras, images) files of the COLMAP model under `root`, or None if there is none.

    Looks in `sparse/0/` then `sparse/`, preferring `.bin` over `.txt` for each file.

    Raises:
        ColmapError: a folder holds one of the two files but not the other.
    """
    for sub in _MODEL_DIRS:
        folder = Path(root) / sub
        cameras, images = _either(folder, "cameras"), _either(folder, "images")
        if cameras and images:
            return cameras, images
        if cameras or images:
            missing = "images" if cameras else "cameras"
            raise ColmapError(
                f"{cameras or images}: COLMAP model has no {missing}.bin or {missing}.txt beside it"
            )
    return None


def read_cameras(path: Path) -> dict[int, ColmapCamera]:
    """Cameras of a `cameras.bin` or `cameras.txt` file, by CAMERA_ID."""
    path = Path(path)
    cameras = _read_cameras_bin(path) if _is_binary(path) else _read_cameras_txt(path)
    return {cam.id: cam for cam in cameras}


def read_images(path: Path) -> dict[int, ColmapImage]:
    """Image poses of an `images.bin` or `images.txt` file, by IMAGE_ID."""
    path = Path(path)
    images = _read_images_bin(path) if _is_binary(path) else _read_images_txt(path)
    return {image.id: image for image in images}


def _either(folder: Path, stem: str) -> Path | None:
    for suffix in (".bin", ".txt"):
        if (folder / f"{stem}{suffix}").is_file():
            return folder / f"{stem}{suffix}"
    return None


def _is_binary(path: Path) -> bool:
    if path.suffix not in (".bin", ".txt"):
        raise ColmapError(f"{path}: expected a .bin or .txt COLMAP file")
    if not path.is_file():
        raise ColmapError(f"{path}: file not found")
    return path.suffix == ".bin"


class _Reader:
    """Little-endian reads from a binary file that fail with the file's name when it runs short."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.data = path.read_bytes()
        self.pos = 0

    def take(self, fmt: str) -> tuple:
        size = struct.calcsize("<" + fmt)
        self._need(size)
        values = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += size
        return values

    def skip(self, size: int) -> None:
        self._need(size)
        self.pos += size

    def cstring(self) -> str:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            raise ColmapError(f"{self.path}: truncated (unterminated image name at byte {self.pos})")
        text = self.data[self.pos : end].decode("utf-8", errors="replace")
        self.pos = end + 1
        return text

    def _need(self, size: int) -> None:
        if self.pos + size > len(self.data):
            raise ColmapError(f"{self.path}: truncated (needs {size} more bytes at byte {self.pos})")


def _read_cameras_bin(path: Path) -> list[ColmapCamera]:
    reader = _Reader(path)
    (count,) = reader.take("Q")
    cameras = []
    for _ in range(count):
        cam_id, model_id, width, height = reader.take("iiQQ")
        if model_id not in CAMERA_MODELS:
            # The parameter count depends on the model, so nothing after this can be read.
            raise ColmapError(f"{path}: camera {cam_id} has unknown camera model id {model_id}")
        name, n_params = CAMERA_MODELS[model_id]
        cameras.append(ColmapCamera(cam_id, name, width, height, reader.take(f"{n_params}d")))
    return cameras


def _read_images_bin(path: Path) -> list[ColmapImage]:
    reader = _Reader(path)
    (count,) = reader.take("Q")
    images = []
    for _ in range(count):
        (image_id,) = reader.take("i")
        qvec, tvec = reader.take("4d"), reader.take("3d")
        (camera_id,) = reader.take("i")
        name = reader.cstring()
        (n_points,) = reader.take("Q")
        reader.skip(24 * n_points)  # x, y (double) and point3D_id (int64) per keypoint
        images.append(ColmapImage(image_id, qvec, tvec, camera_id, name))
    return images


def _data_lines(path: Path) -> list[tuple[int, str]]:
    """(line number, text) of every line that is not a comment; blank lines are kept."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise ColmapError(f"{path}: cannot read: {e}") from e
    return [(i + 1, line) for i, line in enumerate(text.splitlines()) if not line.lstrip().startswith("#")]


def _read_cameras_txt(path: Path) -> list[ColmapCamera]:
    cameras = []
    for lineno, line in _data_lines(path):
        fields = line.split()
        if not fields:
            continue
        where = f"{path}: line {lineno}"
        if len(fields) < 4:
            raise ColmapError(f"{where}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]")
        model = fields[1]
        if model not in _PARAMS_BY_NAME:
            raise ColmapError(f"{where}: unknown camera model {model!r}")
        params = _numbers(fields[4:], float, where)
        if len(params) != _PARAMS_BY_NAME[model]:
            raise ColmapError(
                f"{where}: {model} takes {_PARAMS_BY_NAME[model]} parameters, got {len(params)}"
            )
        cam_id, width, height = _numbers([fields[0], fields[2], fields[3]], int, where)
        cameras.append(ColmapCamera(cam_id, model, width, height, tuple(params)))
    return cameras


def _read_images_txt(path: Path) -> list[ColmapImage]:
    lines = _data_lines(path)
    images = []
    i = 0
    while i < len(lines):
        lineno, line = lines[i]
        if not line.strip():
            i += 1
            continue
        fields = line.split(maxsplit=9)
        where = f"{path}: line {lineno}"
        if len(fields) != 10:
            raise ColmapError(f"{where}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME")
        values = _numbers(fields[1:8], float, where)
        image_id, camera_id = _numbers([fields[0], fields[8]], int, where)
        images.append(
            ColmapImage(image_id, tuple(values[:4]), tuple(values[4:]), camera_id, fields[9].strip())
        )
        i += 2  # the next line lists the image's 2D points (possibly none), which are not needed
    return images


def _numbers(fields: list[str], kind: type, where: str) -> list:
    try:
        return [kind(f) for f in fields]
    except ValueError as e:
        raise ColmapError(f"{where}: {e}") from e


_COLMAP_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")


def read_colmap(root: Path, cameras_path: Path, images_path: Path) -> Layout:
    try:
        cameras = read_cameras(cameras_path)
        images = read_images(images_path)
    except ColmapError as e:
        raise SceneError(str(e)) from e
    if not images:
        raise SceneError(f"{images_path}: COLMAP model has no images")
    frames = [
        _colmap_frame(root, cameras_path, images_path, cameras, image)
        for image in sorted(images.values(), key=lambda im: im.name)
    ]
    return Layout(
        root, images_path, unique_names(root, images_path, frames), depth_kind(root, images_path, {})
    )


def _colmap_frame(
    root: Path,
    cameras_path: Path,
    images_path: Path,
    cameras: dict[int, ColmapCamera],
    image: ColmapImage,
) -> Frame:
    where = f"{images_path}: image {image.name!r}"
    if image.camera_id not in cameras:
        raise SceneError(f"{where} uses camera {image.camera_id}, which {cameras_path} does not define")
    fx, fy, cx, cy, distortion = _colmap_intrinsics(cameras_path, cameras[image.camera_id])
    image_path = root / IMAGES_DIR / image.name
    if not image_path.is_file():
        raise SceneError(f"{image_path}: image file not found (listed in {images_path})")
    try:
        # COLMAP stores world-to-camera in the OpenCV convention; Camera wants camera-to-world, OpenGL.
        c2w = np.linalg.inv(image.world_to_camera()) @ GL_TO_CV
        camera = Camera(
            image_path.stem,
            cameras[image.camera_id].width,
            cameras[image.camera_id].height,
            fx,
            fy,
            cx,
            cy,
            c2w,
        )
    except (ValueError, np.linalg.LinAlgError) as e:
        raise SceneError(f"{where}: {e}") from e
    return Frame(image_path.stem, camera, image_path, distortion)


def _colmap_intrinsics(path: Path, cam: ColmapCamera) -> tuple[float, float, float, float, Distortion | None]:
    """(fx, fy, cx, cy, distortion) of a COLMAP camera; radial models map onto OpenCV k1 k2 p1 p2."""
    p = cam.params
    match cam.model:
        case "SIMPLE_PINHOLE":
            fx, fy, cx, cy, dist = p[0], p[0], p[1], p[2], (0.0, 0.0, 0.0, 0.0)
        case "PINHOLE":
            fx, fy, cx, cy, dist = *p, (0.0, 0.0, 0.0, 0.0)
        case "SIMPLE_RADIAL":
            fx, fy, cx, cy, dist = p[0], p[0], p[1], p[2], (p[3], 0.0, 0.0, 0.0)
        case "RADIAL":
            fx, fy, cx, cy, dist = p[0], p[0], p[1], p[2], (p[3], p[4], 0.0, 0.0)
        case "OPENCV":
            fx, fy, cx, cy, dist = *p[:4], tuple(p[4:])
        case _:
            raise SceneError(
                f"{path}: camera {cam.id} uses camera model {cam.model}, which is not supported "
                f"(supported: {', '.join(_COLMAP_MODELS)})"
            )
    return fx, fy, cx, cy, dist if any(dist) else None
