"""The deformation model against analytic geometry: lines, circles, helices, known twists."""

import numpy as np
import pytest

from napari_unwind.deformation import Deformation, Keyframe, parallel_transport_frames
from napari_unwind.errors import InvalidInputError


def circle_deformation(radius=50.0, n_keys=200, arc=np.pi, cage=5.0, bend_in="u"):
    """Keyframes densely on a circle in the (axis1, axis2) plane, frames: n tangent.

    ``bend_in="u"``: v = axis0 (normal to the circle's plane), so the curve bends in the plane of u and n;
    ``bend_in="v"``: u = axis0, so it bends in the plane of v and n.
    """
    t = np.linspace(0, arc, n_keys)
    pos = np.stack([np.zeros_like(t), radius * np.sin(t), radius * (1 - np.cos(t))], axis=1)
    n = np.stack([np.zeros_like(t), np.cos(t), np.sin(t)], axis=1)
    axis0 = np.tile([1.0, 0.0, 0.0], (n_keys, 1))
    if bend_in == "u":
        v = axis0
        u = np.cross(v, n)
    else:
        u = axis0
        v = np.cross(n, u)  # u x v = u x (n x u) = n
    return Deformation.from_keyframes(pos, np.stack([u, v, n], axis=1), cage), t


def straight_deformation(length=40.0, cage=(3.0, 4.0)):
    frame = np.eye(3)[[1, 2, 0]]  # u = axis1, v = axis2, n = axis0: right-handed (e1 x e2 = e0)
    pos = np.array([[0.0, 10.0, 10.0], [length, 10.0, 10.0]])
    return Deformation.from_keyframes(pos, np.stack([frame, frame]), cage)


def test_straight_line_is_a_translation():
    d = straight_deformation()
    rng = np.random.default_rng(0)
    xys = np.column_stack([rng.uniform(-3, 3, 50), rng.uniform(-4, 4, 50), rng.uniform(0, 40, 50)])
    got = d.forward(xys)
    expect = np.column_stack([xys[:, 2], 10 + xys[:, 0], 10 + xys[:, 1]])
    np.testing.assert_allclose(got, expect, atol=1e-12)
    assert d.length == pytest.approx(40.0)


