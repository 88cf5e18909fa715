"""The average straight specimen (issue 24 item 3) on a seeded family whose average is known.

The family: one template fish in straight space (a tapered elliptic body, a dorsal fin on +y over the middle, a
bright spine rod above the axis), each member a copy scaled in length and across by z, rolled about s by theta,
shifted across, with its own grey-value gain and offset and a little noise. The average must be the template
(normalised, rolled as the median member, centred on its own centroid), computed here from the template's formula,
never through the code under test; the rolls must be the members' own, and a member that is not of the family (the
template upside down) must stand out by its residual.
"""
from __future__ import annotations

import numpy as np
import pytest

from napari_unwind.average import average
from napari_unwind.errors import InvalidInputError
from napari_unwind.io import Volume

NS0, NY0 = 120, 41


def template(t, y, x):
    """Grey value of the template at length fraction t and cross-section (y, x) (template pixels)."""
    a = 10.0 * np.clip(np.sin(np.pi * t), 0, 1) ** 0.6 + 1.0
    b = 0.6 * a
    v = np.full(np.broadcast(t, y, x).shape, 100.0)
    body = (y / a) ** 2 + (x / b) ** 2 <= 1.0
    v[body] = 1000.0
    fin = (y >= a) & (y <= a + 6.0) & (np.abs(x) <= 1.5) & (t >= 0.3) & (t <= 0.6)
    v[fin] = 900.0
    spine = (y - 0.4 * a) ** 2 + x ** 2 <= 1.5 ** 2
    v[spine & body] = 2500.0
    return v


def member(z, theta, shift, gain, offset, rng, flip=False):
    ns, n = int(round(NS0 * z)), int(round(NY0 * z)) | 1
    k, y, x = np.indices((ns, n, n), dtype=float)
    c = (n - 1) / 2
    yc, xc = (y - c - shift[0]) / z, (x - c - shift[1]) / z
    th = np.radians(theta)
    yr, xr = np.cos(th) * yc + np.sin(th) * xc, -np.sin(th) * yc + np.cos(th) * xc   # the template turned by -theta
    if flip:
        yr = -yr
    v = template(k / (ns - 1), yr, xr) * gain + offset + rng.normal(0, 10 * gain, (ns, n, n))
    return Volume(v.astype(np.float32), spacing=(0.5, 0.5, 0.5), unit="mm")


