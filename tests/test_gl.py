"""viewer.gl: one table of binding points used by Python and every shader, the program cache's
search path (a backend folder with its own shaders that include shared ones)."""

from __future__ import annotations

import re

import numpy as np
import pytest

from viewer.backends.gl_traversal import SHADER_DIR as GLSL_DIR
from viewer.gl import bindings
from viewer.gl.programs import SHADER_DIR, ProgramCache, load_shader_source

SHADER_FILES = sorted(p for p in SHADER_DIR.iterdir() if p.suffix in (".glsl", ".vert", ".frag", ".geom", ".comp"))


def test_binding_points_are_unique_per_namespace():
    for table in (bindings.SSBO, bindings.IMAGE, bindings.TEXTURE):
        assert len(set(table.values())) == len(table), table
        assert all(k.startswith("BIND_") and v >= 0 for k, v in table.items())
    assert not set(bindings.SSBO) & set(bindings.IMAGE)
    assert not (set(bindings.SSBO) | set(bindings.IMAGE)) & set(bindings.TEXTURE)
    assert all(v >= 16 for v in bindings.TEXTURE.values())  # below 16: the passes' own units
    header = bindings.shader_header()
    for name, value in {**bindings.SSBO, **bindings.IMAGE, **bindings.TEXTURE}.items():
        assert f"#define {name} {value}\n" in header
        assert getattr(bindings, name) == value


@pytest.mark.parametrize("path", SHADER_FILES, ids=lambda p: p.name)
def test_shaders_name_binding_points(path):
    """No literal binding numbers in shaders: every `binding =` names a BIND_* of the table."""
    text = path.read_text()
    known = {**bindings.SSBO, **bindings.IMAGE, **bindings.TEXTURE}
    for m in re.finditer(r"binding\s*=\s*([A-Za-z0-9_]+)", text):
        assert m.group(1) in known, f"{path.name}: binding = {m.group(1)}"


def test_loaded_source_carries_the_binding_header():
    src = load_shader_source("trace_glsl.frag", {"STACK_SIZE": 24}, search=[GLSL_DIR])
    lines = src.splitlines()
    assert lines[0] == "#version 450 core"
    assert "#define BIND_NODES 0" in lines and "#define STACK_SIZE 24" in lines
    assert "#include" not in src  # scene.glsl, intersect.glsl expanded


def test_backend_folder_shaders_include_shared_ones(gl_ctx, tmp_path):
    """A backend folder's own fragment shader, found through the search path, includes the shared
    scene.glsl from viewer/shaders/ and reads the scene through BIND_MATERIALS; a file of the same
    name in the folder wins over the shared one."""
    folder = tmp_path / "mybackend"
    folder.mkdir()
    (folder / "mine.frag").write_text('#include "scene.glsl"\n#include "local.glsl"\nout vec4 color;\n'
                                      "void main() { color = vec4(materials[1].rgb * LOCAL_SCALE, 1.0); }\n")
    (folder / "local.glsl").write_text("const float LOCAL_SCALE = 0.5;\n")
    ctx = gl_ctx
    programs = ProgramCache(ctx).with_path(folder)
    prog = programs.get("fullscreen.vert", "mine.frag")
    assert programs.get("fullscreen.vert", "mine.frag") is prog  # cached
    with pytest.raises(FileNotFoundError):
        load_shader_source("mine.frag")  # not on the default path
    mats = np.array([[0.1, 0.2, 0.3, 0.0], [0.8, 0.4, 0.2, 0.0]], np.float32)
    buf = ctx.buffer(mats.tobytes())
    tex = ctx.texture((4, 4), 4, dtype="f4")
    fbo = ctx.framebuffer(color_attachments=[tex])
    vao = ctx.vertex_array(prog, [])
    try:
        buf.bind_to_storage_buffer(bindings.BIND_MATERIALS)
        fbo.use()
        vao.render(vertices=3)
        out = np.frombuffer(tex.read(), np.float32).reshape(4, 4, 4)
        np.testing.assert_allclose(out[..., :3], np.broadcast_to(mats[1, :3] * 0.5, (4, 4, 3)), rtol=1e-6)
    finally:
        for obj in (vao, fbo, tex, buf):
            obj.release()