def test_frames_are_orthonormal_and_right_handed_everywhere():
    d, _ = circle_deformation(n_keys=7)
    d = d.twist_keyframe(3, 1.0).tilt_keyframe(5, 0.3, axis="v")
    _, r = d.sample(np.linspace(-1, d.length + 1, 301))
    np.testing.assert_allclose(np.einsum("kij,klj->kil", r, r), np.broadcast_to(np.eye(3), r.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-12)


def test_circle_centre_and_arclength_match_the_analytic_circle():
    radius = 50.0
    d, t = circle_deformation(radius=radius)
    # polyline length = sum of chords: 2 R sin(dt/2) per segment
    dt = t[1] - t[0]
    assert d.length == pytest.approx((len(t) - 1) * 2 * radius * np.sin(dt / 2), rel=1e-12)
    # the centre stays within the sagitta of the circle, and n stays tangent
    c, r = d.sample(np.linspace(0, d.length, 997))
    dist = np.hypot(c[:, 1], c[:, 2] - radius)
    assert np.abs(dist - radius).max() <= radius * (1 - np.cos(dt / 2)) + 1e-9
    theta = np.arctan2(c[:, 1], radius - c[:, 2])
    tangent = np.stack([np.zeros_like(theta), np.cos(theta), np.sin(theta)], axis=1)
    assert np.min(np.einsum("ij,ij->i", tangent, r[:, 2])) > np.cos(dt)


def test_slerp_twist_is_linear_in_arclength_and_continuous():
    """Two twists on a straight rod: the twist angle is piecewise linear in s and has no jump at keyframes."""
    frame = np.eye(3)[[1, 2, 0]]
    pos = np.array([[0.0, 0, 0], [10.0, 0, 0], [30.0, 0, 0]])
    d = Deformation.from_keyframes(pos, np.stack([frame] * 3), 2.0)
    d = d.twist_keyframe(1, 0.6).twist_keyframe(2, 0.6 + 1.0)
    s = np.linspace(0, 30, 601)
    _, r = d.sample(s)
    u0 = frame[0]
    v0 = frame[1]
    angle = np.unwrap(np.arctan2(r[:, 0] @ v0, r[:, 0] @ u0))
    expect = np.interp(s, [0, 10, 30], [0, 0.6, 1.6])
    np.testing.assert_allclose(angle, expect, atol=1e-9)
    np.testing.assert_allclose(r[:, 2], np.broadcast_to(frame[2], r[:, 2].shape), atol=1e-12)


def test_inverse_of_forward_is_identity_and_outside_points_are_flagged():
    d, _ = circle_deformation(radius=40.0, n_keys=9, cage=6.0)
    d = d.twist_keyframe(4, 0.8).with_pad(3.0, 2.0)
    rng = np.random.default_rng(1)
    xys = np.column_stack([rng.uniform(-6, 6, 3000), rng.uniform(-6, 6, 3000), rng.uniform(-3, d.length + 2, 3000)])
    inv = d.inverse(d.forward(xys))
    assert inv.inside.all()
    np.testing.assert_allclose(inv.xys, xys, atol=1e-7)
    assert np.nanmax(inv.residual) < 1e-7
    # points beyond the cage: outside
    far = d.forward(np.array([[9.0, 0.0, 10.0], [0.0, -9.0, 20.0], [0.0, 0.0, d.length + 5]]))
    assert not d.inverse(far).inside.any()


def test_inverse_on_the_analytic_circle():
    """A point at angle phi and distance rho from the circle's axis has s = R phi (dense keyframes)."""
    radius = 30.0
    d, _ = circle_deformation(radius=radius, n_keys=400, cage=8.0)
    phi = np.array([0.3, 1.0, 2.0, 2.9])
    rho = np.array([25.0, 30.0, 34.0, 28.0])
    height = np.array([1.0, -2.0, 0.5, 0.0])
    pts = np.stack([height, rho * np.sin(phi), radius - rho * np.cos(phi)], axis=1)
    inv = d.inverse(pts)
    assert inv.inside.all()
    np.testing.assert_allclose(inv.xys[:, 2], radius * phi, rtol=2e-4)
    np.testing.assert_allclose(inv.xys[:, 1], height, atol=1e-6)  # v = axis0
    np.testing.assert_allclose(np.abs(inv.xys[:, 0]), np.abs(radius - rho), atol=1e-3)


@pytest.mark.parametrize("cage, folds", [(0.8, False), (1.2, True)])
def test_folds_where_the_cage_exceeds_the_radius_of_curvature(cage, folds):
    radius = 20.0
    d, _ = circle_deformation(radius=radius, n_keys=300, cage=cage * radius, arc=np.pi / 2)
    found = d.folds()
    assert bool(found) == folds
    if folds:
        lo, hi = found[0]
        assert lo <= 1.0 and hi >= d.length - 1.0  # the whole arc folds
    # the smallest Jacobian is 1 - cage/R on a circle (analytic)
    j = d.jacobian_min(np.linspace(1, d.length - 1, 50))
    np.testing.assert_allclose(j, 1 - cage, atol=2e-3)


@pytest.mark.parametrize("bend_in", ["u", "v"])
@pytest.mark.parametrize("cage", [(1.2, 0.1), (0.1, 1.2), (0.9, 0.3), (0.3, 0.9)])
def test_folds_with_asymmetric_cages_follow_the_extent_along_the_bend(cage, bend_in):
    """On a circle of radius R, det J = 1 - x/R with x the offset along the bend direction (towards the centre):
    the smallest Jacobian over the cage is 1 - r/R, r the half-extent along the bend (rx when the curve bends in
    the plane of u, ry in the plane of v); it folds exactly when r > R. The other half-extent does not matter."""
    radius = 20.0
    he = (cage[0] * radius, cage[1] * radius)
    d, _ = circle_deformation(radius=radius, n_keys=300, cage=he, arc=np.pi / 2, bend_in=bend_in)
    along = cage[0] if bend_in == "u" else cage[1]
    j = d.jacobian_min(np.linspace(1, d.length - 1, 50))
    np.testing.assert_allclose(j, 1 - along, atol=2e-3)
    found = d.folds()
    assert bool(found) == (along > 1)
    if found:
        lo, hi = found[0]
        assert lo <= 1.0 and hi >= d.length - 1.0  # the whole arc folds
    # the analytic Jacobian at the cage's corners, by finite differences of the forward map
    s = d.length / 2
    h = 1e-5
    corners = [(sx * he[0], sy * he[1]) for sx in (-1, 1) for sy in (-1, 1)]
    dets = []
    for x, y in corners:
        p = np.array([[x, y, s]])
        jac = np.stack([(d.forward(p + h * e) - d.forward(p - h * e))[0] / (2 * h) for e in np.eye(3)], axis=1)
        dets.append(np.linalg.det(jac))
    assert min(dets) == pytest.approx(1 - along, abs=2e-3)


def test_straight_parts_never_fold():
    assert straight_deformation(cage=(100.0, 100.0)).folds() == []


def test_adding_a_keyframe_keeps_the_map():
    d, _ = circle_deformation(n_keys=6)
    d = d.twist_keyframe(2, 0.7)
    d2 = d.add_keyframe(d.length * 0.43)
    assert len(d2) == len(d) + 1
    xys = np.random.default_rng(2).uniform([-4, -4, 0], [4, 4, d.length], (500, 3))
    np.testing.assert_allclose(d2.forward(xys), d.forward(xys), atol=1e-10)
    with pytest.raises(InvalidInputError, match="0 < s <"):
        d.add_keyframe(-1.0)


def test_edits_do_what_they_say():
    d, _ = circle_deformation(n_keys=5)
    k = d.keyframes[2]
    moved = d.move_keyframe(2, 1.5, -2.0).keyframes[2]
    np.testing.assert_allclose(moved.position - k.position, 1.5 * k.u - 2.0 * k.v, atol=1e-12)
    twisted = d.twist_keyframe(2, np.pi / 6).keyframes[2]
    np.testing.assert_allclose(twisted.n, k.n, atol=1e-12)
    assert np.arctan2(twisted.u @ k.v, twisted.u @ k.u) == pytest.approx(np.pi / 6)
    tilted = d.tilt_keyframe(2, 0.2, axis="u").keyframes[2]
    np.testing.assert_allclose(tilted.u, k.u, atol=1e-12)
    assert np.arccos(np.clip(tilted.n @ k.n, -1, 1)) == pytest.approx(0.2)
    resized = d.resize_keyframe(2, (7.0, 3.0)).keyframes[2]
    assert resized.half_extent == (7.0, 3.0)
    assert len(d.delete_keyframe(-1)) == 4
    padded = d.with_pad(4.0, 2.0)
    assert padded.output_shape(1.0)[0] == d.output_shape(1.0)[0] + 6
    for bad, why in ((lambda: d.delete_keyframe(9), "index 9 is out of range"),
                     (lambda: d.tilt_keyframe(0, 0.1, axis="n"), "tilt axis must be 'u' or 'v', got 'n'"),
                     (lambda: straight_deformation().delete_keyframe(0), "at least 2 keyframes"),
                     (lambda: d.with_pad(-1, 0), r"padding must be >= 0 at both ends, got \(-1, 0\)")):
        with pytest.raises(InvalidInputError, match=why):
            bad()


def test_slice_geometry_matches_forward_on_the_output_grid():
    d, _ = circle_deformation(n_keys=8, cage=4.0)
    d = d.with_pad(2.0, 1.0)
    ds = 0.7
    ns, ny, nx = d.output_shape(ds)
    base, dv, du = d.slice_geometry(ds)
    k, i, j = 5, 3, 9
    expect = d.forward(np.array([[(j - (nx - 1) / 2) * ds, (i - (ny - 1) / 2) * ds, -2.0 + k * ds]]))[0]
    np.testing.assert_allclose(base[k] + i * dv[k] + j * du[k], d.to_voxels(expect[None])[0], atol=1e-12)
    assert ny == 2 * int(np.ceil(4.0 / ds)) + 1 and nx == ny


def test_from_polyline_uses_voxels_and_spacing():
    pts = np.array([[0, 0, 0], [10, 0, 0], [20, 5, 0]], float)
    d = Deformation.from_polyline(pts, spacing=(2.0, 1.0, 1.0), cage_half_extent=3.0, up=(0, 1, 0))
    np.testing.assert_allclose(d.positions, pts * [2, 1, 1])
    assert d.length == pytest.approx(20 + np.hypot(20, 5))
    np.testing.assert_allclose(d.keyframes[0].v, [0, 1, 0], atol=1e-12)  # follows 'up'
    np.testing.assert_allclose(d.to_voxels(d.positions), pts)


def test_parallel_transport_has_no_twist_on_a_helix():
    """Rotation-minimising frames: the relative rotation of neighbours has no component about n."""
    t = np.linspace(0, 4 * np.pi, 800)
    pts = np.stack([3 * t, 10 * np.cos(t), 10 * np.sin(t)], axis=1)
    f = parallel_transport_frames(pts)
    # d u / ds has no component along v for a rotation-minimising frame
    du = np.diff(f[:, 0], axis=0)
    twist_rate = np.einsum("ij,ij->i", du, f[:-1, 1])
    bend_rate = np.linalg.norm(np.diff(f[:, 2], axis=0), axis=1)
    assert np.abs(twist_rate).max() < 0.02 * bend_rate.max()


def test_serialisation_round_trip_and_malformed_input():
    d, _ = circle_deformation(n_keys=4)
    d = d.twist_keyframe(1, 0.4).with_pad(1.0, 2.0)
    back = Deformation.from_dict(d.to_dict())
    assert back == d
    xys = np.random.default_rng(3).uniform([-4, -4, 0], [4, 4, d.length], (100, 3))
    np.testing.assert_allclose(back.forward(xys), d.forward(xys), atol=1e-12)
    bad = d.to_dict()
    bad["keyframes"][0]["frame"] = [[1, 0, 0], [0, 1, 0], [0, 0, -1]]  # left-handed
    with pytest.raises(InvalidInputError, match="right-handed"):
        Deformation.from_dict(bad)
    with pytest.raises(InvalidInputError, match="schema"):
        Deformation.from_dict({"schema": "something else"})
    with pytest.raises(InvalidInputError, match="malformed"):
        Deformation.from_dict({**d.to_dict(), "keyframes": [{"position": [0, 0, 0]}] * 2})


def test_bad_keyframes_are_refused():
    with pytest.raises(InvalidInputError, match="at least 2"):
        Deformation((Keyframe([0, 0, 0], np.eye(3), 1.0),))
    with pytest.raises(InvalidInputError, match="same position"):
        Deformation.from_keyframes([[0, 0, 0], [0, 0, 0]], np.stack([np.eye(3)] * 2), 1.0)
    with pytest.raises(InvalidInputError, match="degenerate"):
        Keyframe([0, 0, 0], np.zeros((3, 3)), 1.0)
    with pytest.raises(InvalidInputError, match="positive"):
        Keyframe([0, 0, 0], np.eye(3), (1.0, 0.0))
    with pytest.raises(InvalidInputError, match="coincide"):
        parallel_transport_frames(np.array([[0, 0, 0], [0, 0, 0], [1, 0, 0]], float))


# ---------------------------------------------------------------------------------------------------------------------
# per-side cages (keyframe offsets): analytic references on the circle, whose centre of curvature lies at x = +R
# ---------------------------------------------------------------------------------------------------------------------
def _with_bounds(d, bounds):
    return d.set_cage(None, bounds)


@pytest.mark.parametrize("bounds", [(-3.0, 8.0, -2.0, 2.0), (-8.0, 3.0, -2.0, 2.0), (-9.0, -1.0, 1.0, 6.0),
                                    (2.0, 9.5, -4.0, -1.0)])
def test_jacobian_min_of_an_offset_cage_is_one_minus_its_inner_side_over_r(bounds):
    radius = 10.0
    d, _ = circle_deformation(radius=radius, n_keys=400, arc=np.pi / 2, cage=1.0, bend_in="u")
    d = _with_bounds(d, bounds)
    s = np.linspace(0.5, d.length - 0.5, 50)
    # det J = 1 - x / R, smallest at the side nearest the centre of curvature (x = x_hi)
    np.testing.assert_allclose(d.jacobian_min(s), 1 - bounds[1] / radius, atol=2e-3)
    assert (len(d.folds()) > 0) == (bounds[1] >= radius)


def test_jacobian_min_matches_finite_differences_of_forward_over_an_offset_cage():
    rng = np.random.default_rng(3)
    d, _ = circle_deformation(radius=12.0, n_keys=30, arc=2.0, cage=1.0, bend_in="v")
    d = d.twist_keyframe(10, 0.4).tilt_keyframe(20, 0.2)
    d = d.set_cage(None, (-2.0, 5.0, -6.0, 3.0)).set_cage(5, (-1.0, 2.0, -9.0, 1.0))
    s = rng.uniform(0.2, d.length - 0.2, 40)
    b = d.bounds_at(s)
    h = 1e-5
    best = np.full(len(s), np.inf)
    for fx in np.linspace(0, 1, 9):
        for fy in np.linspace(0, 1, 9):
            x = b[:, 0] + fx * (b[:, 1] - b[:, 0])
            y = b[:, 2] + fy * (b[:, 3] - b[:, 2])
            cols = []
            for e in np.eye(3):
                p = np.column_stack([x, y, s])
                cols.append((d.forward(p + h * e) - d.forward(p - h * e)) / (2 * h))
            det = np.linalg.det(np.stack(cols, axis=2))
            best = np.minimum(best, det)
    # the Jacobian is affine in (x, y): its minimum over the box is at a corner, which the 9 x 9 grid holds
    np.testing.assert_allclose(d.jacobian_min(s), best, atol=1e-5)


def test_inverse_inside_follows_the_offset_cage():
    d, _ = circle_deformation(radius=30.0, n_keys=60, arc=1.0, cage=1.0, bend_in="u")
    d = d.set_cage(None, (-3.0, 6.0, -1.0, 4.0))
    s = np.full(6, d.length / 2)
    xys = np.column_stack([[-2.9, 5.9, -3.2, 6.2, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0, 3.9, -1.2], s])
    res = d.inverse(d.forward(xys))
    np.testing.assert_allclose(res.xys, xys, atol=1e-6)
    assert res.inside.tolist() == [True, True, False, False, True, False]


def test_output_grid_covers_the_union_of_cages_with_the_curve_on_a_pixel():
    d = straight_deformation(length=20.0, cage=1.0)
    d = d.set_cage(0, (-3.0, 8.0, -1.5, 2.0)).set_cage(1, (-5.0, 2.0, -1.0, 4.2))
    ns, ny, nx = d.output_shape(1.0)
    i0, j0 = d.grid_centre(1.0)
    assert (ns, ny, nx) == (21, 2 + 5 + 1, 5 + 8 + 1)
    assert (i0, j0) == (2, 5)
    base, dv, du = d.slice_geometry(1.0, voxels=False)
    # pixel (i0, j0) of every slice is the curve point; pixel (0, 0) is (x, y) = (-5, -2)
    c, _ = d.sample(np.arange(ns, dtype=float))
    np.testing.assert_allclose(base + i0 * dv + j0 * du, c, atol=1e-9)
    np.testing.assert_allclose(base, d.forward(np.column_stack([np.full(ns, -5.0), np.full(ns, -2.0),
                                                               np.arange(ns, dtype=float)])), atol=1e-9)


def test_offsets_survive_edits_and_serialisation_and_schema_1_reads_as_zero_offsets():
    d, _ = circle_deformation(radius=30.0, n_keys=5, arc=1.0, cage=2.0)
    d = d.set_cage(2, (-1.0, 4.0, -3.0, 1.0))
    assert d.keyframes[2].bounds == (-1.0, 4.0, -3.0, 1.0)
    for e in (d.twist_keyframe(2, 0.3), d.tilt_keyframe(2, 0.1), d.move_keyframe(2, 1.0, 0.5),
              d.resize_keyframe(2, (2.5, 2.0))):
        assert e.keyframes[2].offset == (1.5, -1.0)
    s2 = d.knots[2] + 0.25 * (d.knots[3] - d.knots[2])
    added = d.add_keyframe(s2)
    np.testing.assert_allclose(added.keyframes[3].bounds, d.bounds_at(s2)[0])
    assert Deformation.from_dict(d.to_dict()) == d
    old = d.set_cage(None, (-2.0, 2.0, -2.0, 2.0)).to_dict()
    old["schema"] = "napari-unwind/deformation/1"
    for k in old["keyframes"]:
        del k["offset"]
    back = Deformation.from_dict(old)
    assert np.all(back.offsets == 0) and np.allclose(back.half_extents, 2.0)
    bad = d.to_dict()
    bad["schema"] = "napari-unwind/deformation/1"
    with pytest.raises(InvalidInputError, match="no cage offsets"):
        Deformation.from_dict(bad)
    with pytest.raises(InvalidInputError, match="x_lo < x_hi"):
        d.set_cage(0, (1.0, -1.0, 0.0, 1.0))


def test_an_off_centre_cage_keeps_its_x_sides_through_the_output_grid():
    """An asymmetric cage x in [-2, 6], y in [-1, 3] on a straight rod along axis0, u = axis1, v = axis2: every
    figure below is derived by hand, and the straightened scan is checked voxel by voxel against the scan's own
    coordinates (no forward map). Swapping the x sides anywhere (Keyframe.offset or bounds, set_cage, the grid's
    centre column) moves the straight image's columns by 4 (issue 19)."""
    from napari_unwind.warp import straighten

    u, v, n = [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]  # u x v = n
    frames = np.array([[u, v, n]] * 2)
    d = Deformation.from_keyframes([[5.0, 20.0, 20.0], [25.0, 20.0, 20.0]], frames, 1.0, spacing=(1.0, 1.0, 1.0))
    d = d.set_cage(None, (-2.0, 6.0, -1.0, 3.0))
    for k in d.keyframes:
        assert k.bounds == (-2.0, 6.0, -1.0, 3.0)
        assert k.half_extent == (4.0, 2.0) and k.offset == (2.0, 1.0)
    np.testing.assert_array_equal(d.bounds, [[-2.0, 6.0, -1.0, 3.0]] * 2)
    assert d.extent == (-2.0, 6.0, -1.0, 3.0)
    # rows: y from -1 to 3 (5), columns: x from -2 to 6 (9); the curve (x = y = 0) at row 1, column 2
    assert d.output_shape(1.0) == (21, 5, 9)
    assert d.grid_centre(1.0) == (1, 2)
    # the cage's x_lo side lies 2 voxels to the -axis1 side of the curve, x_hi 6 to the +axis1 side
    np.testing.assert_allclose(d.forward(np.array([[-2.0, 0.0, 3.0], [6.0, 3.0, 3.0]])),
                               [[8.0, 18.0, 20.0], [8.0, 26.0, 23.0]])
    g = np.indices((30, 40, 40), dtype=float)
    scan = (1000 * g[0] + 30 * g[1] + g[2]).astype(np.float32)  # linear: trilinear sampling is exact
    out = np.asarray(straighten(scan, d, spacing=1.0, order=1).data)
    k, i, j = np.indices(out.shape)
    # straight voxel (k, i, j) is x = j - 2, y = i - 1 at axis0 = 5 + k: scan (5 + k, 20 + x, 20 + y)
    want = 1000 * (5 + k) + 30 * (20 + j - 2) + (20 + i - 1)
    np.testing.assert_allclose(out, want, rtol=0, atol=1e-2)
