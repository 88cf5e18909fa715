"""Fold-free cages: per-side fitting, shrinking, coverage and tilt against analytic references and phantoms."""

import warnings

import numpy as np
import pytest

from napari_unwind.datasets import hard_fish_phantom
from napari_unwind.deformation import Deformation, parallel_transport_frames
from napari_unwind.progress import run
from napari_unwind.skeleton import estimate_deformation_iter
from napari_unwind.skeleton._cage import fit_cages
from napari_unwind.skeleton._foldfree import coverage, max_tilt, tilted_frames, unfold


def _straight_curve(n=60):
    pts = np.stack([np.arange(5.0, 5.0 + n), np.full(n, 20.0), np.full(n, 20.0)], axis=1)
    frames = parallel_transport_frames(pts, up=(0, 1, 0))
    return pts, frames


def test_fit_cages_follows_each_side_of_an_off_centre_body():
    # a rod whose section is the box u in [-3, 7], v in [-5, 2] about a straight curve along axis0
    pts, frames = _straight_curve()
    u, v = frames[0, 0], frames[0, 1]
    mask = np.zeros((70, 40, 40), dtype=bool)
    g = np.argwhere(np.ones(mask.shape, dtype=bool)).astype(float)
    d = g - np.array([0.0, 20.0, 20.0])
    x, y = d @ u, d @ v
    inside = (g[:, 0] >= 5) & (g[:, 0] <= 64) & (x >= -3) & (x <= 7) & (y >= -5) & (y <= 2)
    mask[tuple(g[inside].astype(int).T)] = True
    keys = np.array([0, 20, 40, 59])
    b = fit_cages(mask, pts, frames, keys, spacing=1.0, margin=0.0, min_margin=0.0)
    np.testing.assert_allclose(b, np.tile([-3.0, 7.0, -5.0, 2.0], (4, 1)), atol=1e-9)
    b2 = fit_cages(mask, pts, frames, keys, spacing=1.0, margin=0.1, min_margin=2.0)
    np.testing.assert_allclose(b2, np.tile([-5.3, 9.7, -7.5, 4.2], (4, 1)), atol=1e-9)


def _arc(radius, n_keys=80, arc=np.pi / 2):
    t = np.linspace(0, arc, n_keys)
    pos = np.stack([np.zeros_like(t), radius * np.sin(t), radius * (1 - np.cos(t))], axis=1)
    n = np.stack([np.zeros_like(t), np.cos(t), np.sin(t)], axis=1)
    v = np.tile([1.0, 0.0, 0.0], (n_keys, 1))
    u = np.cross(v, n)  # towards the centre of curvature: det J = 1 - x / R
    return Deformation.from_keyframes(pos, np.stack([u, v, n], axis=1), 1.0)


def test_unfold_shrinks_only_the_inner_side_to_the_analytic_limit():
    radius, eps = 10.0, 0.2
    d = _arc(radius).set_cage(None, (-12.0, 14.0, -3.0, 3.0))
    assert d.folds()
    u = unfold(d, eps=eps)
    s = np.linspace(0, u.length, 500)
    assert u.jacobian_min(s).min() >= eps - 1e-3
    # the outer side and the y sides are kept; the inner side is R (1 - eps) (up to the chord's n . c' < 1)
    np.testing.assert_allclose(u.bounds[:, [0, 2, 3]], np.tile([-12.0, -3.0, 3.0], (len(u), 1)))
    np.testing.assert_allclose(u.bounds[:, 1], radius * (1 - eps), atol=0.01)
    # a floor keeps the tissue: the side stops there even if that folds less than eps
    floor = np.tile([-1.0, 9.0, -1.0, 1.0], (len(d), 1))
    np.testing.assert_allclose(unfold(d, eps=eps, floor=floor).bounds[:, 1], 9.0)
    # nothing to do: the same object
    ok = _arc(radius).set_cage(None, (-12.0, 5.0, -3.0, 3.0))
    assert unfold(ok, eps=eps) is ok


