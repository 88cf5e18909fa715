"""Every private napari and vispy access of the straight view, in one place.

napari offers no public hook into its volume visual's sampling, so the straight view (``_straight_view.py``) reaches
into napari 0.9's vispy layer and vispy's ``VolumeVisual``. Everything that does so is here, and the module refuses
to import against a napari minor version other than the pinned one (pyproject: ``napari>=0.9.2,<0.10``), since any
of these names may change without notice.

The private names used:

- ``viewer.window._qt_viewer.canvas.layer_to_visual[layer]`` -> napari's vispy layer;
- ``viewer.window._qt_window`` -> the main window (its Close event: :func:`main_window`, ``_gc.py``);
- ``vispy_layer._layer_node._volume_node`` -> the 3D node (a vispy ``VolumeVisual``);
- vispy's ``gloo.Program._parse_variables_from_code``, ``_shaders``, ``_code_variables`` and
  ``_process_pending_variables`` (memoised: :func:`memoise_program_parse`);
- on that node: ``_interpolation_fun`` (the Function templates behind the ``$get_data`` slot), ``_texture`` (the scan
  texture), ``_need_interpolation_update``, ``_vol_shape``, ``_need_vertex_update``, ``shared_program['u_shape']``.
"""
from __future__ import annotations

from typing import Any

import napari
import numpy as np
from vispy.visuals.volume import VolumeVisual

PINNED_MINOR = (0, 9)


def _check_version(version: str) -> None:
    try:
        minor = tuple(int(p) for p in version.split(".")[:2])
    except ValueError:
        minor = None
    if minor != PINNED_MINOR:
        raise ImportError(
            f"napari-unwind's straight view uses private napari APIs checked against napari "
            f"{PINNED_MINOR[0]}.{PINNED_MINOR[1]}.x, but napari {version} is installed; install "
            f"'napari>={PINNED_MINOR[0]}.{PINNED_MINOR[1]}.2,<{PINNED_MINOR[0]}.{PINNED_MINOR[1] + 1}'"
        )


_check_version(napari.__version__)


def _set(node: Any, key: str, value: Any) -> None:
    """Set an attribute vispy's frozen visual does not know (its __setattr__ refuses new names)."""
    object.__setattr__(node, key, value)


def volume_node(viewer: Any, layer: Any) -> VolumeVisual:
    """The vispy ``VolumeVisual`` that draws ``layer`` in 3D."""
    vispy_layer = viewer.window._qt_viewer.canvas.layer_to_visual[layer]
    node = vispy_layer._layer_node._volume_node
    if not isinstance(node, VolumeVisual):
        raise RuntimeError(f"napari's 3D node for {layer.name!r} is a {type(node).__name__}, not a VolumeVisual")
    return node


def scene_canvas(viewer: Any) -> Any:
    """The vispy SceneCanvas of the viewer (for ``render()``, which returns rows top-down)."""
    return viewer.window._qt_viewer.canvas._scene_canvas


def scan_texture(node: VolumeVisual) -> Any:
    """The node's 3D texture (holds the scan level; uploaded by napari's set_data only)."""
    return node._texture


def install(node: VolumeVisual, lookup: Any, box_zyx: tuple[int, int, int]) -> None:
    """Make ``node`` sample through ``lookup`` (a vispy Function with a ``$texture`` slot) over a ray box of shape
    ``box_zyx``, and keep it so across napari's later ``set_data`` calls (which reset the box to the texture's)."""
    if not hasattr(node, "_unwind_saved"):
        _set(node, "_unwind_saved", dict(node._interpolation_fun))
    node._interpolation_fun["linear"] = lookup
    node._interpolation_fun["nearest"] = lookup
    _set(node, "_unwind_box", tuple(int(v) for v in box_zyx))

    def set_data(vol: Any, clim: Any = None, copy: bool = True) -> None:
        VolumeVisual.set_data(node, vol, clim=clim, copy=copy)
        box = getattr(node, "_unwind_box", None)
        if box is not None:
            _apply_box(node, box)

    _set(node, "set_data", set_data)
    _apply_box(node, node._unwind_box)
    node._need_interpolation_update = True
    node.update()


def set_box(node: VolumeVisual, box_zyx: tuple[int, int, int]) -> None:
    """Change the ray box (the straight shape changes with an edit's arclength): a uniform and 8 vertices."""
    _set(node, "_unwind_box", tuple(int(v) for v in box_zyx))
    _apply_box(node, node._unwind_box)
    node.update()


