"""The real scans of ../shared/data as other users would hand them over (issue 23: vessels and masks beyond fish).

    .venv/bin/python -m benchmarks.bench_real_variants

Each case is made here from the aorta CT and its expert mask, or the spine MRI and its cord mask, and run through
the one pipeline (``pipeline.run``, as ``unwind run --mask`` runs it, ends suggested unless said): a label map in
place of the mask (the aorta as label 1, every other voxel over 300 HU as label 2), with and without its label;
the scan flipped along axis 0; every other slice (3 mm along axis 0; the spine 2 mm along axis 1); the scan and
mask cut at axis0 = 60, so that the arch is outside and the vessel is in two parts, with the ends suggested and as
a chain through both parts. Prints per case the status, coverage, the roll against the rotation-minimising frames
(total and the largest change within 10 mm, as ``bench_roll``), whether the twist was estimated, and the reason.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
from scipy import ndimage as ndi

from napari_unwind.io import Volume, open_volume
from napari_unwind.pipeline import run
from napari_unwind.session import Endpoints
from napari_unwind.skeleton import suggest_endpoints
from tests.test_real_scans_run import _roll_against_rotation_minimising

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"


def _vol(data: np.ndarray, like: Volume, spacing: tuple | None = None) -> Volume:
    return Volume(np.ascontiguousarray(data), spacing=spacing or like.spacing, origin=like.origin, unit=like.unit)


def _chain(mask: np.ndarray, spacing: tuple) -> Endpoints:
    """A chain through the mask's separate parts, each from its suggested ends, in the order and directions whose
    gaps between consecutive parts are shortest (two parts here)."""
    labels, n = ndi.label(mask, np.ones((3, 3, 3)))
    ends = []
    for i in range(1, n + 1):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            a, b = suggest_endpoints(labels == i, spacing=spacing)
        ends.append((np.asarray(a, float), np.asarray(b, float)))
    (a1, b1), (a2, b2) = ends[:2]
    options = [((a1, b1), (a2, b2)), ((b1, a1), (a2, b2)), ((a1, b1), (b2, a2)), ((b1, a1), (b2, a2))]
    best = min(options, key=lambda o: np.linalg.norm(o[0][1] - o[1][0]))
    chain = tuple((tuple(p), tuple(q)) for p, q in best)
    return Endpoints(head=chain[0][0], tail=chain[-1][1], chain=chain)


def cases() -> list[tuple[str, Volume, Volume, dict]]:
    ct, aorta = open_volume(DATA / "aorta_ct.nrrd"), open_volume(DATA / "aorta_ct_aorta_mask.nrrd")
    mri, cord = open_volume(DATA / "spine_t2.nrrd"), open_volume(DATA / "spine_t2_cord_mask.nrrd")
    a, m = np.asarray(ct.data), np.asarray(aorta.data)
    s, c = np.asarray(mri.data), np.asarray(cord.data)
    labels = m.astype(np.uint8)
    labels[(a > 300) & (m == 0)] = 2
    sp = ct.spacing
    cut_m = m[:60]
    out = [
        ("aorta, expert mask", ct, _vol(m, ct), {}),
        ("aorta, label map (no label)", ct, _vol(labels, ct), {}),
        ("aorta, label map, mask_label=1", ct, _vol(labels, ct), {"mask_label": 1}),
        ("aorta flipped along axis 0", _vol(a[::-1], ct), _vol(m[::-1], ct), {}),
        ("aorta, 3 mm slices along axis 0", _vol(a[::2], ct, (2 * sp[0], sp[1], sp[2])),
         _vol(m[::2], ct, (2 * sp[0], sp[1], sp[2])), {}),
        ("aorta cut at axis0 = 60, ends suggested", _vol(a[:60], ct), _vol(cut_m, ct), {}),
        ("aorta cut at axis0 = 60, chain through both parts", _vol(a[:60], ct), _vol(cut_m, ct),
         {"endpoints": _chain(cut_m > 0, sp)}),
        ("spinal cord, cord mask", mri, cord, {}),
        ("spinal cord, 2 mm along axis 1", _vol(s[:, ::2], mri, (mri.spacing[0], 2 * mri.spacing[1], mri.spacing[2])),
         _vol(c[:, ::2], mri, (mri.spacing[0], 2 * mri.spacing[1], mri.spacing[2])), {}),
    ]
    return out


def main() -> None:
    for name, scan, mask, kw in cases():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            r = run(scan, mask=mask, **kw)
        roll, s = _roll_against_rotation_minimising(r.skeleton.deformation)
        k = int(round(10.0 / 0.5))
        local = np.abs(roll[k:] - roll[:-k]) if len(roll) > k else np.zeros(1)
        labels = [w for w in r.warnings if "labels" in w]
        print(f"{name}: {r.status}, coverage {r.coverage:.3f}, roll {roll.max() - roll.min():.1f} deg in all, "
              f"{local.max():.1f} within 10 mm; twist {r.skeleton.twist_source}"
              + (f"; {labels[0][:80]}..." if labels else "")
              + (f"; reason: {r.reason[:200]}" if r.reason else ""), flush=True)


if __name__ == "__main__":
    main()