def test_coverage_counts_the_points_inside_and_locates_the_rest():
    pts, frames = _straight_curve(41)
    d = Deformation.from_keyframes(pts[[0, -1]], frames[[0, -1]], (4.0, 4.0))
    rng = np.random.default_rng(0)
    inside = np.column_stack([rng.uniform(-3.9, 3.9, 300), rng.uniform(-3.9, 3.9, 300), rng.uniform(0, 40, 300)])
    # 100 points beyond the cage at s in [10, 20]
    out = np.column_stack([rng.uniform(4.5, 6, 100), rng.uniform(-3, 3, 100), rng.uniform(10, 20, 100)])
    c = coverage(d, d.forward(np.vstack([inside, out])), bin_width=2.0)
    assert c.fraction == pytest.approx(0.75)
    assert c.folded == 0
    lo = min(a for a, _, _ in c.lost)
    hi = max(b for _, b, _ in c.lost)
    assert 8 <= lo <= 10 and 20 <= hi <= 22
    assert sum(f for *_, f in c.lost) == pytest.approx(0.25)


def test_tilted_frames_spread_a_kink_and_max_tilt_measures_it():
    # a polyline with a 60 degree kink at its middle: the tangents jump there
    a = np.stack([np.arange(0.0, 30.0), np.zeros(30), np.zeros(30)], axis=1)
    turn = np.array([np.cos(np.pi / 3), np.sin(np.pi / 3), 0.0])
    b = a[-1] + np.arange(1.0, 31.0)[:, None] * turn
    pts = np.vstack([a, b])
    frames = parallel_transport_frames(pts, up=(0, 0, 1))
    sc = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    keys = np.array([0, 20, 29, 40, 59])
    same = tilted_frames(frames, sc, keys, np.zeros(5))
    np.testing.assert_array_equal(same, frames[keys])
    tilted = tilted_frames(frames, sc, keys, np.full(5, 8.0))
    # keyframe 20 (10 before the kink) leans towards the new direction; the frames stay rotations
    assert 0 < np.degrees(np.arccos(tilted[1, 2] @ frames[20, 2])) < 30
    for f in tilted:
        np.testing.assert_allclose(f @ f.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(f) > 0
    d = Deformation.from_keyframes(pts[keys], tilted, 2.0)
    chord_angles = []
    for k in range(len(keys) - 1):
        chord = pts[keys[k + 1]] - pts[keys[k]]
        chord /= np.linalg.norm(chord)
        chord_angles += [np.degrees(np.arccos(np.clip(tilted[k, 2] @ chord, -1, 1))),
                         np.degrees(np.arccos(np.clip(tilted[k + 1, 2] @ chord, -1, 1)))]
    assert max_tilt(d) == pytest.approx(max(chord_angles), abs=0.5)


# Seed 3 (a tight helix: the tilted, shrunk cages keep only about 93 % of the mask) is not in the suite: the goal is
# open, and the coverage of tight helices is a figure in benchmarks/RESULTS.md, not an expected failure.
@pytest.mark.parametrize("seed", [0, 1])
def test_hard_phantoms_do_not_fold_and_keep_the_mask(seed):
    ph = hard_fish_phantom(seed, noise=0)
    ends = (ph.centerline[0], ph.centerline[-1])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = run(estimate_deformation_iter(ph.mask, ends, spacing=ph.spacing))
        old = run(estimate_deformation_iter(ph.mask, ends, spacing=ph.spacing, fold_free=False))
    s = np.linspace(0, r.deformation.length, 4000)
    assert r.deformation.jacobian_min(s).min() > 0.15
    assert r.min_jacobian > 0.15 and not r.deformation.folds()
    assert r.coverage >= 0.99
    # without the construction these bends fold (one cage for the whole body)
    assert old.deformation.folds()



def test_straightening_an_offset_cage_samples_where_its_origin_says():
    from napari_unwind.warp import map_points, straighten

    g = np.indices((40, 40, 60), dtype=float)
    vol = (g[0] + 2 * g[1] + 3 * g[2]).astype(np.float32)  # linear: trilinear interpolation is exact
    frame = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])  # u x v = n, n along -axis2
    d = Deformation.from_keyframes([[20.0, 20.0, 50.0], [22.0, 18.0, 10.0]], [frame, frame], 1.0)
    d = d.set_cage(0, (-3.0, 8.0, -6.0, 2.0)).set_cage(1, (-5.0, 4.0, -2.0, 5.0))
    out = straighten(vol, d, spacing=1.0, order=1)
    data = np.asarray(out.data)
    assert data.shape == d.output_shape(1.0) == (data.shape[0], 6 + 5 + 1, 5 + 8 + 1)
    k, i, j = np.indices(data.shape).reshape(3, -1).astype(float)
    o = np.asarray(out.origin)
    xys = np.column_stack([o[2] + j, o[1] + i, o[0] + k])
    expect = d.to_voxels(d.forward(xys)) @ np.array([1.0, 2.0, 3.0])
    np.testing.assert_allclose(data.reshape(-1), expect, atol=1e-3)
    # points go to the straight voxel whose coordinates the origin gives, and back
    p = d.to_voxels(d.forward(np.array([[6.0, 1.5, 12.0], [-4.0, 3.0, 30.0]])))
    st = map_points(p, d, to="straight")
    np.testing.assert_allclose(o[::-1][:2] + st[:, [2, 1]], [[6.0, 1.5], [-4.0, 3.0]], atol=1e-6)
    np.testing.assert_allclose(map_points(st, d, to="scan"), p, atol=1e-6)