def _apply_box(node: VolumeVisual, box: tuple[int, int, int]) -> None:
    node.shared_program["u_shape"] = (box[2], box[1], box[0])
    if node._vol_shape != box:
        node._vol_shape = box
        node._need_vertex_update = True


def uninstall(node: VolumeVisual) -> None:
    """Restore vispy's own sampling and the texture's box (the bent view of the same texture)."""
    saved = getattr(node, "_unwind_saved", None)
    if saved is None:
        return
    node._interpolation_fun.update(saved)
    _set(node, "_unwind_box", None)
    try:
        del node.set_data  # the instance wrapper; back to VolumeVisual.set_data
    except AttributeError:
        pass
    data = node._last_data
    if data is not None:
        _apply_box(node, tuple(data.shape[:3]))
    node._need_interpolation_update = True
    node.update()


def max_3d_texture_size() -> int | None:
    """GL_MAX_3D_TEXTURE_SIZE of the current GL (napari's cached query; 2048 on Mesa llvmpipe)."""
    from napari._vispy.utils.gl import get_max_texture_sizes

    return get_max_texture_sizes()[1]


def gl_extensions() -> str:
    """The GL extension string (napari's cached query)."""
    from napari._vispy.utils.gl import get_gl_extensions

    return get_gl_extensions()


def max_fragment_uniform_vectors() -> int | None:
    """GL_MAX_FRAGMENT_UNIFORM_VECTORS of the current GL (vispy's gloo has no name for it)."""
    from napari._vispy.utils.gl import _opengl_context
    from vispy.gloo import gl

    with _opengl_context():
        try:
            value = gl.glGetParameter(0x8DFD)
        except Exception:
            return None
    return int(value) if value else None


def set_uniform(node: VolumeVisual, name: str, value: Any) -> None:
    """Set a uniform array the straight view's Function declares itself.

    vispy stores a uniform array raveled and re-applies it that way when the program's code changes (napari
    rebuilds it on a rendering or interpolation change); its own shape check then refuses it ("needs shape (n, 3)
    not (1, 3n)"), the re-apply stops half way and the visual stops drawing. So the value is kept here and the
    stored copies are put back in 2D before every draw (a wrapper of the node's ``_prepare_draw``).
    """
    value = np.ascontiguousarray(value, dtype=np.float32)
    arrays = node.__dict__.get("_unwind_uniforms")
    if arrays is None:
        arrays = {}
        _set(node, "_unwind_uniforms", arrays)

        def prepare_draw(view: Any) -> None:
            _fix_uniform_arrays(node)
            VolumeVisual._prepare_draw(node, view)

        _set(node, "_prepare_draw", prepare_draw)
    arrays[name] = value
    node.shared_program[name] = value
    _fix_uniform_arrays(node)


def _fix_uniform_arrays(node: VolumeVisual) -> None:
    """Called before each draw, before vispy flushes its queued GL commands. Besides the 2D copies: vispy's GL
    side computes a uniform array's element count only when it first looks the uniform's location up, and later
    sets only element 0 (vispy 0.15 ``GlirProgram.set_uniform``); dropping the cached location makes the next set
    look it up again, with the full count."""
    from vispy.gloo import get_current_canvas

    canvas = get_current_canvas()
    objects = getattr(getattr(canvas.context.shared, "parser", None), "_objects", {}) if canvas is not None else {}
    for name, value in node.__dict__.get("_unwind_uniforms", {}).items():
        for program in list(node.shared_program._programs.values()):
            for store in (program._user_variables, program._pending_variables):
                if name in store:
                    store[name] = value
            glir_program = objects.get(program.id)
            if glir_program is not None:
                glir_program._handles.pop(name, None)


# -- a coarse 3D texture for a large Image layer (``_layers.ImageIn3D``) -------------------------------------------
# napari's vispy layer hands the layer's 3D slice to ``downsample_texture(data, max_size)`` just before it uploads it
# to the volume node; napari itself strides there when a side exceeds GL_MAX_3D_TEXTURE_SIZE and records the stride
# in the layer's ``tile2data`` transform (which each new slice resets to the identity, so 2D is untouched). The
# names used: ``canvas.layer_to_visual[layer]``, its ``downsample_texture`` and ``_on_matrix_change`` /
# ``_on_data_change``, and ``layer._transforms['tile2data']`` (an Affine), ``layer._slice_input``.
def vispy_layer(viewer: Any, layer: Any) -> Any:
    """napari's vispy layer of ``layer`` (KeyError / AttributeError when the viewer has no canvas for it)."""
    return viewer.window._qt_viewer.canvas.layer_to_visual[layer]


