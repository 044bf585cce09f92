"""Virtual cameras: interpolation endpoints, rotations, bounds, determinism and the edge cases."""

from __future__ import annotations

import numpy as np
import pytest

from langfield.camera import Camera
from langfield.training.virtual_views import interpolate_camera, sample_virtual_cameras


@pytest.fixture
def cameras() -> list[Camera]:
    """Four cameras around the origin, looking at it, with different image sizes and intrinsics; one
    pair is nearly opposite (a rotation of almost 180 degrees between them)."""
    eyes = [(3.0, 0.0, 1.0), (0.0, 3.0, 0.5), (-2.5, 0.3, 1.5), (0.2, -3.0, 0.8)]
    return [
        Camera.look_at(
            eye, (0.0, 0.0, 0.0), width=40 + 8 * k, height=30 + 4 * k, fov_x_deg=50 + 5 * k, name=f"train_{k}"
        )
        for k, eye in enumerate(eyes)
    ]


def _angle(r0: np.ndarray, r1: np.ndarray) -> float:
    """The angle of the rotation taking r0 to r1, in radians."""
    return float(np.arccos(np.clip((np.trace(r0.T @ r1) - 1.0) / 2.0, -1.0, 1.0)))


def test_endpoints_are_the_training_cameras(cameras) -> None:
    a, b = cameras[0], cameras[2]
    at0, at1 = interpolate_camera(a, b, 0.0, name="v"), interpolate_camera(a, b, 1.0)
    np.testing.assert_allclose(at0.c2w, a.c2w, atol=1e-12)
    np.testing.assert_allclose(at1.c2w, b.c2w, atol=1e-12)
    assert at0.name == "v"
    for cam in (at0, at1):  # intrinsics and size are a's
        assert (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy) == (
            a.width,
            a.height,
            a.fx,
            a.fy,
            a.cx,
            a.cy,
        )


def test_the_midpoint_turns_half_way_along_the_shortest_arc(cameras) -> None:
    a, b = cameras[1], cameras[3]  # nearly opposite
    mid = interpolate_camera(a, b, 0.5)
    ra, rb, rm = a.c2w[:3, :3], b.c2w[:3, :3], mid.c2w[:3, :3]
    assert _angle(ra, rm) == pytest.approx(_angle(rm, rb), abs=1e-9)
    assert _angle(ra, rm) + _angle(rm, rb) == pytest.approx(_angle(ra, rb), abs=1e-9)
    np.testing.assert_allclose(mid.center, (a.center + b.center) / 2, atol=1e-12)


def test_without_jitter_cameras_lie_between_two_training_cameras(cameras) -> None:
    virtual = sample_virtual_cameras(cameras, 40, np.random.default_rng(0), jitter=0.0)
    for v in virtual:
        hits = []
        for a in cameras:
            for b in cameras:
                if a is b or (v.width, v.fx) != (a.width, a.fx):
                    continue
                ab, av = b.center - a.center, v.center - a.center
                t = float(ab @ av / (ab @ ab))
                on_segment = np.allclose(a.center + t * ab, v.center, atol=1e-9) and -1e-9 <= t <= 1 + 1e-9
                rv = v.c2w[:3, :3]
                between = (
                    abs(
                        _angle(a.c2w[:3, :3], rv)
                        + _angle(rv, b.c2w[:3, :3])
                        - _angle(a.c2w[:3, :3], b.c2w[:3, :3])
                    )
                    < 1e-7
                )
                hits.append(on_segment and between)
        assert any(hits), v.name


@pytest.mark.parametrize("jitter", [0.0, 0.1, 0.5])
def test_rotations_are_orthonormal_and_centres_stay_in_the_expanded_box(cameras, jitter) -> None:
    virtual = sample_virtual_cameras(cameras, 50, np.random.default_rng(1), jitter=jitter)
    assert [v.name for v in virtual] == [f"virtual_{i}" for i in range(50)]
    centres = np.stack([c.center for c in cameras])
    i, j = np.triu_indices(len(cameras), k=1)
    margin = jitter * np.linalg.norm(centres[i] - centres[j], axis=1).mean()
    lo, hi = centres.min(0) - margin - 1e-9, centres.max(0) + margin + 1e-9
    for v in virtual:
        r = v.c2w[:3, :3]
        np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
        assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-12)
        np.testing.assert_array_equal(v.c2w[3], [0.0, 0.0, 0.0, 1.0])
        assert (lo <= v.center).all() and (v.center <= hi).all()
    if jitter > 0:  # and the jitter does move them: the displacement has length margin
        plain = sample_virtual_cameras(cameras, 50, np.random.default_rng(1), jitter=0.0)
        moved = [np.linalg.norm(v.center - p.center) for v, p in zip(virtual, plain, strict=True)]
        np.testing.assert_allclose(moved, margin, rtol=1e-9)


def test_same_seed_same_cameras(cameras) -> None:
    first = sample_virtual_cameras(cameras, 10, np.random.default_rng(7), jitter=0.2)
    second = sample_virtual_cameras(cameras, 10, np.random.default_rng(7), jitter=0.2)
    other = sample_virtual_cameras(cameras, 10, np.random.default_rng(8), jitter=0.2)
    assert all(np.array_equal(a.c2w, b.c2w) and a.name == b.name for a, b in zip(first, second, strict=True))
    assert not all(np.array_equal(a.c2w, b.c2w) for a, b in zip(first, other, strict=True))


def test_zero_cameras_requested_and_no_training_cameras(cameras) -> None:
    assert sample_virtual_cameras(cameras, 0, np.random.default_rng(0)) == []
    with pytest.raises(ValueError, match="at least one training camera"):
        sample_virtual_cameras([], 3, np.random.default_rng(0))
    with pytest.raises(ValueError, match="n must be an integer >= 0"):
        sample_virtual_cameras(cameras, -1, np.random.default_rng(0))
    with pytest.raises(ValueError, match="jitter must be finite and >= 0"):
        sample_virtual_cameras(cameras, 1, np.random.default_rng(0), jitter=-0.1)


def test_one_camera_gives_jittered_copies_of_it(cameras) -> None:
    cam = cameras[0]
    virtual = sample_virtual_cameras([cam], 5, np.random.default_rng(3), jitter=0.1)
    scale = np.linalg.norm(cam.center)  # one camera: the jitter is relative to its distance from the origin
    for v in virtual:
        np.testing.assert_allclose(v.c2w[:3, :3], cam.c2w[:3, :3], atol=1e-12)
        assert np.linalg.norm(v.center - cam.center) == pytest.approx(0.1 * scale, rel=1e-9)
        assert (v.width, v.height, v.fx, v.cx) == (cam.width, cam.height, cam.fx, cam.cx)
    assert len({tuple(v.center) for v in virtual}) == 5
    still = sample_virtual_cameras([cam], 2, np.random.default_rng(3), jitter=0.0)
    assert all(np.allclose(v.c2w, cam.c2w, atol=1e-12) for v in still)
