"""Tests of the synthetic specimens: their ground truth is checked against independent computations."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage
from scipy.spatial import cKDTree

from napari_unwind import datasets as ds
from napari_unwind.errors import InvalidInputError
from napari_unwind.io import Volume


# ------------------------------------------------------------------------------------------------------------------
# fixtures (module scope: each phantom is built once)
# ------------------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def fish():
    return ds.fish_phantom()


@pytest.fixture(scope="module")
def clean_fish():
    return ds.fish_phantom(noise=0.0)


@pytest.fixture(scope="module")
def cylinder():
    return ds.cylinder_phantom()


@pytest.fixture(scope="module")
def helix():
    return ds.fish_phantom(curve="helix", twist=3.0, noise=0.0)


@pytest.fixture(scope="module")
def cbend():
    return ds.fish_phantom(curve="c-bend", twist=-2.0, roll=1.0, noise=0.0, tube=False)


@pytest.fixture(scope="module")
def aniso():
    return ds.fish_phantom(spacing=(1.5, 1.0, 0.8), length=120.0, noise=0.0)


@pytest.fixture(scope="module")
def tank():
    return ds.tank_phantom(noise=0.0)


@pytest.fixture(scope="module")
def phantoms(fish, cylinder, helix, cbend, aniso, tank):
    return {"fish": fish, "cylinder": cylinder, "helix": helix, "cbend": cbend, "aniso": aniso, "tank0": tank.fish[0]}


ALL = ["fish", "cylinder", "helix", "cbend", "aniso", "tank0"]


# ------------------------------------------------------------------------------------------------------------------
# independent helpers
# ------------------------------------------------------------------------------------------------------------------
def straighten(p: ds.Phantom, bent: np.ndarray) -> np.ndarray:
    """Resample ``bent`` on the straight grid at c(s) + x u + y v, from the returned centreline and frames only.

    The centreline and frames are interpolated linearly along s (not with the module's own helper) and the
    frame is re-orthonormalised; ``scipy.ndimage.map_coordinates(order=1)`` does the sampling.
    """
    ns, ny, nx = p.straight_shape
    d = p.straight_spacing
    s = np.arange(ns) * d
    y = (np.arange(ny) - (ny - 1) / 2) * d
    x = (np.arange(nx) - (nx - 1) / 2) * d
    c = np.column_stack([np.interp(s, p.arclength, p.centerline_physical[:, a]) for a in range(3)])
    u = np.column_stack([np.interp(s, p.arclength, p.frames[:, 0, a]) for a in range(3)])
    n = np.column_stack([np.interp(s, p.arclength, p.frames[:, 2, a]) for a in range(3)])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    u -= np.sum(u * n, axis=1, keepdims=True) * n
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(n, u)
    pts = (
        c[:, None, None, :]
        + x[None, None, :, None] * u[:, None, None, :]
        + y[None, :, None, None] * v[:, None, None, :]
    )
    idx = pts / np.asarray(p.spacing)
    return ndimage.map_coordinates(bent.astype(np.float32), np.moveaxis(idx, -1, 0), order=1, cval=0.0)


def dice(a: np.ndarray, b: np.ndarray) -> float:
    return 2.0 * np.count_nonzero(a & b) / (np.count_nonzero(a) + np.count_nonzero(b))


def transported_twist(p: ds.Phantom) -> np.ndarray:
    """Twist of the returned frames relative to a discrete parallel transport built from their own n."""
    frames = p.frames
    u, v = frames[0, 0].copy(), frames[0, 1].copy()
    out = [0.0]
    for k in range(len(frames) - 1):
        a, b = frames[k, 2], frames[k + 1, 2]
        axis = np.cross(a, b)
        sn = np.linalg.norm(axis)
        if sn > 1e-15:  # minimal rotation taking n_k to n_k+1 (Rodrigues)
            axis /= sn
            ang = np.arctan2(sn, a @ b)

            def rot(w, axis=axis, ang=ang):
                return w * np.cos(ang) + np.cross(axis, w) * np.sin(ang) + axis * (axis @ w) * (1 - np.cos(ang))

            u, v = rot(u), rot(v)
        vr = frames[k + 1, 1]
        out.append(np.arctan2(-(vr @ u), vr @ v))
    return np.unwrap(np.array(out))


# ------------------------------------------------------------------------------------------------------------------
# geometry of the ground truth
# ------------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ALL)
def test_frames_orthonormal_right_handed_and_tangent(phantoms, name):
    p = phantoms[name]
    F = p.frames
    assert F.shape == (len(p.arclength), 3, 3)
    np.testing.assert_allclose(F @ np.swapaxes(F, 1, 2), np.broadcast_to(np.eye(3), F.shape), atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(F), 1.0, atol=1e-9)
    np.testing.assert_allclose(np.cross(F[:, 0], F[:, 1]), F[:, 2], atol=1e-9)
    tangent = np.gradient(p.centerline_physical, p.arclength, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    assert np.min(np.sum(tangent * F[:, 2], axis=1)) > 0.9999


@pytest.mark.parametrize("name", ALL)
def test_arclength_matches_polyline(phantoms, name):
    p = phantoms[name]
    seg = np.linalg.norm(np.diff(p.centerline_physical, axis=0), axis=1)
    assert p.arclength[0] == 0.0
    assert p.arclength[-1] == pytest.approx(p.length, rel=1e-12)
    np.testing.assert_allclose(np.diff(p.arclength), seg, rtol=1e-4)
    assert seg.sum() == pytest.approx(p.length, rel=1e-5)
    assert np.max(seg) <= 0.5 * min(p.spacing) + 1e-9  # dense
    np.testing.assert_allclose(p.centerline, p.centerline_physical / np.asarray(p.spacing))
    np.testing.assert_allclose(p.head, p.centerline[0])
    np.testing.assert_allclose(p.tail, p.centerline[-1])


def test_named_fish_has_the_requested_length():
    p = ds.fish_phantom(length=100.0, body_radius=5.0, noise=0.0, tube=False)
    seg = np.linalg.norm(np.diff(p.centerline_physical, axis=0), axis=1)
    assert seg.sum() == pytest.approx(100.0, rel=1e-5)
    assert p.straight_shape[0] == int(np.floor(100.0 / p.straight_spacing)) + 1


@pytest.mark.parametrize("name", ALL)
def test_centerline_inside_mask(phantoms, name):
    p = phantoms[name]
    inner = (p.arclength > 1.5 * max(p.spacing)) & (p.arclength < p.length - 1.5 * max(p.spacing))
    idx = np.round(p.centerline[inner]).astype(int)
    assert np.all(p.mask[tuple(idx.T)])


@pytest.mark.parametrize("name", ALL)
def test_straight_grid_shape(phantoms, name):
    p = phantoms[name]
    rx, ry = p.half_extent
    d = p.straight_spacing
    assert d == min(p.spacing)
    assert p.straight_shape == (
        int(np.floor(p.length / d + 1e-9)) + 1,
        2 * int(np.ceil(ry / d - 1e-9)) + 1,
        2 * int(np.ceil(rx / d - 1e-9)) + 1,
    )
    s, y, x = p.straight_grid()
    assert s[0] == 0 and y[(len(y) - 1) // 2] == 0 and x[(len(x) - 1) // 2] == 0
    # the specimen lies inside the cage, and the cage is not wider than needed
    _, i, j = np.nonzero(p.straight_mask)
    assert np.all(np.abs(y[i]) <= ry) and np.all(np.abs(x[j]) <= rx)
    assert np.abs(y[i]).max() > ry - 3 * max(p.spacing)


# ------------------------------------------------------------------------------------------------------------------
# independent straightening
# ------------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ALL)
def test_straightened_mask_matches_ground_truth(phantoms, name):
    p = phantoms[name]
    got = straighten(p, p.mask) > 0.5
    assert dice(got, p.straight_mask) >= 0.95
    if min(p.spacing) == max(p.spacing):
        # away from a one-voxel band at the surface the two agree exactly
        st = ndimage.generate_binary_structure(3, 1)
        assert not np.any(ndimage.binary_erosion(p.straight_mask, st) & ~got)
        assert not np.any(got & ~ndimage.binary_dilation(p.straight_mask, st))


@pytest.mark.parametrize("name", ["fish", "cylinder", "helix"])
def test_straightened_volume_matches_ground_truth(phantoms, clean_fish, name):
    p = clean_fish if name == "fish" else phantoms[name]
    got = straighten(p, p.volume)
    err = np.abs(got - p.straight_volume.astype(np.float32))
    assert err.mean() < 0.04 * (ds.FLESH - ds.BACKGROUND)
    assert np.median(err) < 0.01 * (ds.FLESH - ds.BACKGROUND)


def test_straight_to_bent_follows_the_centerline(fish):
    s = fish.arclength[::7]
    pts = fish.straight_to_bent(np.column_stack([np.zeros_like(s), np.zeros_like(s), s]))
    np.testing.assert_allclose(pts, fish.centerline[::7], atol=1e-9)
    k = len(fish.arclength) // 2
    u, v, _ = fish.frames[k]
    got = fish.straight_to_bent([2.0, -3.0, fish.arclength[k]], physical=True)
    np.testing.assert_allclose(got, fish.centerline_physical[k] + 2.0 * u - 3.0 * v, atol=1e-9)
    with pytest.raises(InvalidInputError, match=r"must have shape \(\.\.\., 3\).*got \(4, 2\)"):
        fish.straight_to_bent(np.zeros((4, 2)))


# ------------------------------------------------------------------------------------------------------------------
# twist and orientation
# ------------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["fish", "helix", "cbend", "aniso", "tank0"])
def test_twist_is_relative_to_parallel_transport(phantoms, name):
    p = phantoms[name]
    assert p.twist[0] == 0.0
    np.testing.assert_allclose(transported_twist(p), p.twist, atol=np.radians(0.5))


def test_twist_totals(fish, helix, cbend, cylinder):
    assert fish.twist[-1] == pytest.approx(np.pi / 2)
    assert helix.twist[-1] == pytest.approx(3.0)
    assert cbend.twist[-1] == pytest.approx(-2.0)
    assert np.all(np.diff(helix.twist) >= 0) and np.all(np.diff(cbend.twist) <= 0)
    np.testing.assert_array_equal(cylinder.twist, 0.0)


def test_roll_turns_the_head_frame():
    a = ds.fish_phantom(noise=0.0, tube=False, length=60.0, body_radius=4.0)
    b = ds.fish_phantom(noise=0.0, tube=False, length=60.0, body_radius=4.0, roll=0.7)
    ua, va, na = a.frames[0]
    vb = b.frames[0, 1]
    np.testing.assert_allclose(b.frames[0, 2], na, atol=1e-12)
    assert np.arctan2(-(vb @ ua), vb @ va) == pytest.approx(0.7, abs=1e-9)
    # roll 0: dorsal faces "up" in a napari slice (-axis1) as closely as the head direction allows
    up = np.array([0.0, -1.0, 0.0])
    assert va @ up == pytest.approx(np.linalg.norm(up - (up @ na) * na), abs=1e-9)


@pytest.mark.parametrize("name", ["fish", "helix", "cbend", "aniso", "tank0"])
def test_fin_and_spine_are_dorsal(phantoms, name):
    p = phantoms[name]
    _, y, _ = p.straight_grid()
    yy = y[None, :, None]
    above = np.count_nonzero(p.straight_mask & (yy > 0))
    below = np.count_nonzero(p.straight_mask & (yy < 0))
    assert above > 1.05 * below
    # the fin: mask higher above the centre than the body reaches below it, only along the middle of the body
    s, _, _ = p.straight_grid()
    k, i, _ = np.nonzero(p.straight_mask)
    ventral = -y[i].min()
    fin = y[i] > ventral + max(p.spacing)
    assert np.count_nonzero(fin) > 20
    assert 0.25 * p.length < s[k[fin]].min() and s[k[fin]].max() < 0.7 * p.length
    # the spine (brightest voxels) sits on the dorsal side of the centre
    if p.straight_volume.max() > 2000:
        _, i, _ = np.nonzero(p.straight_volume > 2000)
        assert np.mean(y[i]) > 0.1 * p.half_extent[1] and np.mean(y[i] >= 0) > 0.95


def test_fin_is_dorsal_in_the_bent_volume(clean_fish):
    """Bent mask voxels projected on the returned centreline and frames: more mass on the +v side."""
    p = clean_fish
    vox = np.argwhere(p.mask) * np.asarray(p.spacing)
    _, k = cKDTree(p.centerline_physical).query(vox)
    inner = (k > 0) & (k < len(p.arclength) - 1)
    rel = vox[inner] - p.centerline_physical[k[inner]]
    y = np.sum(rel * p.frames[k[inner], 1], axis=1)
    assert np.count_nonzero(y > 0) > 1.05 * np.count_nonzero(y < 0)
    assert np.count_nonzero(y > 10.0) > 50 and np.count_nonzero(y < -10.0) == 0


# ------------------------------------------------------------------------------------------------------------------
# values, noise, determinism
# ------------------------------------------------------------------------------------------------------------------
def test_intensity_levels(clean_fish):
    p = clean_fish
    v = p.volume
    assert v.dtype == np.uint16 and p.mask.dtype == bool and p.straight_mask.dtype == bool
    far = ndimage.distance_transform_edt(~p.mask) > 3
    rin, rout = p.tube_radii
    c1, c2 = p.tube_center
    yy = np.arange(v.shape[1])[:, None] * p.spacing[1] - c1
    xx = np.arange(v.shape[2])[None, :] * p.spacing[2] - c2
    rho = np.hypot(yy, xx)
    wall = (rho > rin + 0.6) & (rho < rout - 0.6)
    background = far & ~((rho > rin - 1) & (rho < rout + 1))[None]
    assert np.all(v[background] == ds.BACKGROUND)
    assert np.all(v[:, wall] == ds.TUBE)
    core = ndimage.binary_erosion(p.mask, iterations=2)
    assert np.median(v[core]) == ds.FLESH
    assert v.max() == ds.SPINE
    # partial volume: a voxel is in the mask iff the specimen fills at least half of it
    assert np.all(p.straight_volume[~p.straight_mask] <= (ds.BACKGROUND + ds.FLESH) / 2 + 1)
    assert np.all(p.straight_volume[p.straight_mask] >= (ds.BACKGROUND + ds.FIN) / 2 - 1)
    assert ds.FIN in np.unique(p.straight_volume)


def test_tube_does_not_touch_fish_or_cage(clean_fish):
    p = clean_fish
    rin, _ = p.tube_radii
    pts = np.argwhere(p.mask) * np.asarray(p.spacing)
    rho = np.hypot(pts[:, 1] - p.tube_center[0], pts[:, 2] - p.tube_center[1])
    assert rin - rho.max() >= 3.0
    # the corners of the cage stay inside the tube too
    rx, ry = p.half_extent
    u, v = p.frames[:, 0], p.frames[:, 1]
    for a in (-1, 1):
        for b in (-1, 1):
            c = p.centerline_physical + a * rx * u + b * ry * v
            assert np.all(np.hypot(c[:, 1] - p.tube_center[0], c[:, 2] - p.tube_center[1]) < rin)


def test_noise_is_deterministic_and_of_the_requested_size(fish, clean_fish):
    again = ds.fish_phantom()
    np.testing.assert_array_equal(again.volume, fish.volume)
    other = ds.fish_phantom(seed=1)
    assert not np.array_equal(other.volume, fish.volume)
    np.testing.assert_array_equal(other.mask, fish.mask)
    np.testing.assert_array_equal(fish.mask, clean_fish.mask)
    np.testing.assert_array_equal(fish.straight_volume, clean_fish.straight_volume)
    diff = fish.volume.astype(float) - clean_fish.volume.astype(float)
    assert np.std(diff) == pytest.approx(40.0, rel=0.05)
    assert abs(np.mean(diff)) < 2.0
    # smoothed: neighbouring voxels are correlated
    r = np.corrcoef(diff[:, :, :-1].ravel(), diff[:, :, 1:].ravel())[0, 1]
    assert 0.2 < r < 0.9


def test_default_fish_size(fish):
    assert fish.shape[0] <= 192 and max(fish.shape[1:]) <= 96
    assert fish.length == pytest.approx(160.0)


def test_to_volume_and_layer_data(fish):
    vol = fish.to_volume()
    assert isinstance(vol, Volume)
    assert vol.shape == fish.shape and vol.dtype == np.uint16
    assert vol.spacing == fish.spacing and vol.unit == "micrometer"
    np.testing.assert_array_equal(vol.data.compute(), fish.volume)
    layers = fish.layer_data()
    assert [t[2] for t in layers] == ["image", "labels"]
    assert layers[0][1]["scale"] == fish.spacing
    np.testing.assert_array_equal(layers[1][0] > 0, fish.mask)


def test_cylinder_is_a_bent_round_rod(cylinder):
    p = cylinder
    # ground truth: a straight cylinder of radius 6 (area per slice ~ pi r^2 away from the ends)
    area = p.straight_mask[5:-5].sum(axis=(1, 2))
    assert np.all(np.abs(area - np.pi * 36) < 0.1 * np.pi * 36)
    # bent: the centreline runs along axis2 at the middle of axis0 and follows the sine along axis1
    c = p.centerline
    np.testing.assert_allclose(c[:, 0], (p.shape[0] - 1) / 2)
    assert np.ptp(c[:, 1]) == pytest.approx(24.0, abs=0.01)
    assert np.all(np.diff(c[:, 2]) > 0)


# ------------------------------------------------------------------------------------------------------------------
# the tank
# ------------------------------------------------------------------------------------------------------------------
def test_tank_labels_and_masks(tank):
    assert len(tank.fish) == 3
    assert tank.labels.shape == tank.volume.shape and tank.labels.max() == 3
    total = 0
    for i, f in enumerate(tank.fish):
        np.testing.assert_array_equal(f.mask, tank.labels == i + 1)
        assert f.volume is tank.volume
        assert f.mask.any()
        total += np.count_nonzero(f.mask)
    assert total == np.count_nonzero(tank.labels)  # disjoint
    twists = [f.twist[-1] for f in tank.fish]
    assert len(set(np.round(twists, 6))) == 3
    heads = np.array([f.head for f in tank.fish])
    assert np.min(np.linalg.norm(heads[:, None] - heads[None], axis=-1)[np.triu_indices(3, 1)]) > 3


def test_tank_fish_are_apart(tank):
    n = len(tank.fish)
    dmin = np.inf
    for i in range(n):
        dist = ndimage.distance_transform_edt(tank.labels != i + 1)
        for j in range(n):
            if j != i:
                dmin = min(dmin, dist[tank.labels == j + 1].min())
    assert dmin >= 3.0
    assert tank.min_distance == pytest.approx(dmin)


def test_tank_tube_does_not_touch_fish(tank):
    rin, rout = tank.tube_radii
    shape = tank.volume.shape
    yy = np.arange(shape[1])[:, None] * tank.spacing[1] - tank.tube_center[0]
    xx = np.arange(shape[2])[None, :] * tank.spacing[2] - tank.tube_center[1]
    rho = np.hypot(yy, xx)
    tube = np.broadcast_to(((rho >= rin - 0.5) & (rho <= rout + 0.5))[None], shape)
    dist = ndimage.distance_transform_edt(~tube)
    assert dist[tank.labels > 0].min() >= 3.0
    wall = (rho > rin + 0.6) & (rho < rout - 0.6)
    assert np.all(tank.volume[:, wall] == ds.TUBE)  # noise-free tank


def test_tank_fish_ground_truth(tank):
    for f in tank.fish:
        got = straighten(f, f.mask) > 0.5
        assert dice(got, f.straight_mask) >= 0.95
        inner = (f.arclength > 1.5) & (f.arclength < f.length - 1.5)
        assert np.all(f.mask[tuple(np.round(f.centerline[inner]).astype(int).T)])


def test_tank_is_deterministic():
    small = {"n_fish": 2, "length": 80.0, "body_radius": 5.0}
    a = ds.tank_phantom(seed=7, **small)
    b = ds.tank_phantom(seed=7, **small)
    c = ds.tank_phantom(seed=8, **small)
    np.testing.assert_array_equal(a.volume, b.volume)
    np.testing.assert_array_equal(a.labels, b.labels)
    assert a.labels.shape != c.labels.shape or not np.array_equal(a.labels, c.labels)
    vol = a.to_volume()
    assert vol.shape == a.volume.shape and vol.unit == "micrometer"


# ------------------------------------------------------------------------------------------------------------------
# bad input
# ------------------------------------------------------------------------------------------------------------------
def _arc(radius: float) -> np.ndarray:
    t = np.linspace(0, np.pi, 12)
    return np.column_stack([40 + radius * np.sin(t), 40 + radius * np.cos(t), np.full_like(t, 40.0)])


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: ds.cylinder_phantom(radius=-1.0), "radius"),
        (lambda: ds.cylinder_phantom(radius=float("nan")), "radius"),
        (lambda: ds.fish_phantom(body_radius=0.0), "body_radius"),
        (lambda: ds.fish_phantom(length=500.0, shape=(64, 64, 64)), "does not fit"),
        (lambda: ds.cylinder_phantom(amplitude=40.0), "does not fit"),
        (lambda: ds.cylinder_phantom(shape=(64, 64, 20)), "too short"),
        (lambda: ds.fish_phantom(curve=_arc(10.0)), "radius of curvature"),
        (lambda: ds.cylinder_phantom(wavelength=20.0), "radius of curvature"),
        (lambda: ds.fish_phantom(curve="zigzag"), "s-bend"),
        (lambda: ds.fish_phantom(curve=np.zeros((5, 2))), "shape"),
        (lambda: ds.fish_phantom(curve=_arc(40.0), length=50.0), "length=None"),
        (lambda: ds.fish_phantom(spacing=0.0), "spacing"),
        (lambda: ds.fish_phantom(seed=-1), "seed"),
        (lambda: ds.fish_phantom(noise=-1.0), "noise"),
        (lambda: ds.fish_phantom(shape=(10, 10)), "shape"),
        (lambda: ds.fish_phantom(length=10.0), "diameter"),
        (lambda: ds.tank_phantom(n_fish=0), "n_fish"),
        (lambda: ds.tank_phantom(gap=-1.0), "gap"),
    ],
)
def test_bad_input(make, match):
    with pytest.raises(InvalidInputError, match=match):
        make()


def test_curve_coming_back_on_itself_is_rejected():
    t = np.linspace(0, 2.3 * np.pi, 40)
    loop = np.column_stack([40 + 30 * np.cos(t), 40 + 30 * np.sin(t), 40 + 2 * t])
    with pytest.raises(InvalidInputError, match="comes back"):
        ds.fish_phantom(curve=loop, body_radius=4.0, tube=False)


def test_control_point_curve_is_followed():
    pts = np.array([[10.0, 30.0, 30.0], [60.0, 35.0, 30.0], [110.0, 30.0, 34.0], [150.0, 30.0, 30.0]])
    p = ds.fish_phantom(curve=pts, noise=0.0)
    np.testing.assert_allclose(p.head, pts[0], atol=1e-6)
    np.testing.assert_allclose(p.tail, pts[-1], atol=1e-6)
    # the curve passes through every control point (distance to the dense polyline's segments)
    a, b = p.centerline[:-1], p.centerline[1:]
    for q in pts:
        t = np.clip(np.sum((q - a) * (b - a), axis=1) / np.sum((b - a) ** 2, axis=1), 0, 1)
        assert np.min(np.linalg.norm(a + t[:, None] * (b - a) - q, axis=1)) < 0.01
    got = straighten(p, p.mask) > 0.5
    assert dice(got, p.straight_mask) >= 0.95
