"""The numeric contract (docs/numerics.md): the same rays give the same bits on every device.

OpenCL: every program viewer.cl.programs.build compiles starts with `#pragma OPENCL FP_CONTRACT
OFF` and is built with no fast-math option (and with correctly rounded divide where the device
offers it); a kernel then evaluates a*b+c and a/b as NumPy's float32 does. GLSL: the intersection,
ray-generation and offset math is `precise`, its divisions go through divRounded, and every shader
gets the optionNV pragmas; double-typed constants carry the `lf` suffix (NVIDIA rejects
`dvec2(1e300)`, Mesa forgives it).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import opencl_missing
from viewer.cl import programs
from viewer.gl.programs import NUMERIC_PRAGMAS, SHADER_DIR, load_shader_source

VIEWER = Path(__file__).resolve().parents[1] / "viewer"
CL_REASON = opencl_missing()
needs_cl = pytest.mark.skipif(CL_REASON is not None, reason=f"no OpenCL device: {CL_REASON}")

FMA_KERNEL = """
__kernel void madd(__global const float *a, __global const float *b, __global const float *c,
                   __global float *out, __global float *quo) {
    int i = get_global_id(0);
    out[i] = a[i] * b[i] + c[i];
    quo[i] = a[i] / b[i];
}
"""


def test_every_cl_source_starts_with_the_pragma():
    """program_source (the text build compiles) puts the pragma first for every kernel file of the
    project, ahead of any caller prelude."""
    files = sorted(VIEWER.rglob("*.cl"))
    assert len(files) >= 10
    for f in files:
        src = programs.program_source(f, prelude="#define PRED(x) (x)")
        assert src.startswith("#pragma OPENCL FP_CONTRACT OFF\n"), f
    assert "-cl-mad-enable" in programs.FORBIDDEN_OPTIONS


@needs_cl
def test_built_program_carries_contract_and_evaluates_unfused(tmp_path):
    """A kernel built through programs.build: its source starts with the pragma, its options hold no
    fast-math flag, and a*b+c on inputs where a fused multiply-add gives another answer (and a/b on
    random inputs) equals NumPy's float32 bit for bit."""
    import pyopencl as cl

    from viewer.cl.context import cl_context

    ctx = cl_context()
    path = tmp_path / "madd.cl"
    path.write_text(FMA_KERNEL)
    prog = programs.build(path, {"UNUSED": 1}, ctx)
    src = prog.get_info(cl.program_info.SOURCE)
    assert src.startswith(programs.NUMERIC_PRELUDE)
    opts = programs.build_options({"UNUSED": 1}, ctx)
    assert not set(opts) & set(programs.FORBIDDEN_OPTIONS)
    if ctx.device.single_fp_config & cl.device_fp_config.CORRECTLY_ROUNDED_DIVIDE_SQRT:
        assert programs.CORRECT_DIV_SQRT in opts

    rng = np.random.default_rng(3)
    n = 4096
    # a = b = 1 + 2^-12 (+ random low bits), c = -round(a*b): separate rounding gives a*b's rounding
    # error lost (often 0), a fused multiply-add keeps it
    a = (1 + 2.0 ** -12 + rng.integers(0, 64, n) * 2.0 ** -23).astype(np.float32)
    b = (1 + 2.0 ** -12 + rng.integers(0, 64, n) * 2.0 ** -23).astype(np.float32)
    c = -(a * b)
    a[n // 2:] = rng.uniform(-10, 10, n - n // 2).astype(np.float32)
    b[n // 2:] = rng.uniform(0.1, 10, n - n // 2).astype(np.float32)
    c[n // 2:] = rng.uniform(-10, 10, n - n // 2).astype(np.float32)
    exact = a.astype(np.float64) * b.astype(np.float64) + c.astype(np.float64)
    expected = a * b + c
    assert (expected[: n // 2] != exact[: n // 2].astype(np.float32)).sum() > n // 8  # fusing would show
    mf = cl.mem_flags
    bufs = [cl.Buffer(ctx.context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=x) for x in (a, b, c)]
    out = np.empty(n, np.float32)
    quo = np.empty(n, np.float32)
    ob, qb = cl.Buffer(ctx.context, mf.WRITE_ONLY, out.nbytes), cl.Buffer(ctx.context, mf.WRITE_ONLY, quo.nbytes)
    prog.madd(ctx.queue, (n,), None, *bufs, ob, qb)
    cl.enqueue_copy(ctx.queue, out, ob)
    cl.enqueue_copy(ctx.queue, quo, qb)
    ctx.queue.finish()
    assert np.array_equal(out, expected)
    if programs.CORRECT_DIV_SQRT in opts:
        assert np.array_equal(quo, a / b)


def test_shaders_get_the_numeric_pragmas():
    src = load_shader_source("raygen.frag")
    first = src.split("\n", 1)
    assert first[0].startswith("#version")
    assert first[1].startswith(NUMERIC_PRAGMAS)


def _function(text: str, name: str) -> str:
    """The body of GLSL function `name` (braces matched), comments removed."""
    text = re.sub(r"//[^\n]*", "", text)
    m = re.search(r"\b\w+\s+" + name + r"\s*\([^)]*\)\s*\{", text)
    assert m, name
    depth, i = 1, m.end()
    while depth:
        depth += {"{": 1, "}": -1}.get(text[i], 0)
        i += 1
    return text[m.end():i - 1]


def _precise_names(body: str) -> set[str]:
    names: set[str] = set()
    for m in re.finditer(r"\bprecise\s+\w+\s+([^;]+);", body):
        decl = re.sub(r"\([^()]*\)", "", re.sub(r"\([^()]*\)", "", m.group(1)))  # drop call arguments
        names |= {part.split("=")[0].strip() for part in decl.split(",")}
    return names


def test_intersection_math_is_precise():
    """The values the watertight test, the distance, the slab test, the hit point and the offset
    depend on are `precise`, their divisions correctly rounded (divRounded) and their dot products
    written out (dotPrecise): no fused multiply-add, no approximate division or builtin dot."""
    text = (SHADER_DIR / "intersect.glsl").read_text()
    tri = _function(text, "intersectTriangle")
    assert {"A", "B", "C", "Ax", "Ay", "Bx", "By", "Cx", "Cy", "U", "V", "W", "det", "n", "dn",
            "CxBy", "CyBx", "AxCy", "AyCx", "BxAy", "ByAx"} <= _precise_names(tri)
    assert {"t0", "t1", "exit"} <= _precise_names(_function(text, "intersectBox"))
    assert "c" in _precise_names(_function(text, "crossRounded"))
    assert "s" in _precise_names(_function(text, "dotPrecise"))
    assert "q" in _precise_names(_function(text, "divRounded"))
    for name in ("intersectTriangle", "prepareRay", "safeRcp"):
        body = _function(text, name)
        assert not re.search(r"[^/]/[^/]", body), f"{name}: a raw division (use divRounded)"
        assert not re.search(r"\bdot\s*\(", body), f"{name}: builtin dot (use dotPrecise)"
    raygen = (SHADER_DIR / "raygen.frag").read_text()
    assert {"p", "po"} <= _precise_names(raygen)
    assert "q" in _precise_names(_function((SHADER_DIR / "sampling.glsl").read_text(), "offsetRayOrigin"))
    assert "d" in _precise_names(_function((SHADER_DIR / "camera.glsl").read_text(), "primaryDir"))


# ------------------------------------------------------------------------------------------------
# double literals
# ------------------------------------------------------------------------------------------------

SHADER_EXT = {".glsl", ".vert", ".frag", ".geom", ".comp", ".tesc", ".tese"}
DOUBLE_CONTEXT = re.compile(r"\b(double|dvec[234]|dmat[234](x[234])?)\b")
# a floating constant: digits '.' [digits] | '.' digits, optional exponent; or digits with an exponent.
# Not part of an identifier or a swizzle (no word character or '.' just before), then its suffix.
FLOAT_LITERAL = re.compile(r"(?<![\w.])((?:\d+\.\d*|\.\d+)(?:[eE][+-]?\d+)?|\d+[eE][+-]?\d+)(lf|LF|f|F)?(?![\w.])")


def unsuffixed_double_literals(text: str) -> list[tuple[int, str]]:
    """(line number, literal) for every floating literal without lf/LF on a line that names a double
    type (double, dvecN, dmatN): in a double context a float literal is a float constant (1e300
    overflows, 1.1 is not 1.1) and NVIDIA rejects or rounds it. Comments are ignored."""
    text = re.sub(r"/\*.*?\*/", lambda m: "\n" * m.group(0).count("\n"), text, flags=re.S)
    bad = []
    for no, line in enumerate(text.splitlines(), 1):
        code = line.split("//", 1)[0]
        if not DOUBLE_CONTEXT.search(code):
            continue
        for m in FLOAT_LITERAL.finditer(code):
            if (m.group(2) or "").lower() != "lf":
                bad.append((no, m.group(0)))
    return bad


@pytest.mark.parametrize("snippet, found", [
    ("dvec2 lo = dvec2(1e300), hi = dvec2(-1e300);", ["1e300", "1e300"]),
    ("double x = 1.0e-5 * y + .5 - 2. + 3.f;", ["1.0e-5", ".5", "2.", "3.f"]),
    ("double x = 1.0e-5lf * y + .5LF - 2.lf + 1e3lf + 3;", []),
    ("dmat3 m = dmat3(0.25); vec3 v3 = p.xy1;", ["0.25"]),
    ("float x = 1e300; // double 2.5", []),
    ("/* double 1.5 */ float y = 2.5;", []),
])
def test_literal_scanner(snippet, found):
    assert [lit for _, lit in unsuffixed_double_literals(snippet)] == found


def test_no_double_literal_without_lf():
    """Every shader file of the project (viewer/shaders and backend folders): no float literal
    without lf on a line that uses a double type."""
    files = sorted(p for p in VIEWER.rglob("*") if p.suffix in SHADER_EXT)
    assert any(p.name == "gbuffer.geom" for p in files) and len(files) > 20
    bad = {str(p.relative_to(VIEWER)): lits for p in files if (lits := unsuffixed_double_literals(p.read_text()))}
    assert not bad, f"double-context literals without lf: {bad}"