def ndisplay_of(layer: Any) -> int:
    """The number of displayed dimensions of the layer's current slice (napari's own, not the viewer's dims)."""
    return int(layer._slice_input.ndisplay)


def coarse_3d_texture(viewer: Any, layer: Any, coarsen: Any) -> Any:
    """From now on napari uploads ``coarsen(data)`` to ``layer``'s 3D volume node instead of its 3D slice ``data``.

    ``coarsen(data)`` returns ``(small, steps)`` -- ``small[i]`` stands for the block ``data[i*s:(i+1)*s]`` on each
    axis (``steps`` per axis of ``data``) -- or None to upload ``data`` as napari would. The layer's ``tile2data``
    transform gets scale ``steps`` and translate ``(steps - 1) / 2`` (a block's centre), so napari places and
    clips the coarse volume itself and every layer property (contrast limits, colormap, rendering, ...) applies as
    before. The layer's data, its slice and its picking (``get_value`` reads the slice) are untouched; 2D slices
    reset ``tile2data`` to the identity. Returns the vispy layer; :func:`restore_3d_texture` undoes this.
    """
    vl = vispy_layer(viewer, layer)
    original = type(vl).downsample_texture.__get__(vl)

    def downsample_texture(data: Any, max_texture_size: Any) -> Any:
        if ndisplay_of(layer) == 3 and not layer.multiscale and getattr(data, "ndim", 0) == 3:
            out = coarsen(data)
            if out is not None:
                small, steps = out
                displayed = list(layer._slice_input.displayed)
                scale = np.ones(layer.ndim)
                translate = np.zeros(layer.ndim)
                for i, d in enumerate(displayed):
                    scale[d] = float(steps[i])
                    translate[d] = (float(steps[i]) - 1.0) / 2.0
                tile2data = layer._transforms["tile2data"]
                tile2data.scale = scale
                tile2data.translate = translate
                vl._on_matrix_change()
                data = small
        return original(data, max_texture_size)

    _set(vl, "downsample_texture", downsample_texture)
    refresh_3d_texture(vl)
    return vl


def restore_3d_texture(vl: Any) -> None:
    """Undo :func:`coarse_3d_texture`: napari's own ``downsample_texture`` again (the full slice on the next draw)."""
    if "downsample_texture" in vl.__dict__:
        object.__delattr__(vl, "downsample_texture")
        refresh_3d_texture(vl)


def refresh_3d_texture(vl: Any) -> None:
    """Upload the layer's 3D slice again (through ``downsample_texture``) when it is shown in 3D."""
    layer = vl.layer
    if ndisplay_of(layer) == 3:
        if not layer.multiscale:
            layer._transforms["tile2data"].scale = np.ones(layer.ndim)
            layer._transforms["tile2data"].translate = np.zeros(layer.ndim)
        vl._on_data_change()


# -- vispy: the GLSL parse of a new program, memoised ----------------------------------------------------------------
_PARSED: dict[str, dict] = {}
_PARSED_MAX = 512


def memoise_program_parse() -> None:
    """Make vispy's ``gloo.Program._parse_variables_from_code`` reuse its result for GLSL it has parsed before.

    Every new napari layer builds a new vispy program, and vispy finds its uniforms and attributes by regular
    expressions over the whole GLSL source (about 55 ms of the ~140 ms first paint of a Points layer under Xvfb's
    software GL). The result depends on the source alone, so it is kept per source text (at most ``_PARSED_MAX``
    sources); the pending variables are processed as before. Installed once, when the dock is made.
    """
    from vispy.gloo.program import Program

    if getattr(Program._parse_variables_from_code, "_unwind_memoised", False):
        return
    original = Program._parse_variables_from_code

    def parse(self: Any, update_variables: bool = True) -> None:
        code = "\n\n".join(sh.code for sh in self._shaders)
        known = _PARSED.get(code)
        if known is None:
            _parse_variables(self, code)
            if len(_PARSED) < _PARSED_MAX:
                _PARSED[code] = dict(self._code_variables)
        else:
            self._code_variables = dict(known)
        if update_variables:
            self._process_pending_variables()

    parse._unwind_memoised = True  # type: ignore[attr-defined]
    parse._unwind_original = original  # type: ignore[attr-defined]
    Program._parse_variables_from_code = parse