class _FakeGL:
    def __init__(self, renderer: str):
        self.info = {"GL_RENDERER": renderer}
        self.released = self.entered = False

    def release(self) -> None:
        self.released = True

    def __enter__(self):
        self.entered = True
        return self


@pytest.mark.parametrize("devices,expect", [(["llvmpipe (LLVM 15)", "NVIDIA H100/PCIe/SSE2"], 1),
                                            (["NVIDIA H100/PCIe/SSE2", "llvmpipe (LLVM 15)"], 0),
                                            (["llvmpipe (LLVM 15)"], 0),
                                            (["llvmpipe (LLVM 15)", "llvmpipe (LLVM 15)"], 0)])
def test_headless_context_prefers_a_hardware_egl_device(monkeypatch, devices, expect):
    """EGL device 0 may be Mesa's software rasterizer on a machine with NVIDIA's driver too: the
    first hardware device is taken (GLCONTEXT_DEVICE_INDEX, when set, decides alone)."""
    import moderngl

    from viewer.gl import context as glc

    made: list[_FakeGL] = []

    def create_context(standalone=True, backend="egl", require=450, device_index=0):
        if device_index >= len(devices):
            raise Exception(f"requested device index {device_index}, but found {len(devices)} devices")
        made.append(_FakeGL(devices[device_index]))
        return made[-1]

    monkeypatch.setattr(moderngl, "create_context", create_context)
    monkeypatch.delenv(glc.DEVICE_INDEX_ENV, raising=False)
    ctx = glc.create_headless_context()
    assert ctx.info["GL_RENDERER"] == devices[expect] and not ctx.released
    assert all(c.released for c in made if c is not ctx)
    monkeypatch.setenv(glc.DEVICE_INDEX_ENV, "0")
    made.clear()
    assert glc.create_headless_context().info["GL_RENDERER"] == devices[0] and len(made) == 1


@pytest.mark.parametrize("devices", [["llvmpipe (LLVM 15)", "GL 4.1 GPU"],
                                     ["llvmpipe (LLVM 15)", "GL 4.1 GPU", "llvmpipe"]])
def test_headless_context_is_current_after_a_failed_probe(monkeypatch, devices):
    """A probe of another EGL device that fails after glcontext made its context current (moderngl's
    GL 4.5 check raises after creation) leaves device 0 current again, not the dead probe."""
    import moderngl

    from viewer.gl import context as glc

    current: list[_FakeGL] = []

    class Current(_FakeGL):
        def __enter__(self):
            current.append(self)
            return self

    def create_context(standalone=True, backend="egl", require=450, device_index=0):
        if device_index >= len(devices):
            raise Exception(f"requested device index {device_index}, but found {len(devices)} devices")
        ctx = Current(devices[device_index])
        current.append(ctx)  # glcontext makes a new context current
        if devices[device_index].startswith("GL 4.1"):
            raise ValueError("Requested OpenGL version 450, got version 410")
        return ctx

    monkeypatch.setattr(moderngl, "create_context", create_context)
    monkeypatch.delenv(glc.DEVICE_INDEX_ENV, raising=False)
    ctx = glc.create_headless_context()
    assert ctx.info["GL_RENDERER"] == devices[0] and current[-1] is ctx


def test_a_chosen_egl_device_that_fails_names_the_variable(monkeypatch):
    """GLCONTEXT_DEVICE_INDEX past the devices: one line naming the variable (not advice to install
    Mesa, which is there)."""
    import moderngl

    from viewer.errors import RtwalkError
    from viewer.gl import context as glc

    def create_context(standalone=True, backend="egl", require=450, device_index=0):
        raise Exception("requested device index 3, but found 1 devices")

    monkeypatch.setattr(moderngl, "create_context", create_context)
    monkeypatch.setenv(glc.DEVICE_INDEX_ENV, "3")
    with pytest.raises(RtwalkError, match=r"found 1 devices\); GLCONTEXT_DEVICE_INDEX=3 chose the EGL device"):
        glc.create_headless_context()