def test_coverage_does_not_hold_points_where_the_map_folds():
    """A quarter arc of radius 10 with u towards the centre of curvature: det J = 1 - x / R (analytic), so a cage
    reaching x = 14 folds for x > 10. Points drawn in the cage on both sides (none within 0.5 of x = R, where the
    chords' n . c' < 1 blurs the sign) are held iff x < R and folded iff x > R (issue 19: folded voxels counted as
    held)."""
    radius = 10.0
    d = _arc(radius).set_cage(None, (-12.0, 14.0, -3.0, 3.0))
    rng = np.random.default_rng(1)
    x = np.concatenate([rng.uniform(-11.5, 9.5, 600), rng.uniform(10.5, 13.5, 200)])
    xys = np.column_stack([x, rng.uniform(-2.5, 2.5, 800), rng.uniform(1.0, d.length - 1.0, 800)])
    c = coverage(d, d.forward(xys), bin_width=2.0)
    assert c.fraction == pytest.approx(600 / 800)
    assert c.folded == pytest.approx(200 / 800)
    assert sum(f for *_, f in c.lost) == pytest.approx(200 / 800)


def _held_at_own_place(d, ph):
    """Independent coverage: the phantom's true mask voxels mapped by ``Deformation.inverse`` (Newton, not the
    compiled inverse ``coverage`` uses), counted when inside the cage at their own place along the body (within the
    cage's reach of the phantom's true s, as tests/test_hard_phantoms.py counts) where det J, by central
    differences of ``forward``, is > 0."""
    pts = np.argwhere(ph.mask) * np.asarray(ph.spacing) + np.asarray(d.origin)
    inv = d.inverse(pts)
    xys = inv.xys
    ok = np.isfinite(xys).all(axis=1) & (inv.residual < 1e-3)
    s = np.where(ok, xys[:, 2], -1.0)
    b = d.bounds_at(np.clip(s, 0, d.length))
    inside = (ok & (s >= 0) & (s <= d.length) & (xys[:, 0] >= b[:, 0]) & (xys[:, 0] <= b[:, 1])
              & (xys[:, 1] >= b[:, 2]) & (xys[:, 1] <= b[:, 3]))
    q = xys[inside]
    h = 1e-4
    jac = np.stack([(d.forward(q + h * e) - d.forward(q - h * e)) / (2 * h) for e in np.eye(3)], axis=2)
    det = np.full(len(pts), -1.0)
    det[inside] = np.linalg.det(jac)
    own = np.abs(s - ph.mask_arclength[ph.mask]) <= max(ph.half_extent)
    return float(np.mean(inside & own & (det > 0)))


