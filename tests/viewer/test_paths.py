"""Camera paths (langfield/viewer/paths.py): where they go, what they look at, degenerate inputs."""

from __future__ import annotations

import numpy as np
import pytest

from langfield import Camera
from langfield.viewer.paths import interpolate, look_target, orbit

TARGET = np.array([0.5, -0.2, 0.3])


def _ring(azimuths_deg, radius=3.0, height=1.0, target=TARGET) -> list[Camera]:
    """Cameras on a circle about +z through ``target``, each looking at it."""
    cams = []
    for i, a in enumerate(np.deg2rad(azimuths_deg)):
        eye = target + np.array([radius * np.cos(a), radius * np.sin(a), height])
        cams.append(Camera.look_at(eye, target, width=40, height=30, name=f"c{i}"))
    return cams


def _looks_at(cam: Camera, point: np.ndarray) -> float:
    to = point - cam.center
    return float(cam.forward @ (to / np.linalg.norm(to)))


def _azimuth(cam: Camera) -> float:
    d = cam.center - TARGET
    return float(np.rad2deg(np.arctan2(d[1], d[0])))


def test_look_target_finds_the_common_point_and_falls_back_for_parallel_axes() -> None:
    assert np.allclose(look_target(_ring([0, 100, 200])), TARGET, atol=1e-9)
    parallel = [Camera.look_at((x, -3.0, 0.0), (x, 0.0, 0.0), name=str(x)) for x in (-0.2, 0.0, 0.2)]
    assert np.allclose(look_target(parallel, fallback=np.array([0.0, 5.0, 0.0])), [0.0, 5.0, 0.0])
    ahead = look_target(parallel)  # no fallback: ahead of the cameras, along their axes
    assert ahead[1] > -3.0 and abs(ahead[0]) < 1e-9


def test_orbit_of_surrounding_cameras_is_a_full_level_turn_facing_the_target() -> None:
    cams = _ring([10, 130, 250])
    path = orbit(cams, 36)
    assert len(path) == 36 and len({c.name for c in path}) == 36
    for cam in path:
        assert _looks_at(cam, TARGET) == pytest.approx(1.0, abs=1e-9)
        offset = cam.center - TARGET
        assert np.hypot(offset[0], offset[1]) == pytest.approx(3.0, abs=1e-9)
        assert offset[2] == pytest.approx(1.0, abs=1e-9)
        assert (cam.width, cam.height, cam.fx, cam.cx) == (40, 30, cams[0].fx, cams[0].cx)
    steps = np.diff(np.unwrap(np.deg2rad([_azimuth(c) for c in path])))
    assert np.allclose(steps, 2 * np.pi / 36)  # one turn, even steps, starting at the first camera
    assert _azimuth(path[0]) == pytest.approx(10.0)


def test_orbit_of_forward_facing_cameras_swings_over_their_arc_only() -> None:
    # A 20 degree arc, widened by half (at least 5 degrees each way). Axes this close count as parallel,
    # so the target is the fallback (as the field's bounds centre is for LLFF). The path turns about the
    # cameras' mean up, which leans a little from +z when they all look down from one side.
    cams = _ring([80, 90, 100])
    azimuths = [_azimuth(c) for c in orbit(cams, 40, fallback=TARGET)]
    assert max(azimuths) == pytest.approx(90 + 15, abs=1.2)
    assert min(azimuths) == pytest.approx(90 - 15, abs=1.2)
    narrow = _ring([89, 91])
    assert max(_azimuth(c) for c in orbit(narrow, 40, fallback=TARGET)) == pytest.approx(90 + 5, abs=0.6)
    wide = _ring([40, 90, 140])  # 100 degrees: widened by half
    assert max(_azimuth(c) for c in orbit(wide, 40)) == pytest.approx(90 + 75, abs=2.5)


def test_interpolate_passes_through_every_camera_in_azimuth_order() -> None:
    cams = _ring([200, 10, 100, 150])  # out of order on purpose
    path = interpolate(cams, 61)
    ordered = sorted(cams, key=lambda c: _azimuth(c) % 360)  # the arc runs 10 -> 200, its gap 200 -> 10
    assert np.allclose(path[0].c2w, ordered[0].c2w) and np.allclose(path[-1].c2w, ordered[-1].c2w, atol=1e-9)
    for cam in cams:
        nearest = min(path, key=lambda p: np.linalg.norm(p.center - cam.center))
        assert np.linalg.norm(nearest.center - cam.center) < 0.2
        assert _looks_at(nearest, TARGET) > 0.99
    for cam in path:
        rot = cam.c2w[:3, :3]
        assert np.allclose(rot.T @ rot, np.eye(3), atol=1e-9) and np.linalg.det(rot) == pytest.approx(1.0)
    steps = np.linalg.norm(np.diff([c.center for c in path], axis=0), axis=1)
    assert steps.max() < 2.0 * steps.mean()  # spaced by distance, not by camera


def test_degenerate_paths() -> None:
    one = _ring([0])
    assert all(np.allclose(c.c2w, one[0].c2w) for c in interpolate(one, 5))
    assert len(orbit(one, 5)) == 5
    twins = _ring([0, 0, 90])  # two cameras at the same place
    path = interpolate(twins, 20)
    assert all(np.isfinite(c.c2w).all() for c in path)
    with pytest.raises(ValueError, match="at least 2 frames"):
        orbit(twins, 1)
    with pytest.raises(ValueError, match="at least one camera"):
        interpolate([], 10)
