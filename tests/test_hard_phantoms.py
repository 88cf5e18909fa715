"""Hard phantoms (issue 10, item 3): tight S-bends, coils and helices with their ground truth, and the straightening
of 30 random ones through the public API with the true ends.

The fast tests check the family's own ground truth with independent computations: every preimage of sampled
voxels found by brute force along the stored centreline and frames, the body's Jacobian by finite differences of
``straight_to_bent``, radii of curvature and gaps from the stored arrays. The slow test draws 30 phantoms from a
fixed seed (10 of each kind), runs ``estimate_deformation`` with the true ends and ``straighten``, and asserts on
each the issue's goals that its kind meets (:data:`HELD_BY_KIND`): no folds, centreline RMS <= 1 voxel and length
error <= 2 % on all; coverage >= 0.99 and straightened-mask Dice >= 0.9 on all; residual twist <= 10 degrees on
s-bends and coils. The goal not met yet (one helix's twist) is a figure in benchmarks/RESULTS.md, not an expected
failure.
:func:`measure` is shared with benchmarks/bench_hard_phantoms.py.
"""

from __future__ import annotations

import inspect
import time
import warnings

import numpy as np
import pytest
from scipy import ndimage as ndi
from scipy.spatial import cKDTree

from napari_unwind import datasets as ds
from napari_unwind.errors import InvalidInputError
from napari_unwind.progress import run
from napari_unwind.skeleton import estimate_deformation_iter
from napari_unwind.warp import straighten

try:  # under pytest tests/ is on sys.path; the benchmark imports this module from the repository's root
    from skeleton.test_skeleton import centreline_errors, residual_twist_deg
except ImportError:  # pragma: no cover - the benchmark's path
    from tests.skeleton.test_skeleton import centreline_errors, residual_twist_deg

#: The issue's goals: figure, comparison, limit.
GOALS = (
    ("folds", "<=", 0),
    ("coverage", ">=", 0.99),
    ("rms_vox", "<=", 1.0),
    ("length_err_pct", "<=", 2.0),
    ("twist_max_deg", "<=", 10.0),
    ("dice", ">=", 0.9),
)
#: The goals each kind meets on every one of its phantoms (the slow test asserts these): every goal on every kind.
#: The last one open, the twist of tight helices' thin tails (1026: 10.9 degrees over the last tenth), was the
#: twist's sections losing the half voxel at the working mask's crop faces (8.9 since; 90 of 90 phantoms of seeds
#: 1000, 2000 and 3000 meet every goal, benchmarks/RESULTS.md). Where two turns' cages overlap, a voxel the inverse
#: map gives to the other turn is counted when its own turn's section holds it too (:func:`coverage`).
HELD_BY_KIND = {kind: tuple(g for g, _, _ in GOALS) for kind in ("coil", "s-bend", "helix")}
#: The 30 phantoms of the slow test: kinds in turn, seeds from 1000.
CASES = [(ds.HARD_KINDS[i % 3], 1000 + i) for i in range(30)]


# ------------------------------------------------------------------------------------------------------------------
# measuring one straightening against the phantom's ground truth
# ------------------------------------------------------------------------------------------------------------------
def supports_fold_free() -> bool:
    """Whether estimate_deformation has the fold-free construction (its ``fold_free`` option)."""
    return "fold_free" in inspect.signature(estimate_deformation_iter).parameters


def _tolerance(ph) -> float:
    """How far (physical) the straight s of a voxel may be from its true s and still count as its own place: the
    cage's reach. Parts of a hard phantom closer than this in space are further apart along the body."""
    return float(max(ph.half_extent))


