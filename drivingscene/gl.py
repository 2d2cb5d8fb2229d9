"""OpenGL helpers shared by the synthetic renderer and the viewer (moderngl).

Shaders live in ``shaders/<name>.glsl``, one program per file: ``#version`` first, then
``#if defined VERTEX_SHADER ... #elif defined FRAGMENT_SHADER ... #endif``. ``load_program``
injects the stage define (and any extra defines) after the ``#version`` line, and replaces each
``#include "<other>.glsl"`` line by that file (functions shared by several programs, no ``#version``);
compile errors in the k-th file included report its lines as source string k.
"""

from __future__ import annotations

import logging
import re

from drivingscene.errors import DrivingSceneError
from drivingscene.resources import shader_path

log = logging.getLogger(__name__)

STAGES = {
    "vertex_shader": "VERTEX_SHADER",
    "geometry_shader": "GEOMETRY_SHADER",
    "fragment_shader": "FRAGMENT_SHADER",
}
INCLUDE = re.compile(r'^#include "(\w+)\.glsl"[ \t]*$', re.MULTILINE)


def _expand_includes(name: str, text: str, first_line: int, source: int, included: list[str]) -> str:
    """``text``, the lines of ``shaders/<name>.glsl`` from ``first_line`` on (GLSL source string
    ``source``), with its includes expanded; ``included`` collects the files included so far."""
    out, start = [], 0
    for m in INCLUDE.finditer(text):
        other = m.group(1)
        if other == name or other in included:
            raise DrivingSceneError(f"{shader_path(name)}: {other}.glsl included twice (or by itself)")
        included.append(other)
        number = len(included)
        body = _expand_includes(other, shader_path(other).read_text(), 1, number, included)
        line = first_line + text.count("\n", 0, m.start())  # of the #include
        out += [text[start : m.start()], f"#line 1 {number}\n", body, f"\n#line {line + 1} {source}"]
        start = m.end()
    return "".join(out) + text[start:]


def shader_sources(name: str, defines: dict[str, object] | None = None) -> dict[str, str]:
    """Per-stage sources of ``shaders/<name>.glsl`` for the stages the file defines."""
    text = shader_path(name).read_text()
    first, _, body = text.partition("\n")
    if not first.startswith("#version"):
        raise DrivingSceneError(f"{shader_path(name)}: expected '#version' on the first line")
    extra = "".join(f"#define {k} {v}\n" for k, v in (defines or {}).items())
    body = _expand_includes(name, body, 2, 0, [])
    out = {}
    for kwarg, macro in STAGES.items():
        if f"defined {macro}" in body:
            out[kwarg] = f"{first}\n#define {macro}\n{extra}#line 2\n{body}"
    return out


def load_program(ctx, name: str, defines: dict[str, object] | None = None, **kwargs):
    """Compile ``shaders/<name>.glsl`` into a ``moderngl.Program``; errors name the file."""
    import moderngl

    try:
        return ctx.program(**shader_sources(name, defines), **kwargs)
    except moderngl.Error as e:
        raise DrivingSceneError(f"{shader_path(name)}: shader failed to compile/link: {e}") from None


def create_offscreen_context(require: int = 330):
    """A standalone moderngl context through EGL (no X server needed)."""
    import moderngl

    try:
        return moderngl.create_standalone_context(backend="egl", require=require)
    except Exception as e:  # noqa: BLE001 - glcontext raises plain Exception subclasses
        raise DrivingSceneError(
            f"could not create an offscreen OpenGL {require // 100}.{require % 100 // 10} context through EGL: {e} "
            "(install Mesa's EGL drivers: apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri)"
        ) from None