def test_declared_but_inactive_uniforms_take_writes(gl_ctx, tmp_path):
    """A uniform the compiler removed (here: its use switched off by a define; on NVIDIA also what
    its optimiser proves dead) takes writes as a no-op, through `prog[name] = v` and `.value`; a name
    the source never declares still raises KeyError; compute shaders likewise."""
    from viewer.gl.inactive import declared_uniforms
    from viewer.gl.programs import compute_shader

    assert declared_uniforms("uniform float a, b[2];\nlayout(r32i, binding = 0) uniform coherent iimage2D img;\n"
                             "layout(std140) uniform Block { float inside; };\nuniform sampler2D s;") \
        == {"a", "b", "img", "s"}
    (tmp_path / "gated.frag").write_text("uniform float gain;\nuniform float used;\nout vec4 color;\n"
                                         "void main() {\n#ifdef GAIN\n color = vec4(gain);\n#else\n"
                                         " color = vec4(used);\n#endif\n}\n")
    prog = ProgramCache(gl_ctx).with_path(tmp_path).get("fullscreen.vert", "gated.frag")
    assert "gain" not in list(prog)
    prog["gain"] = 2.0
    prog["gain"].value = 3.0
    prog["used"] = 1.0
    assert prog["used"].value == 1.0
    with pytest.raises(KeyError):
        prog["typo"] = 1.0
    (tmp_path / "c.comp").write_text("layout(local_size_x = 1) in;\nuniform int unused;\nvoid main() {}\n")
    cs = compute_shader(gl_ctx, "c.comp", search=(tmp_path,))
    cs["unused"] = 1
    with pytest.raises(KeyError):
        cs["typo"] = 1


def test_integer_targets_are_cleared_as_integers(gl_ctx):
    """clear_int_texture writes the integer itself (glClearTexImage); a framebuffer clear with the
    float clear colour leaves an R32I target undefined by the spec (Mesa: the float's bits)."""
    from viewer.gl.textures import clear_int_texture, int_texture, read_texture

    tex = int_texture(gl_ctx, (5, 3))
    try:
        tex.write(np.arange(15, dtype=np.int32).tobytes())
        clear_int_texture(tex, -1)
        assert (read_texture(tex) == -1).all()
        clear_int_texture(tex, 7)
        assert (read_texture(tex) == 7).all()
    finally:
        tex.release()


def test_gl_errors_are_one_line_with_the_check_on(gl_ctx, monkeypatch):
    """RTWALK_GL_CHECK=1: an error GL recorded (here GL_INVALID_ENUM) stops with one line naming
    it; off (the default) nothing is looked at."""
    from viewer.errors import RtwalkError
    from viewer.gl import io as glio
    from viewer.gl.textures import _gl

    while gl_ctx.error != "GL_NO_ERROR":
        pass
    monkeypatch.delenv(glio.GL_CHECK_ENV, raising=False)
    _gl()["glBindTexture"](0xDEAD, 0)
    glio.check_errors(gl_ctx, "a test")
    monkeypatch.setenv(glio.GL_CHECK_ENV, "1")
    with pytest.raises(RtwalkError, match=r"OpenGL error during a test: GL_INVALID_ENUM \(RTWALK_GL_CHECK=1\)"):
        glio.check_errors(gl_ctx, "a test")
    glio.check_errors(gl_ctx, "a test")  # read once: the flag is clear again


def test_counted_reads_see_the_shader_writes_before_them(gl_ctx):
    """viewer.gl.io.read issues the host-access barrier first: a buffer read right after a draw
    whose fragments count into it with SSBO atomics returns the count. Without the barrier even
    llvmpipe returns the buffer as it was before the draw (measured: 0, every time), so chcrt's
    counts, raygen's ray counts and the occlusion stats would be stale whenever no glFinish comes
    between (phase timing by timer queries)."""
    import moderngl

    from viewer.gl import io as glio

    prog = gl_ctx.program(
        vertex_shader="#version 450\nvoid main() { gl_Position = vec4(vec2(gl_VertexID & 1, gl_VertexID >> 1) * 4.0"
                      " - 1.0, 0.0, 1.0); }\n",
        fragment_shader="#version 450\nlayout(std430, binding = 3) buffer C { uint count; };\nout vec4 color;\n"
                        "void main() { atomicAdd(count, 1u); color = vec4(1.0); }\n")
    vao = gl_ctx.vertex_array(prog, [])
    tex = gl_ctx.texture((64, 32), 4)
    fbo = gl_ctx.framebuffer([tex])
    buf = gl_ctx.buffer(reserve=4)
    try:
        buf.bind_to_storage_buffer(3)
        fbo.use()
        for _ in range(3):
            glio.write(buf, np.zeros(1, np.uint32))
            vao.render(moderngl.TRIANGLES, vertices=3)
            assert np.frombuffer(glio.read(buf), np.uint32)[0] == 64 * 32
    finally:
        for obj in (vao, fbo, tex, buf, prog):
            obj.release()