def test_the_tilt_holds_more_of_a_tight_s_bend_than_the_untilted_cages(monkeypatch):
    """S-bend 1009 (hard_fish_phantom): with the keyframes' normals tilted the cages hold 0.9992 of the mask at its
    own place; the same construction with every window 0 (no tilt) holds 0.9959 (measured, lattice mesher:
    deterministic). Until the twist read its sections up to the working mask's crop faces this test used helix
    1002 (0.999 against 0.9985); on it, and on every helix and coil of seeds 1000-1029, the untilted cages now hold
    as much and are kept, while on s-bends the tilt holds more on 10 of 30 (by up to 0.0034). Issue 19: the tilt
    was never applied and every test stayed green."""
    import napari_unwind.skeleton._foldfree as ff

    ph = hard_fish_phantom(1009, kind="s-bend")
    ends = (ph.centerline[0], ph.centerline[-1])

    def held():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            r = run(estimate_deformation_iter(ph.mask, ends, spacing=ph.spacing, volume=ph.volume))
        assert not r.deformation.folds()
        return _held_at_own_place(r.deformation, ph)

    tilted = held()
    tilt = ff.tilted_frames
    monkeypatch.setattr(ff, "tilted_frames", lambda f, a, k, sigma, **kw: tilt(f, a, k, np.zeros_like(sigma), **kw))
    untilted = held()
    # the figures do not vary run to run
    assert tilted >= 0.995 and tilted > untilted + 0.002, (tilted, untilted)


def test_format_lost_keeps_the_largest_in_order_of_s_and_counts_the_rest():
    from napari_unwind.skeleton._foldfree import format_lost

    lost = ((0.0, 2.0, 0.01), (4.0, 6.0, 0.05), (8.0, 10.0, 0.02), (12.0, 14.0, 0.03), (16.0, 18.0, 0.001))
    assert format_lost(lost, "mm") == ("s = 4..6 mm (5 %), s = 8..10 mm (2 %), s = 12..14 mm (3 %) and 2 more")
    assert format_lost(lost[:2], "mm") == "s = 0..2 mm (1 %), s = 4..6 mm (5 %)"
    assert format_lost((), "mm") == "none"


def test_coverage_of_no_points_is_whole():
    pts, frames = _straight_curve(11)
    d = Deformation.from_keyframes(pts[[0, -1]], frames[[0, -1]], 2.0)
    c = coverage(d, np.zeros((0, 3)))
    assert (c.fraction, c.lost, c.folded) == (1.0, (), 0.0)


