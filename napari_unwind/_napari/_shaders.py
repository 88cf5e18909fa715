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

# The same map with the table in a uniform array (``u_unwind_frames[3 k + 0, 1, 2]`` = base, dv, du of slice k),
# interpolated along s by hand. On Mesa llvmpipe the three float-texture fetches a sample cost ~4x napari's own
# sampling (measured 0.21 s against 0.06 s a frame, 256^3 scan, 712x749 canvas); indexing a uniform array costs
# about half of that. The array's size is fixed at compile time: CAPACITY slices (>= Ns, rounded up so that edits
# changing the length rarely recompile), bounded by GL_MAX_FRAGMENT_UNIFORM_VECTORS.
FRAMES_UNIFORM = "u_unwind_frames"


def uniform_lookup(capacity: int) -> str:
    """:data:`STRAIGHT_LOOKUP` reading the frame table from ``uniform vec3 u_unwind_frames[3 * capacity]``."""
    head = f"uniform vec3 {FRAMES_UNIFORM}[{3 * int(capacity)}];\nvec4 straight_lookup"
    code = STRAIGHT_LOOKUP.replace("vec4 straight_lookup", head, 1)
    fetch = code[code.index("    // linear filtering"):code.index("    vec3 p = base")]
    by_hand = """    float kf = clamp(q.z, 0.0, ns - 1.0);
    int k0 = int(floor(kf));
    int k1 = min(k0 + 1, int(ns) - 1);
    float t = kf - float(k0);
    vec3 base = mix(u_unwind_frames[3 * k0], u_unwind_frames[3 * k1], t);
    vec3 dv = mix(u_unwind_frames[3 * k0 + 1], u_unwind_frames[3 * k1 + 1], t);
    vec3 du = mix(u_unwind_frames[3 * k0 + 2], u_unwind_frames[3 * k1 + 2], t);
"""
    return code.replace(fetch, by_hand)