@pytest.fixture(scope="module")
def family():
    rng = np.random.default_rng(24)
    thetas = np.array([-35.0, -20.0, -8.0, 0.0, 12.0, 25.0, 40.0])
    rng.shuffle(thetas)
    zs = rng.uniform(0.8, 1.25, len(thetas))
    zs[np.argsort(zs)[len(zs) // 2]] = 1.0            # the member of median length is the template's size
    members = [member(z, th, rng.uniform(-3, 3, 2), rng.uniform(0.5, 2.0), rng.uniform(0, 300), rng)
               for z, th in zip(zs, thetas, strict=True)]
    return members, thetas, zs


def truth_on(shape, roll, centre_offset):
    """The template on the average's grid: scaled to its length (every member is scaled by its length's factor),
    rolled by ``roll`` like the median member, centred on its centroid (template pixels)."""
    n, ny, nx = shape
    zoom = (n - 1) / (NS0 - 1)
    k, y, x = np.indices(shape, dtype=float)
    yc, xc = (y - (ny - 1) / 2) / zoom + centre_offset[0], (x - (nx - 1) / 2) / zoom + centre_offset[1]
    th = np.radians(roll)
    yr, xr = np.cos(th) * yc + np.sin(th) * xc, -np.sin(th) * yc + np.cos(th) * xc
    return template(k / (n - 1), yr, xr)


def test_the_average_of_a_family_is_its_template_and_the_rolls_are_recovered(family):
    members, thetas, zs = family
    res = average(members)
    n = int(np.median([m.shape[0] for m in members]))
    assert res.mean.shape[0] == n and res.spacing == 0.5 and res.unit == members[0].unit
    # rolls: the members' own, relative to the median member, to 1.5 degrees (either sign convention)
    rel = thetas - np.median(thetas)
    assert min(np.abs(res.roll - rel).max(), np.abs(res.roll + rel).max()) < 1.5, (res.roll, rel)
    assert np.allclose(res.scale * (np.array([m.shape[0] for m in members]) - 1), n - 1)
    # the template's centroid (normalised weight, over the mean cross-section): the average is centred on it
    k, y, x = np.indices((NS0, NY0, NY0), dtype=float)
    t = template(k / (NS0 - 1), y - 20, x - 20)
    w = np.clip((t - np.median(t)) / (np.percentile(t, 99) - np.median(t)), 0, None).mean(axis=0)
    yy, xx = np.indices(w.shape, dtype=float)
    offset = np.array([(w * yy).sum() / w.sum() - 20, (w * xx).sum() / w.sum() - 20])
    truth = truth_on(res.mean.shape, np.median(thetas), offset)
    corr = np.corrcoef(truth.ravel(), res.mean.ravel())[0, 1]
    assert corr > 0.97, corr
    assert np.corrcoef(truth.ravel(), res.median.ravel())[0, 1] > 0.97
    assert (res.correlation > 0.9).all(), res.correlation
    # the std is small where every member agrees (deep background, far from the body)
    assert np.median(res.std[:, :3, :3]) < 0.1


def test_a_member_not_of_the_family_stands_out_by_its_residual(family):
    members, thetas, zs = family
    odd = member(1.0, 0.0, (0.0, 0.0), 1.0, 0.0, np.random.default_rng(1), flip=True)   # upside down
    res = average([*members, odd])   # upside down is a turn of 180 degrees: beyond the search (90 each way)
    others = res.correlation[:-1]
    assert res.correlation[-1] < others.min() - 0.05, res.correlation
    assert res.rms[-1] > res.rms[:-1].max()
    rows = res.table()
    assert len(rows) == len(members) + 1 and set(rows[0]) >= {"name", "roll_deg", "rms", "correlation"}


def test_what_cannot_be_averaged_is_refused_in_one_line(family):
    members, _, _ = family
    with pytest.raises(InvalidInputError, match="at least 2"):
        average(members[:1])
    with pytest.raises(InvalidInputError, match="isotropic"):
        average([members[0], Volume(members[1].data, spacing=(1.0, 0.5, 0.5), unit="mm")])
    with pytest.raises(InvalidInputError, match="units"):
        average([members[0], Volume(members[1].data, spacing=(0.5, 0.5, 0.5), unit="um")])
    with pytest.raises(InvalidInputError, match="scale"):
        average(members, scale="size")


@pytest.mark.parametrize("count", [2, 3, 5, 8, 13, 20, 33])
def test_the_voxel_statistics_are_numpys(count):
    """The median by a sorting network (and the mean, std and residual sums of the same loop) against numpy, for
    odd and even counts, with ties."""
    from napari_unwind.average import _sorting_network, _voxel_stats

    rng = np.random.default_rng(count)
    stack = rng.normal(size=(count, 3, 257)).astype(np.float32)
    stack[:, :, :40] = np.round(stack[:, :, :40])                        # ties
    mean, median, std = (np.empty((3, 257), np.float32) for _ in range(3))
    sums, msums = np.zeros((count, 4)), np.zeros(2)
    _voxel_stats(stack, _sorting_network(count), mean, median, std, sums, msums)
    np.testing.assert_array_equal(median, np.median(stack, axis=0))
    np.testing.assert_allclose(mean, stack.mean(axis=0, dtype=np.float64), rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(std, stack.std(axis=0, dtype=np.float64), rtol=1e-5, atol=1e-7)
    x, m = stack.reshape(count, -1).astype(np.float64), mean.ravel().astype(np.float64)
    np.testing.assert_allclose(sums, np.stack([((x - m) ** 2).sum(1), x.sum(1), (x * x).sum(1), x @ m], axis=1),
                               rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(msums, [m.sum(), (m * m).sum()], rtol=1e-12)
