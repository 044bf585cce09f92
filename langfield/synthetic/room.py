"""The built-in room's geometry: its furniture as labelled primitives (a fixed arrangement, or one
drawn per layout number) and the cameras around it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from langfield.camera import Camera

_FOV_X_DEG = 60.0

# Independent random streams, so adding draws to one never changes another.
STREAM_LAYOUT, STREAM_PRIOR, STREAM_FEATURES, STREAM_TEXT, _STREAM_ARRANGE = 1, 2, 3, 4, 5


@dataclass(frozen=True)
class Primitive:
    """One mesh of the room with its labels and its look."""

    mesh: o3d.geometry.TriangleMesh
    labels: tuple[str, str, str]  # (subpart, part, whole)
    color: tuple[float, float, float]  # base RGB in [0, 1]
    texture: str  # a kind known to _texture


# ----------------------------------------------------------------------------------------- geometry


def _box(
    size: tuple[float, float, float], center: tuple[float, float, float], yaw_deg: float = 0.0
) -> o3d.geometry.TriangleMesh:
    """A box of `size` (x, y, z) centred at `center`, turned by `yaw_deg` about z."""
    mesh = o3d.geometry.TriangleMesh.create_box(*size)
    mesh.translate(-0.5 * np.asarray(size))
    if yaw_deg:
        mesh.rotate(mesh.get_rotation_matrix_from_xyz((0.0, 0.0, np.deg2rad(yaw_deg))), center=(0, 0, 0))
    return mesh.translate(center)


def _cylinder(radius: float, height: float, center: tuple[float, float, float]) -> o3d.geometry.TriangleMesh:
    """An upright closed cylinder centred at `center`."""
    return o3d.geometry.TriangleMesh.create_cylinder(radius, height, resolution=24).translate(center)


# The furniture groups: each one's home (the floor point it stands on in the built-in room, layout 0) and
# its floor footprint there (x, y lows and highs), which a layout moves, scales about the home and keeps
# from overlapping. "wall": stands against the back wall (y = 2) in every layout.
_GROUPS = {
    "sofa": {"home": (-0.3, 1.5), "footprint": ((-1.25, 1.1), (0.65, 1.9)), "wall": True},
    "table": {"home": (-0.3, 0.4), "footprint": ((-0.8, 0.125), (0.2, 0.675)), "wall": False},
    "lamp": {"home": (1.2, 1.6), "footprint": ((1.05, 1.45), (1.35, 1.75)), "wall": False},
    "chair": {"home": (1.1, 0.35), "footprint": ((0.875, 0.125), (1.325, 0.575)), "wall": False},
    "shelf": {"home": (-1.65, 1.8), "footprint": ((-1.95, 1.65), (-1.35, 1.95)), "wall": True},
}
# Where a layout may put furniture: the floor the training cameras see, inside the walls.
_FLOOR_LO, _FLOOR_HI = (-1.95, 0.0), (1.95, 1.97)
_LAYOUT_SIZES = (0.8, 1.25)  # each group's size factor in a random layout
_LAYOUT_TRIES = 200  # placements tried per group before it is left out


@dataclass(frozen=True)
class _Placement:
    """A furniture group scaled by ``size`` about its home and moved by (dx, dy) from it."""

    kind: str
    size: float = 1.0
    dx: float = 0.0
    dy: float = 0.0

    def footprint(self) -> tuple[np.ndarray, np.ndarray]:
        home = np.asarray(_GROUPS[self.kind]["home"])
        lo, hi = (np.asarray(v) for v in _GROUPS[self.kind]["footprint"])
        move = home + (self.dx, self.dy)
        return move + self.size * (lo - home), move + self.size * (hi - home)


def room_layout(layout: int) -> list[_Placement]:
    """The furniture of layout ``layout``: 0 is the built-in room (every group at home); any other
    number draws which groups stand in the room (at least three placed; a second chair sometimes),
    their sizes and their places on the floor, from its own random stream. Footprints are drawn 5 cm
    apart; make_room then shifts each group by up to 5 cm with the scene's seed, so two groups may
    touch and a group against the back wall may reach 2 cm into it."""
    if layout == 0:
        return [_Placement(kind) for kind in _GROUPS]
    rng = np.random.default_rng([layout, _STREAM_ARRANGE])
    placed: list[_Placement] = []
    while len(placed) < 3:  # a draw that fits fewer (a large sofa can leave no room for the shelf) is redrawn
        placed = _draw_layout(rng)
    return placed


def _draw_layout(rng: np.random.Generator) -> list[_Placement]:
    kinds = [k for k in _GROUPS if rng.random() < 0.75]
    while len(kinds) < 3:
        kinds = sorted({*kinds, str(rng.choice(list(_GROUPS)))}, key=list(_GROUPS).index)
    if "chair" in kinds and rng.random() < 0.4:
        kinds.append("chair")
    placed: list[_Placement] = []
    for kind in kinds:
        for _ in range(_LAYOUT_TRIES):
            size = float(rng.uniform(*_LAYOUT_SIZES))
            lo, hi = _Placement(kind, size).footprint()
            dx = float(rng.uniform(_FLOOR_LO[0] - lo[0], _FLOOR_HI[0] - hi[0]))
            if _GROUPS[kind]["wall"]:  # its back to the back wall, a few centimetres off
                dy = float(_FLOOR_HI[1] - hi[1] - rng.uniform(0.0, 0.05))
            else:
                dy = float(rng.uniform(_FLOOR_LO[1] - lo[1], _FLOOR_HI[1] - hi[1]))
            candidate = _Placement(kind, size, dx, dy)
            if all(not _overlap(candidate, other) for other in placed):
                placed.append(candidate)
                break
    return placed


def _overlap(a: _Placement, b: _Placement, gap: float = 0.05) -> bool:
    (alo, ahi), (blo, bhi) = a.footprint(), b.footprint()
    return bool(np.all(alo < bhi + gap) and np.all(blo < ahi + gap))


Color = tuple[float, float, float]


def room_primitives(rng: np.random.Generator, scale: float, layout: int = 0) -> list[Primitive]:
    """Every primitive of the room (furniture of :func:`room_layout`), in world coordinates x `scale`.

    Each furniture group is shifted by a few centimetres and each colour jittered by a few percent,
    both from `rng`, so that seeds give different (but equally valid) rooms.
    """
    prims: list[Primitive] = []

    def adder(shift: tuple[float, float], place: _Placement | None = None):
        def add(
            mesh: o3d.geometry.TriangleMesh, subpart: str, part: str, whole: str, color: Color, texture: str
        ) -> None:
            dx = dy = 0.0
            if place is not None:
                if place.size != 1.0:
                    home = _GROUPS[place.kind]["home"]
                    mesh.scale(place.size, center=(home[0], home[1], 0.0))
                dx, dy = place.dx, place.dy
            mesh.translate((shift[0] + dx, shift[1] + dy, 0.0))
            jitter = np.clip(np.asarray(color) * (1 + rng.uniform(-0.06, 0.06, 3)), 0, 1)
            mesh.scale(scale, center=(0, 0, 0))
            prims.append(Primitive(mesh, (subpart, part, whole), tuple(float(c) for c in jitter), texture))

        return add

    def shift() -> tuple[float, float]:
        return tuple(rng.uniform(-0.05, 0.05, 2))

    # Room shell: the floor's top face is z = 0; the front (camera) and right sides are open.
    fixed = adder((0.0, 0.0))
    fixed(_box((4.0, 4.0, 0.05), (0.0, 0.0, -0.025)), "floor", "floor", "floor", (0.74, 0.6, 0.44), "checker")
    fixed(_box((4.0, 0.05, 2.5), (0.0, 2.025, 1.25)), "wall", "wall", "wall", (0.86, 0.84, 0.78), "plaster")
    fixed(
        _box((0.05, 4.05, 2.5), (-2.025, 0.025, 1.25)), "wall", "wall", "wall", (0.8, 0.83, 0.86), "plaster"
    )
    adder(shift())(
        _box((2.0, 1.4, 0.01), (-0.3, 0.4, 0.005)), "rug", "rug", "rug", (0.6, 0.26, 0.22), "stripes"
    )
    for place in room_layout(layout):
        _BUILDERS[place.kind](adder(shift(), place))
    return prims


def _sofa(add) -> None:
    """Against the back wall, facing -y."""
    fabric = (0.26, 0.36, 0.58)
    add(_box((1.6, 0.8, 0.35), (-0.3, 1.5, 0.175)), "sofa base", "sofa seat", "sofa", fabric, "fabric")
    for x in (-0.7, 0.1):
        add(
            _box((0.78, 0.6, 0.12), (x, 1.4, 0.41)),
            "sofa cushion",
            "sofa seat",
            "sofa",
            (0.36, 0.48, 0.72),
            "fabric",
        )
    add(_box((1.6, 0.2, 0.5), (-0.3, 1.8, 0.6)), "sofa back", "sofa back", "sofa", (0.3, 0.4, 0.62), "fabric")
    for x in (-1.175, 0.575):
        add(
            _box((0.15, 0.8, 0.6), (x, 1.5, 0.3)),
            "sofa armrest",
            "sofa armrests",
            "sofa",
            (0.22, 0.32, 0.52),
            "fabric",
        )


def _table(add) -> None:
    """A coffee table with a mug and a book on it."""
    add(
        _box((1.0, 0.55, 0.04), (-0.3, 0.4, 0.44)),
        "table top",
        "table top",
        "table",
        (0.56, 0.36, 0.2),
        "wood",
    )
    for dx in (-0.45, 0.45):
        for dy in (-0.22, 0.22):
            leg = _cylinder(0.025, 0.42, (-0.3 + dx, 0.4 + dy, 0.21))
            add(leg, "table leg", "table legs", "table", (0.3, 0.2, 0.12), "plain")
    red = (0.82, 0.16, 0.14)
    add(_cylinder(0.045, 0.1, (-0.05, 0.35, 0.51)), "mug body", "mug", "mug", red, "plain")
    add(_box((0.03, 0.015, 0.06), (0.01, 0.35, 0.51)), "mug handle", "mug", "mug", red, "plain")
    add(
        _box((0.22, 0.16, 0.04), (-0.58, 0.45, 0.48), yaw_deg=15),
        "book",
        "book",
        "book",
        (0.16, 0.46, 0.26),
        "plain",
    )


def _lamp(add) -> None:
    """A floor lamp."""
    metal = (0.22, 0.22, 0.24)
    add(_cylinder(0.15, 0.04, (1.2, 1.6, 0.02)), "lamp base", "lamp stand", "lamp", metal, "plain")
    add(_cylinder(0.02, 1.3, (1.2, 1.6, 0.69)), "lamp pole", "lamp stand", "lamp", metal, "plain")
    add(
        _cylinder(0.2, 0.28, (1.2, 1.6, 1.45)),
        "lamp shade",
        "lamp shade",
        "lamp",
        (0.96, 0.88, 0.64),
        "fabric",
    )


def _chair(add) -> None:
    """A chair facing -x."""
    wood = (0.66, 0.46, 0.26)
    add(_box((0.45, 0.45, 0.05), (1.1, 0.35, 0.45)), "chair seat", "chair seat", "chair", wood, "wood")
    add(_box((0.05, 0.45, 0.45), (1.3, 0.35, 0.7)), "chair back", "chair back", "chair", wood, "wood")
    for dx in (-0.19, 0.19):
        for dy in (-0.19, 0.19):
            leg = _cylinder(0.02, 0.425, (1.1 + dx, 0.35 + dy, 0.2125))
            add(leg, "chair leg", "chair legs", "chair", (0.4, 0.27, 0.15), "plain")


def _shelf(add) -> None:
    """An open shelf: two sides and four boards."""
    shelf = (0.52, 0.34, 0.2)
    for x in (-1.935, -1.365):
        add(_box((0.03, 0.3, 1.4), (x, 1.8, 0.7)), "shelf side", "shelf frame", "shelf", shelf, "wood")
    for z in (0.06, 0.5, 0.94, 1.39):
        add(_box((0.54, 0.3, 0.025), (-1.65, 1.8, z)), "shelf board", "shelf boards", "shelf", shelf, "wood")


_BUILDERS = {"sofa": _sofa, "table": _table, "lamp": _lamp, "chair": _chair, "shelf": _shelf}


def room_cameras(width: int, height: int, n_train: int, n_test: int, scale: float) -> list[Camera]:
    """Training views on a 70 degree arc at 1.5 m, test views between and slightly off the arc.

    Test views sit at 0.88 or 0.94 of the arc's radius and 0.12 m above or below it, so none coincides
    with a training view even where their angles agree.
    """
    target = np.array([0.0, 0.8, 0.55])
    radius, eye_z, span = 2.7, 1.5, 70.0

    def camera(angle_deg: float, r: float, z: float, name: str) -> Camera:
        a = np.deg2rad(angle_deg)
        eye = np.array([target[0] + r * np.sin(a), target[1] - r * np.cos(a), z])
        return Camera.look_at(
            eye * scale, target * scale, width=width, height=height, fov_x_deg=_FOV_X_DEG, name=name
        )

    train_angles = np.linspace(-span / 2, span / 2, n_train) if n_train > 1 else np.zeros(1)
    cams = [camera(a, radius, eye_z, f"train_{i:03d}") for i, a in enumerate(train_angles)]
    for i in range(n_test):
        angle = -span / 2 + span * (i + 0.5) / n_test
        r = radius * (0.88 if i % 2 == 0 else 0.94)
        z = eye_z + (0.12 if i % 2 == 0 else -0.12)
        cams.append(camera(angle, r, z, f"test_{i:03d}"))
    return cams