# -- napari's text glyphs, rendered ahead --------------------------------------------------------------------------
# napari's canvas renders each character of a text (a Points layer's labels) once, into its font manager's atlas,
# when a text first shows it (``canvas._font_info``: ``font_manager.get_font(face)[char]``, napari's QtTextureFont);
# vispy's TextVisual also measures a line with "ÅÉÑŐ", "jgpqy" and " " on its first draw. About 4-5 ms a glyph
# under Xvfb: 40-50 ms of the first paint of the dock's "ends" layer.
#: the characters the dock's texts need: vispy's line metrics and the ends' roles ("head", "tail", "point 3")
GLYPHS = "ÅÉÑŐjgpqy headtailpoin0123456789"


def warm_glyphs(viewer: Any, chars: str = GLYPHS, limit: int | None = None) -> bool:
    """Render up to ``limit`` (None: all) of ``chars``'s glyphs that the viewer's canvas font has not rendered yet;
    True when none is left. A viewer without napari's Qt font (another napari) is left alone (True)."""
    try:
        info = viewer.window._qt_viewer.canvas._font_info
        font = info.font_manager.get_font(info.face)
        glyphs = font._glyphs
    except AttributeError:
        return True
    todo = [c for c in dict.fromkeys(chars) if c not in glyphs]
    for c in todo[:limit]:
        font[c]
    return limit is None or len(todo) <= limit


# -- a layer added without napari selecting it ---------------------------------------------------------------------
def add_layer_unselected(viewer: Any, layer: Any) -> None:
    """``viewer.add_layer(layer)`` without napari making the new layer the active one (its layer list's
    ``_activate_on_insert``): the selection's change (napari's layer controls and buttons follow it) is 15-25 % of
    napari's cost of adding a layer, and twice that when the previous selection is put back."""
    layers = viewer.layers
    before = layers.__dict__.get("_activate_on_insert")
    if before is None:
        viewer.add_layer(layer)
        return
    layers._activate_on_insert = False
    try:
        viewer.add_layer(layer)
    finally:
        layers._activate_on_insert = before


def main_window(viewer: Any) -> Any:
    """The viewer's Qt main window (napari's ``Window._qt_window``), or None: no window, or closed. A viewer given
    to a plugin's widget through napari's ``PublicOnlyProxy`` is unwrapped (the proxy's window is no QObject)."""
    viewer = getattr(viewer, "__wrapped__", viewer)
    return getattr(getattr(viewer, "window", None), "_qt_window", None)


def viewer_closed(viewer: Any) -> bool:
    """The viewer's window was closed (napari's ``Window.close`` deletes its ``_qt_window``); False for a viewer
    without a window (a ViewerModel)."""
    window = getattr(getattr(viewer, "__wrapped__", viewer), "window", None)  # napari's proxy unwrapped
    return window is not None and not hasattr(window, "_qt_window")


def _strip_line_comments(code: str) -> str:
    """vispy's ``re.sub(r'(.*)(//.*)', r'\\1', code, flags=re.M)`` without its regex: on each line that holds
    ``//``, the text from the last ``//`` on (the greedy ``(.*)`` keeps what precedes the last one). The regex
    backtracks over every line at every position: about 25 ms of the first paint of napari's Points layer."""
    lines = code.split("\n")
    for i, line in enumerate(lines):
        at = line.rfind("//")
        if at >= 0:
            lines[i] = line[:at]
    return "\n".join(lines)


def _parse_variables(program: Any, code: str) -> None:
    """vispy 0.15's ``Program._parse_variables_from_code(update_variables=False)`` on ``code`` (the program's
    shaders' code joined), with the comments stripped by :func:`_strip_line_comments`."""
    import re

    from vispy.gloo.program import REGEX_VAR

    code = _strip_line_comments(code)
    variables: dict[str, tuple] = {}
    for kind in ("uniform", "attribute", "varying", "const", "in", "out"):
        reg = REGEX_VAR[kind]
        if kind == "in":
            kind = "attribute"
        elif kind == "out":
            kind = "varying"
        for m in re.finditer(reg, code):
            gtype = m.group("type")
            size = int(m.group("size")) if m.group("size") else -1
            this_kind = kind
            if size >= 1:
                for i in range(size):
                    name = f"{m.group('name')}[{i}]"
                    variables[name] = kind, gtype, name, -1
                this_kind = "uniform_array"
            name = m.group("name")
            variables[name] = this_kind, gtype, name, size
    program._code_variables = variables