def test_texel_view_reads_the_buffer_bits(gl_ctx):
    """A TexelView over a storage buffer (and over a range of it) gives a shader the buffer's bits,
    NaN and infinity patterns included; a range the device cannot view is a one-line RtwalkError."""
    from viewer.errors import RtwalkError
    from viewer.gl.textures import TEXEL_BYTES, TexelView, texel_buffer_limit_cached

    ctx = gl_ctx
    rng = np.random.default_rng(3)
    data = rng.integers(0, 2**32, size=(64, 4), dtype=np.uint64).astype(np.uint32)
    data[0] = [0x7FC00001, 0x7F800000, 0xFF800000, 0x80000000]  # NaN payload, +inf, -inf, -0
    buf = ctx.buffer(data.tobytes())
    out = ctx.buffer(reserve=data.nbytes)
    prog = ctx.compute_shader("""#version 450
layout(local_size_x = 64) in;
layout(binding = 20) uniform usamplerBuffer src;
layout(std430, binding = 0) buffer Out { uvec4 o[]; };
uniform int n;
void main() { int i = int(gl_GlobalInvocationID.x); o[i] = i < n ? texelFetch(src, i) : uvec4(0xdeadu); }""")
    view = TexelView(20)
    try:
        out.bind_to_storage_buffer(0)
        view.attach(buf)
        prog["n"] = 64
        prog.run(1)
        assert np.array_equal(np.frombuffer(out.read(), np.uint32).reshape(64, 4), data)
        _, align = texel_buffer_limit_cached()
        first = -(-align // TEXEL_BYTES)  # the first texel at an aligned offset
        view.attach(buf, first * TEXEL_BYTES, 8 * TEXEL_BYTES)
        prog["n"] = 8
        prog.run(1)
        got = np.frombuffer(out.read(), np.uint32).reshape(64, 4)
        assert np.array_equal(got[:8], data[first:first + 8]) and (got[8:] == 0xDEAD).all()
        with pytest.raises(RtwalkError, match="buffer texture"):
            view.attach(buf, 4)  # not a multiple of the offset alignment
        with pytest.raises(RtwalkError, match="buffer texture"):
            view.attach(buf, 0, 0)
    finally:
        view.release()
        for obj in (prog, out, buf):
            obj.release()


def test_scene_fetch_path_is_chosen_from_the_device_limit(gl_ctx, monkeypatch):
    """Buffer textures (SCENE_TEXELS) when nodes and triangles fit the device's buffer-texture limit,
    the SSBOs otherwise; RTWALK_SCENE_FETCH forces either, and a value it cannot honour is a one-line
    error."""
    from viewer.errors import RtwalkError
    from viewer.gl import scene as gls

    monkeypatch.delenv(gls.FETCH_ENV, raising=False)
    assert gls.choose_texels(1000, 2000)
    monkeypatch.setattr(gls, "texel_buffer_limit_cached", lambda: (3000, 16))  # 3 texels a triangle
    assert gls.choose_texels(1000, 700) and not gls.choose_texels(1001, 700)
    assert not gls.choose_texels(10, 751)  # 4 texels a node
    monkeypatch.setenv(gls.FETCH_ENV, "ssbo")
    assert not gls.choose_texels(10, 10)
    monkeypatch.setenv(gls.FETCH_ENV, "texels")
    assert gls.choose_texels(10, 10)
    with pytest.raises(RtwalkError, match="exceed"):
        gls.choose_texels(1001, 10)
    monkeypatch.setenv(gls.FETCH_ENV, "fast")
    with pytest.raises(RtwalkError, match="expected"):
        gls.choose_texels(10, 10)
