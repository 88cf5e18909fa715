"""The memoised GLSL parse of vispy's programs (``_private.memoise_program_parse``): the same variables as vispy's
own parser finds, per source; different sources are not confused (napari, vispy, Xvfb)."""

import pytest

pytest.importorskip("napari")

from vispy.gloo.program import Program  # noqa: E402

from napari_unwind._napari import _private  # noqa: E402

pytestmark = pytest.mark.gui

VERT = """
uniform float u_scale;  // a comment with uniform float u_fake;
attribute vec2 a_position;
varying vec4 v_color;
void main() { gl_Position = vec4(a_position * u_scale, 0.0, 1.0); v_color = vec4(1.0); }
"""
FRAG = """
varying vec4 v_color;
uniform vec4 u_tint[2];
void main() { gl_FragColor = v_color * u_tint[0]; }
"""


def test_the_memoised_parse_finds_what_vispys_own_parser_finds():
    _private.memoise_program_parse()
    parse = Program._parse_variables_from_code
    assert parse._unwind_memoised
    original = parse._unwind_original
    frag2 = FRAG.replace("u_tint[2]", "u_tint[3]")
    for vert, frag in ((VERT, FRAG), (VERT, FRAG), (VERT, frag2)):
        p = Program(vert, frag)          # parsed through the memo (the second time from it)
        q = Program.__new__(Program)
        q._shaders = p._shaders
        original(q, update_variables=False)
        assert p._code_variables == q._code_variables
        assert "u_fake" not in p._code_variables and "u_scale" in p._code_variables
    assert "u_tint[2]" in Program(VERT, frag2)._code_variables
    assert "u_tint[2]" not in Program(VERT, FRAG)._code_variables
    p = Program(VERT, FRAG)
    p["u_scale"] = 2.0  # pending variables are processed as before
    assert "u_scale" in p._user_variables