def test_tilted_normal_is_the_gaussian_mean_of_the_tangents():
    """21 dense samples 1 apart: tangents along axis0 up to sample 10, along axis1 after it. At key 8 with sigma 2
    the new normal is (A, B, 0) / |(A, B)|, A and B the sums of exp(-(j - 8)^2 / 8) over each part (written out
    here); the minimal rotation about axis2 keeps u = axis2."""
    j = np.arange(21.0)
    n = np.where((j <= 10)[:, None], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    u = np.tile([0.0, 0.0, 1.0], (21, 1))
    frames = np.stack([u, np.cross(n, u), n], axis=1)
    out = tilted_frames(frames, j, np.array([8, 15]), np.array([2.0, 0.0]))
    a = sum(np.exp(-((k - 8) ** 2) / 8) for k in range(11))
    b = sum(np.exp(-((k - 8) ** 2) / 8) for k in range(11, 21))
    want = np.array([a, b, 0.0]) / np.hypot(a, b)
    np.testing.assert_allclose(out[0, 2], want, atol=1e-12)
    np.testing.assert_allclose(out[0, 0], [0.0, 0.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(out[0, 1], np.cross(want, [0.0, 0.0, 1.0]), atol=1e-12)
    np.testing.assert_array_equal(out[1], frames[15])


def test_unfold_shrinks_the_inner_y_side_when_v_points_to_the_centre():
    """The arc of the test above with its frames turned a quarter about n (u' = -v, v' = u): v now points to the
    centre of curvature, det J = 1 - y / R, and only y_hi shrinks, to R (1 - eps)."""
    radius, eps = 10.0, 0.2
    d = _arc(radius)
    turned = [np.stack([-k.frame[1], k.frame[0], k.frame[2]]) for k in d.keyframes]
    d = Deformation.from_keyframes([k.position for k in d.keyframes], turned, 1.0).set_cage(None, (-3.0, 3.0, -12.0,
                                                                                                   14.0))
    assert d.folds()
    u = unfold(d, eps=eps)
    np.testing.assert_allclose(u.bounds[:, [0, 1, 2]], np.tile([-3.0, 3.0, -12.0], (len(u), 1)))
    np.testing.assert_allclose(u.bounds[:, 3], radius * (1 - eps), atol=0.01)


def _turned_arc(radius, theta, bounds):
    """The quarter arc of :func:`_arc` (80 keyframes) with every frame turned by ``theta`` about n (u' = cos u +
    sin v, v' = -sin u + cos v). Towards the centre of curvature is u = cos(theta) u' - sin(theta) v', so on every
    segment det J = n . c' - k (x cos(theta) - y sin(theta)): a bend about both axes at once, w_x = k sin(theta),
    w_y = k cos(theta). Between keyframes an angle 2h apart the chord is 2 R sin(h), so exactly n . c' = cos(h)
    at both ends of a segment and k = 2h / chord = h / (R sin(h)). Returns the deformation, cos(h) and k."""
    d = _arc(radius)
    c, s = np.cos(theta), np.sin(theta)
    turned = [np.stack([c * k.frame[0] + s * k.frame[1], -s * k.frame[0] + c * k.frame[1], k.frame[2]])
              for k in d.keyframes]
    d = Deformation.from_keyframes([k.position for k in d.keyframes], turned, 1.0).set_cage(None, bounds)
    h = np.pi / 2 / (len(d) - 1) / 2
    return d, np.cos(h), h / (radius * np.sin(h))


# (theta in degrees, cage, floor, side -> its unfolded value as f(base - eps, kx, ky), kx = k |cos|, ky = k |sin|)
_BOTH_SIDES = {
    # x rotates faster (cos 30 > sin 30): the inner x side x_hi takes the whole deficit, y_lo = -12 is kept
    "x-faster": (30, (-3.0, 14.0, -12.0, 3.0), None, {1: lambda m, kx, ky: (m - 12 * ky) / kx}),
    # y rotates faster (sin 60 > cos 60): the inner y side y_lo takes it, x_hi = 14 is kept
    "y-faster": (60, (-3.0, 14.0, -12.0, 3.0), None, {2: lambda m, kx, ky: -(m - 14 * kx) / ky}),
    # the same with a floor at y_lo = -4: y stops there, the rest comes off x_hi
    "y-floored": (60, (-3.0, 14.0, -12.0, 3.0), (-1.0, 1.0, -4.0, 1.0),
                  {1: lambda m, kx, ky: (m - 4 * ky) / kx, 2: lambda m, kx, ky: -4.0}),
    # the other corner (w_x, w_y < 0: x_lo and y_hi inner), y faster
    "other-corner": (-120, (-14.0, 3.0, -3.0, 12.0), None, {3: lambda m, kx, ky: (m - 14 * kx) / ky}),
    # x_hi alone folds (18 k cos 60 > 1 - eps): y_hi, faster, goes onto the curve first (its y_lo is 0: a
    # sliver keeps the box), then x_hi to the limit of x alone
    "y-onto-curve": (-60, (-3.0, 18.0, 0.0, 5.0), None, {1: lambda m, kx, ky: m / kx, 3: lambda m, kx, ky: 0.0}),
}


@pytest.mark.parametrize("case", list(_BOTH_SIDES))
def test_unfold_of_a_cage_folding_on_an_x_and_a_y_side_takes_the_deficit_off_the_faster_side(case):
    """A bend about both frame axes (the arc's frames turned about n): the cage's inner corner folds through an x
    and a y side at once. unfold cuts the side of the faster rotation first, down to the floor (or the curve),
    then the other, until det J at the inner corner is eps; every keyframe gets the same analytic sides."""
    theta, cage, floor, want = _BOTH_SIDES[case]
    radius, eps = 10.0, 0.2
    d, base, k = _turned_arc(radius, np.radians(theta), cage)
    assert d.folds()
    u = unfold(d, eps=eps, floor=None if floor is None else np.tile(floor, (len(d), 1)))
    kx, ky = k * abs(np.cos(np.radians(theta))), k * abs(np.sin(np.radians(theta)))
    expect = np.array(cage)
    for side, f in want.items():
        expect[side] = f(base - eps, kx, ky)
    got = u.bounds
    assert got[:, 1].min() > got[:, 0].max() and got[:, 3].min() > got[:, 2].max()
    # a side on the curve keeps a sliver (1e-6 of the largest side), all others are exact
    np.testing.assert_allclose(got, np.tile(expect, (len(u), 1)), rtol=1e-9, atol=2e-5)
    np.testing.assert_allclose(u.jacobian_min(u.knots), eps, atol=1e-5)


@pytest.mark.parametrize("theta, side", [(0, 1), (-90, 3)], ids=["u-inward", "v-inward"])
def test_unfold_finds_the_inner_side_of_a_cage_beside_the_curve(theta, side):
    """A cage wholly on the inner side of a tight arc (R = 0.5, so the rate k ~ 2 > 1): across the curve
    direction it spans [0.3, 1.0]. The inner side is the far one, 1.0, where det J = cos(h) - 2 k < 0; its near
    side 0.3 holds (cos(h) - 0.6 k > eps). unfold brings the far side to (cos(h) - eps) / k ~ R (1 - eps) = 0.4
    and keeps the near side: comparing the sides scaled by the rate (x_hi w_y against x_lo w_y) tells them apart,
    scaling one of them by 1 / w instead does not, once w > 1."""
    radius, eps = 0.5, 0.2
    cage = (0.3, 1.0, -0.2, 0.2) if side == 1 else (-0.2, 0.2, 0.3, 1.0)
    d, base, k = _turned_arc(radius, np.radians(theta), cage)
    assert k > 1 and d.folds()
    u = unfold(d, eps=eps)
    expect = np.array(cage)
    expect[side] = (base - eps) / k
    np.testing.assert_allclose(u.bounds, np.tile(expect, (len(u), 1)), rtol=1e-9, atol=1e-12)
    assert not u.folds(threshold=eps - 1e-6)


def _helix(n=400):
    t = np.linspace(0, 3 * np.pi, n)
    return np.stack([8 * np.cos(t), 8 * np.sin(t), 3 * t], axis=1)


def test_tilted_keyframes_carry_u_along_their_own_normals_where_the_twist_is_not_read():
    # a helix tilted hard: with confidence 0 each keyframe's u is the previous one's turned by the minimal rotation
    # between the two normals (written here by Rodrigues), plus the twist's increment about the new normal
    pts = _helix()
    frames = parallel_transport_frames(pts, up=(0, 0, 1))
    sc = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    keys = np.arange(0, 400, 25)
    sigma = np.full(len(keys), 6.0)
    theta = 0.002 * sc  # a slow twist
    absolute = tilted_frames(frames, sc, keys, sigma)
    out = tilted_frames(frames, sc, keys, sigma, twist=theta, confidence=np.zeros(len(sc)))
    np.testing.assert_allclose(out[:, 2], absolute[:, 2], atol=1e-12)  # the same planes
    np.testing.assert_allclose(out[0], absolute[0], atol=1e-12)
    for i in range(1, len(keys)):
        a, b = out[i - 1, 2], out[i, 2]
        axis = np.cross(a, b)
        sn, cs = np.linalg.norm(axis), a @ b
        k = axis / sn
        u = out[i - 1, 0]
        u = u * cs + np.cross(k, u) * sn + k * (k @ u) * (1 - cs)
        d = theta[keys[i]] - theta[keys[i - 1]]
        u = np.cos(d) * u + np.sin(d) * np.cross(b, u)
        np.testing.assert_allclose(out[i, 0], u, atol=1e-9)
        np.testing.assert_allclose(out[i] @ out[i].T, np.eye(3), atol=1e-12)
    # the tilted sections spin against that by tens of degrees when u is turned from the dense frames instead
    spin = [np.degrees(np.arccos(np.clip(out[i, 0] @ absolute[i, 0], -1, 1))) for i in range(len(keys))]
    assert max(spin) > 5.0
    # with confidence 1 the turned dense u (v as near the dorsal direction as the plane allows) is kept
    np.testing.assert_allclose(tilted_frames(frames, sc, keys, sigma, twist=theta, confidence=np.ones(len(sc))),
                               absolute, atol=1e-9)