def coverage(ph, dfm, *, n_max: int = 20000) -> float:
    """Fraction of the mask's voxels (a regular subsample of at most ``n_max``) that the straight volume holds at
    their own place along the body: the inverse map puts them inside the cage within :func:`_tolerance` of their
    true s, or, where two turns' cages overlap and the inverse gives the other turn's place, a cross-section of
    the forward map within that tolerance passes through them inside its cage (:func:`_held_near`)."""
    vox = np.argwhere(ph.mask)
    vox = vox[:: max(1, len(vox) // n_max)]
    p = vox * np.asarray(ph.spacing) + np.asarray(dfm.origin)
    inv = dfm.inverse(p)
    s_true = ph.mask_arclength[tuple(vox.T)]
    held = inv.inside & (np.abs(inv.xys[:, 2] - s_true) <= _tolerance(ph))
    rest = np.flatnonzero(~held)
    if len(rest):
        held[rest] = _held_near(dfm, p[rest], s_true[rest], _tolerance(ph), step=0.25 * min(ph.spacing))
    return float(np.mean(held))


def _held_near(dfm, p, s_true, tol, *, step):
    """Whether a cross-section ``s`` within ``tol`` of ``s_true`` passes through each point ``p`` (a sign change of
    ``(p - c(s)) . n(s)`` over a grid of ``step``, its root by the secant) with the point inside that section's
    cage: the forward map's own sections (``sample``, ``bounds_at``), not the inverse."""
    lo, hi = dfm.s_range
    k = int(np.ceil(2 * tol / step)) + 1
    grid = np.clip(s_true[:, None] + np.linspace(-tol, tol, k)[None, :], lo, hi)
    c, fr = dfm.sample(grid.ravel())
    g = np.einsum("mkj,mkj->mk", p[:, None, :] - c.reshape(len(p), k, 3), fr[:, 2].reshape(len(p), k, 3))
    out = np.zeros(len(p), bool)
    for j in range(k - 1):
        cross = (np.sign(g[:, j]) != np.sign(g[:, j + 1])) & ~out & (grid[:, j + 1] > grid[:, j])
        if not cross.any():
            continue
        i = np.flatnonzero(cross)
        s = grid[i, j] - g[i, j] * (grid[i, j + 1] - grid[i, j]) / (g[i, j + 1] - g[i, j])
        cs, fs = dfm.sample(s)
        d = p[i] - cs
        x, y, z = (np.einsum("ij,ij->i", d, fs[:, a]) for a in range(3))
        b = dfm.bounds_at(s)
        ok = (np.abs(z) <= step) & (x >= b[:, 0]) & (x <= b[:, 1]) & (y >= b[:, 2]) & (y <= b[:, 3])
        out[i[ok]] = True
    return out


def straightened_dice(ph, dfm) -> tuple[float, float, float]:
    """Dice of the straightened mask (``straighten``, order 1) against the analytic straight mask, on the
    phantom's straight grid: counting only voxels from the specimen's own place (within :func:`_tolerance` in s),
    and counting every mask voxel; and the share of the straightened mask that came from another part of the
    body (a neighbouring turn in the cage)."""
    m = straighten(ph.mask.astype(np.float32), dfm, order=1)
    # the true s of the nearest mask voxel, so that the order-1 mask's edge keeps its arclength
    nearest = ndi.distance_transform_edt(~ph.mask, sampling=ph.spacing, return_distances=False, return_indices=True)
    arc = straighten(ph.mask_arclength[tuple(nearest)], dfm, order=0, fill=-1e9)
    ds_ = m.spacing[0]
    got = np.asarray(m.data.compute()) >= 0.5
    ns = got.shape[0]
    s_out = m.origin[0] + ds_ * np.arange(ns)
    own = got & (np.abs(np.asarray(arc.data.compute()) - s_out[:, None, None]) <= _tolerance(ph))
    s, y, x = ph.straight_grid()
    idx = np.meshgrid((s - m.origin[0]) / ds_, (y - m.origin[1]) / ds_, (x - m.origin[2]) / ds_, indexing="ij")
    truth = ph.straight_mask

    def dice(a: np.ndarray) -> float:
        b = ndi.map_coordinates(a.astype(np.float32), idx, order=1, cval=0.0) >= 0.5
        return 2.0 * np.count_nonzero(b & truth) / (np.count_nonzero(b) + np.count_nonzero(truth))

    foreign = 1.0 - np.count_nonzero(own) / max(1, np.count_nonzero(got))
    return dice(own), dice(got), foreign


def measure(ph, *, fold_free: bool | None = None) -> dict:
    """Straighten a hard phantom through the public API with its true ends and measure it.

    ``fold_free`` is passed to ``estimate_deformation`` when not None (it must then support it). Figures that the
    result does not report are None (min_jacobian_reported, max_tilt, coverage_reported).
    """
    options = {} if fold_free is None else {"fold_free": fold_free}
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = run(estimate_deformation_iter(ph.mask, (ph.head, ph.tail), spacing=ph.spacing, volume=ph.volume,
                                            **options))
        seconds = time.perf_counter() - t0
        dfm = res.deformation
        folds = dfm.folds()
        dice, dice_all, foreign = straightened_dice(ph, dfm)
    rms, length_err = centreline_errors(ph, dfm)
    err = residual_twist_deg(ph, dfm)
    body = slice(int(0.03 * len(err)), int(0.97 * len(err)))  # the tips carry no orientation (as test_skeleton)
    step = min(ph.spacing) / 10
    jac = dfm.jacobian_min(np.arange(0.0, dfm.length, step))
    return {
        "folds": len(folds),
        "fold_length": float(sum(b - a for a, b in folds)),
        "min_jacobian": float(jac.min()),
        "min_jacobian_reported": getattr(res, "min_jacobian", None),
        "max_tilt": getattr(res, "max_tilt", None),
        "coverage": coverage(ph, dfm),
        "coverage_reported": getattr(res, "coverage", None),
        "rms_vox": rms,
        "length_err_pct": 100.0 * abs(length_err),
        "twist_max_deg": float(err[body].max()),
        "twist_median_deg": float(np.median(err)),
        "dice": dice,
        "dice_all": dice_all,
        "foreign": foreign,
        "keyframes": len(dfm.keyframes),
        "seconds": seconds,
        "warnings": len(caught),
    }


def failed_goals(fig: dict) -> list[str]:
    """The goals a measurement misses, as 'figure value (goal)'."""
    out = []
    for name, op, limit in GOALS:
        v = fig[name]
        if not (v <= limit if op == "<=" else v >= limit):
            out.append(f"{name} {v:.4g} (goal {op} {limit})")
    return out


# ------------------------------------------------------------------------------------------------------------------
# the family's own ground truth
# ------------------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def family():
    """One clean phantom of each kind (seeds chosen to cover the three spacings)."""
    return {kind: ds.hard_fish_phantom(seed, kind=kind, noise=0.0)
            for kind, seed in (("s-bend", 3), ("coil", 4), ("helix", 6))}


def _preimages(ph, pts: np.ndarray, reach: float) -> list[tuple[int, np.ndarray]]:
    """Every (point index, (x, y, s)) with ``c(s) + x u + y v = p`` within ``reach`` of the curve, by brute force:
    sign changes of ``(p - c_k) . n_k`` along the stored dense centreline, refined by linear interpolation."""
    c, fr, s = ph.centerline_physical, ph.frames, ph.arclength
    out = []
    for b0 in range(0, len(pts), 2000):
        p = pts[b0:b0 + 2000]
        d = p[:, None, :] - c[None]
        g = np.einsum("pkj,kj->pk", d, fr[:, 2])
        i, k = np.nonzero((np.sign(g[:, :-1]) != np.sign(g[:, 1:])) & (np.linalg.norm(d[:, :-1], axis=2) <= reach))
        lam = g[i, k] / (g[i, k] - g[i, k + 1])
        ci = (1 - lam)[:, None] * c[k] + lam[:, None] * c[k + 1]
        u = (1 - lam)[:, None] * fr[k, 0] + lam[:, None] * fr[k + 1, 0]
        v = (1 - lam)[:, None] * fr[k, 1] + lam[:, None] * fr[k + 1, 1]
        r = p[i] - ci
        xys = np.column_stack([np.sum(r * u, axis=1), np.sum(r * v, axis=1), (1 - lam) * s[k] + lam * s[k + 1]])
        out.extend(zip(b0 + i, xys))
    return out


@pytest.mark.parametrize("kind", ds.HARD_KINDS)
def test_mask_is_the_exact_image_of_the_straight_body(family, kind):
    """Each voxel is in the mask iff one of its preimages lies in the straight body (away from a band of one
    straight voxel, diagonals included, around the body's surface, where the grids' rounding decides), and its
    stored arclength is that preimage's s."""
    ph = family[kind]
    sp = np.asarray(ph.spacing)
    rng = np.random.default_rng(0)
    near = ndi.binary_dilation(ph.mask, iterations=4)
    vox = np.argwhere(near)
    vox = vox[rng.choice(len(vox), size=min(len(vox), 30000), replace=False)]
    truth = ph.straight_mask
    cube = np.ones((3, 3, 3), bool)
    band = ndi.binary_dilation(truth, cube) & ~ndi.binary_erosion(truth, cube)
    d = ph.straight_spacing
    ns, ny, nx = ph.straight_shape
    expect = np.zeros(len(vox), bool)
    unsure = np.zeros(len(vox), bool)
    arc = np.full(len(vox), np.nan)
    for i, (x, y, s) in _preimages(ph, vox * sp, float(np.hypot(*ph.half_extent)) + 2 * sp.max()):
        k, yi, xj = round(s / d), round(y / d + (ny - 1) / 2), round(x / d + (nx - 1) / 2)
        if not (0 <= k < ns and 0 <= yi < ny and 0 <= xj < nx):
            unsure[i] |= -d <= s <= ph.length + d  # just past the ends, where the rounding of s decides
            continue
        unsure[i] |= band[k, yi, xj]
        if truth[k, yi, xj]:
            expect[i] = True
            arc[i] = s
    got = ph.mask[tuple(vox.T)]
    sure = ~unsure
    assert sure.mean() > 0.25
    assert np.count_nonzero(got[sure] != expect[sure]) == 0, (
        f"{np.count_nonzero(got[sure] & ~expect[sure])} voxels in the mask without a preimage in the body, "
        f"{np.count_nonzero(~got[sure] & expect[sure])} with one but not in the mask")
    both = got & expect & sure
    np.testing.assert_allclose(ph.mask_arclength[tuple(vox[both].T)], arc[both], atol=0.5 * d)
    assert np.all(np.isnan(ph.mask_arclength[~ph.mask]))


@pytest.mark.parametrize("kind", ds.HARD_KINDS)
def test_the_body_never_folds(family, kind):
    """The Jacobian of the true map, by central differences of straight_to_bent, stays positive over the body
    (the generator keeps it >= 0.15), while the cage of the tight ones folds."""
    ph = family[kind]
    s, y, x = ph.straight_grid()
    k, i, j = np.nonzero(ph.straight_mask)
    keep = (s[k] > 1.0) & (s[k] < ph.length - 1.0)
    p = np.column_stack([x[j], y[i], s[k]])[keep][::3]
    e = 1e-3
    cols = [(ph.straight_to_bent(p + e * a, physical=True) - ph.straight_to_bent(p - e * a, physical=True)) / (2 * e)
            for a in np.eye(3)]
    det = np.linalg.det(np.stack(cols, axis=2))
    assert det.min() > 0.1, f"the body's Jacobian reaches {det.min():.3f}"
    assert det.min() == pytest.approx(ph.info["min_body_jacobian"], abs=0.08)


def test_s_bend_is_as_tight_as_promised(family):
    """Radius of curvature (finite differences of the stored centreline) against the body's half height (read on
    the straight mask's ventral side): down to 0.8-1.2 half heights, with the body bent sideways there."""
    ph = family["s-bend"]
    c, s = ph.centerline_physical, ph.arclength
    t = np.gradient(c, s, axis=0)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    kv = np.gradient(t, s, axis=0)
    kap = np.linalg.norm(kv, axis=1)
    ss, yy, _ = ph.straight_grid()
    ventral = np.where(ph.straight_mask[:, :, (ph.straight_shape[2] - 1) // 2] & (yy[None, :] <= 0), -yy[None, :], 0)
    half = np.interp(s, ss, ventral.max(axis=1) + 0.5 * ph.straight_spacing)
    inner = (s > 0.1 * ph.length) & (s < 0.9 * ph.length)
    ratio = 1.0 / np.maximum(kap, 1e-12) / half
    k = np.flatnonzero(inner)[np.argmin(ratio[inner])]
    assert 0.75 <= ratio[k] <= 1.25
    lateral = abs(kv[k] @ ph.frames[k, 0]) / kap[k]
    assert lateral >= np.cos(np.radians(20))
    assert ratio[k] == pytest.approx(ph.info["radius_to_half_height"], rel=0.1)


@pytest.mark.parametrize("kind", ["coil", "helix"])
def test_neighbouring_turns_pass_within_one_body_width(family, kind):
    """Surface voxels of parts further apart along the body than pi times its reach (from mask_arclength) come
    within one body width of each other, and no closer than two voxels."""
    ph = family[kind]
    sp = np.asarray(ph.spacing)
    edge = ph.mask & ~ndi.binary_erosion(ph.mask)
    vox = np.argwhere(edge)
    pts, s = vox * sp, ph.mask_arclength[tuple(vox.T)]
    width = ph.info["body_width"]
    _, y, x = ph.straight_grid()
    _, i, j = np.nonzero(ph.straight_mask)
    reach = np.hypot(x[j], y[i]).max()  # of the body from its centreline
    pairs = cKDTree(pts).query_pairs(1.5 * width, output_type="ndarray")
    far = np.abs(s[pairs[:, 0]] - s[pairs[:, 1]]) > np.pi * reach
    assert far.any(), "no two turns come within 1.5 body widths"
    dist = np.linalg.norm(pts[pairs[far, 0]] - pts[pairs[far, 1]], axis=1)
    assert 2.0 * sp.max() <= dist.min() <= width
    assert ph.info["turns"] > 1.15


def test_twist_spacing_and_size_of_the_family(family):
    for ph in family.values():
        assert abs(ph.twist[-1]) <= np.radians(200.0) + 1e-9
        assert ph.twist[-1] == pytest.approx(np.radians(ph.info["twist_deg"]))
        assert max(ph.shape) <= 160
        assert ph.spacing in ds.HARD_SPACINGS
        assert ph.name == f"hard-{ph.info['kind']}-{ph.seed}"
    assert {ph.spacing for ph in family.values()} == set(ds.HARD_SPACINGS)


def test_same_seed_same_phantom_with_noise_and_a_drawn_kind(family):
    noisy = ds.hard_fish_phantom(4, kind="coil")
    clean = family["coil"]
    np.testing.assert_array_equal(noisy.mask, clean.mask)
    np.testing.assert_array_equal(noisy.straight_mask, clean.straight_mask)
    assert np.std(noisy.volume.astype(float) - clean.volume) == pytest.approx(40.0, rel=0.1)
    drawn = ds.hard_fish_phantom(7, noise=0.0, spacing=2.0)
    assert drawn.info["kind"] in ds.HARD_KINDS and drawn.spacing == (2.0, 2.0, 2.0)


def test_an_overlapping_body_is_detected():
    """The renderer counts voxels inside the body through two feet: a helix whose turns are closer than the body's
    height has them, the same helix with room between its turns has none."""
    body = ds._Fish(120.0, 6.0, 1.0, 2.0)

    def helix(pitch):
        c, rho = pitch / (2 * np.pi), 12.0
        t1 = 120.0 / np.hypot(rho, c)
        fn = lambda t: np.column_stack([c * t + 30, rho * np.cos(t) + 30, rho * np.sin(t) + 30])  # noqa: E731
        return ds._Curve(fn, 0.0, t1, h=0.25, length=120.0)

    shape = (110, 60, 60)
    assert ds._render_pieces(shape, helix(3.0), body, (1.0, 1.0, 1.0))[3] > 100
    assert ds._render_pieces(shape, helix(14.0), body, (1.0, 1.0, 1.0))[3] == 0


@pytest.mark.parametrize(("kwargs", "match"), [
    (dict(seed=-1), "seed must be a non-negative integer"),
    (dict(seed=1.5), "seed must be a non-negative integer"),
    (dict(kind="spiral"), "kind must be one of s-bend, coil, helix"),
    (dict(max_tries=0), "max_tries must be a positive integer"),
    (dict(noise=-3), "noise must be finite and zero or positive"),
    (dict(spacing=(1, 0, 1)), "spacing"),
])
def test_bad_input(kwargs, match):
    with pytest.raises(InvalidInputError, match=match):
        ds.hard_fish_phantom(**kwargs)


# ------------------------------------------------------------------------------------------------------------------
# the goals, on 30 random phantoms
# ------------------------------------------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize(("kind", "seed"), CASES, ids=[f"{k}-{s}" for k, s in CASES])
def test_hard_phantom_is_straightened_to_the_goals(kind, seed):
    ph = ds.hard_fish_phantom(seed, kind=kind)
    fig = measure(ph, fold_free=True if supports_fold_free() else None)
    failed = failed_goals(fig)
    shown = ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in fig.items())
    # The goals each kind meets on all its phantoms are asserted (HELD_BY_KIND); the ones it does not meet yet are
    # not in the suite (no expected failures): their distribution is in benchmarks/RESULTS.md
    # (bench_hard_phantoms) and the issue notes.
    held = [f for f in failed if f.split()[0] in HELD_BY_KIND[kind]]
    assert not held, f"{ph.name} {ph.spacing}: missed {'; '.join(held)} | {shown}"
