"""GLSL templates of the straight view (vispy ``Function`` code filling the volume shader's ``$get_data`` slot).

The ray caster walks the straight box; ``texcoord`` is a point of that box in texture units,
``texcoord = (index + 0.5) / box`` with ``index = (j, i, k)`` (column along u, row along v, slice along s). The
per-slice table (``Deformation.slice_geometry(voxels=True)``: base, dv, du in scan voxels, axis order 0, 1, 2) is a
float texture of 3 rows x Ns texels (rgb32f, linear filtering, never clamped to [0, 1]): row 0 base, row 1 dv, row 2 du.
The texture's linear filter interpolates it along s (rows sampled at their texel centres), so the scan
is sampled at ``p = base(k) + i dv(k) + j du(k)``, the
straight voxel's scan coordinate, exactly as :func:`napari_unwind.warp.straighten` samples it at whole ``k``.

A sample is valid iff ``0 <= p <= n - 1`` on every axis (the CPU's scipy ``"constant"`` rule); an invalid one, or
a point outside the table's slices, returns ``$fill`` (raw 0: never raises a MIP above the CPU's fill).
``$texture`` is the node's scan texture, set by vispy's ``_build_interpolation``; the texture's own filter
(linear or nearest) is napari's interpolation setting, so nearest gives voxel ``floor(p + 0.5)`` as order 0 does.
"""
from __future__ import annotations

STRAIGHT_LOOKUP = """
vec4 straight_lookup(vec3 texcoord) {
    vec3 q = texcoord * $box - 0.5;            // (j, i, k) in straight voxels
    float ns = $nslices;
    if (q.z < -0.5 || q.z > ns - 0.5) {
        return vec4($fill);
    }
    // linear filtering of the (never clamped) float table interpolates the frames along s: 3 fetches a sample
    float x = (clamp(q.z, 0.0, ns - 1.0) + 0.5) / ns;
    vec3 base = texture2D($frames, vec2(x, 0.5 / 3.0)).rgb;
    vec3 dv = texture2D($frames, vec2(x, 1.5 / 3.0)).rgb;
    vec3 du = texture2D($frames, vec2(x, 2.5 / 3.0)).rgb;
    vec3 p = base + q.y * dv + q.x * du;       // scan voxel (axis0, axis1, axis2)
    vec3 n = $scan_shape;                      // (n0, n1, n2)
    const float eps = 1e-4;
    if (any(lessThan(p, vec3(-eps))) || any(greaterThan(p, n - 1.0 + eps))) {
        return vec4($fill);
    }
    return texture3D($texture, (p.zyx + 0.5) / n.zyx);
}
"""
