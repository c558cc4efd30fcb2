"""NVIDIA portability (docs/device-limits.md, "NVIDIA portability"): what the NVIDIA drivers or the
specs reject but Mesa llvmpipe and PoCL accept, caught without a GPU.

GLSL: every shader file, in each variant its `#ifdef`s allow, passes glslangValidator (the Khronos
reference front end: strict about implicit conversions, qualifiers and layouts where Mesa is
lenient), and every compute shader stays within NVIDIA's 1024 invocations and 48 KiB of shared
memory. OpenCL: every program the CL backends build (renders with each, sized for a 48 KiB device
with RTWALK_CL_LOCAL_KIB=48) compiles as OpenCL C 1.2 for clang's NVIDIA target (nvptx64-nvidia-nvcl:
NVIDIA's OpenCL 3.0 compiles OpenCL C 1.2, no generic address space, pipes or device-side enqueue)
with warnings as errors, and no kernel needs more than 48 KiB of local memory or a work-group over
1024. Tools that are not installed (glslang-tools, clang) skip their test with the reason.
"""

from __future__ import annotations

import functools
import importlib
import os
import re
import shutil
import subprocess
import warnings
from pathlib import Path

import numpy as np
import pytest

from tests.cli_runner import run_cli
from tests.conftest import opencl_missing
from viewer.gl.programs import load_shader_source

VIEWER = Path(__file__).resolve().parents[1] / "viewer"
SHADER_SUFFIXES = (".vert", ".frag", ".geom", ".comp")
NV_LOCAL_BYTES = 48 * 1024  # CL_DEVICE_LOCAL_MEM_SIZE / GL_MAX_COMPUTE_SHARED_MEMORY_SIZE on NVIDIA
NV_MAX_GROUP = 1024  # CL_DEVICE_MAX_WORK_GROUP_SIZE / GL_MAX_COMPUTE_WORK_GROUP_INVOCATIONS
CL_REASON = opencl_missing()
needs_cl = pytest.mark.skipif(CL_REASON is not None, reason=f"no OpenCL device: {CL_REASON}")
GLSLANG = shutil.which("glslangValidator")
#: the glslang major version whose warnings were all looked at (Debian 12's 12.0): a newer one may
#: warn about new things, reported by pytest, not failed, so the stock-machine test command holds
GLSLANG_CHECKED_MAJOR = 12


@functools.cache
def _glslang_major() -> int:
    if GLSLANG is None:
        return 0
    out = subprocess.run([GLSLANG, "--version"], capture_output=True, text=True, timeout=30).stdout
    m = re.search(r"glslang Khronos\S*\s+(\d+)", out)
    return int(m.group(1)) if m else 0


def _clang_for_nvptx() -> str | None:
    """A clang on PATH (`clang`, else the newest `clang-N`: PoCL's package brings a versioned one)
    whose registered targets include nvptx64; None without one, so the test skips instead of
    failing on a clang built without the NVPTX back end."""
    versioned = {p.name for d in os.environ.get("PATH", "").split(os.pathsep) if d and Path(d).is_dir()
                 for p in Path(d).glob("clang-[0-9]*") if p.name[6:].isdigit()}
    for name in ["clang", *sorted(versioned, key=lambda n: -int(n[6:]))]:
        path = shutil.which(name)
        if path is None:
            continue
        try:
            out = subprocess.run([path, "-print-targets"], capture_output=True, text=True, timeout=60).stdout
        except (OSError, subprocess.SubprocessError):
            continue
        if re.search(r"^\s*nvptx64\b", out, re.M):
            return path
    return None


CLANG = _clang_for_nvptx()


def _shader_files() -> list[Path]:
    return sorted(p for p in VIEWER.rglob("*") if p.suffix in SHADER_SUFFIXES)


def _folder_bindings(folder: Path) -> dict:
    """A backend folder's own binding points (`BINDINGS` of one of its modules: the defines its
    ProgramCache passes); {} for viewer/shaders."""
    if folder.parent.name != "backends":
        return {}
    for mod in sorted(folder.glob("*.py")):
        name = f"viewer.backends.{folder.name}" + ("" if mod.stem == "__init__" else f".{mod.stem}")
        bindings = getattr(importlib.import_module(name), "BINDINGS", None)
        if isinstance(bindings, dict):
            return bindings
    return {}


# defines some shaders are never built without (their defaults are for another shader of the file set)
HOST_DEFINES = {"chc_intersect.frag": {"CHC_MAX_ITEMS": 24},
                "chc_visible.comp": {"CHC_MAX_ITEMS": 24, "CHC_COUNT_ITEMS": 1},
                "raygen.frag": {"RAY_TYPE": 3},
                "accumulate.frag": {"ACC_EFFECT": 3}}


def _variants(path: Path) -> list[dict]:
    """Defines for the shader as it is built: none, and every `#ifdef X` / `#if X > N` it (or an
    include) tests switched on at once (X = 1, or N + 1 for a comparison); and with that, every
    bare `#if X` switch (on by default, e.g. RESUMABLE) off."""
    base = {**_folder_bindings(path.parent), **HOST_DEFINES.get(path.name, {})}
    src = load_shader_source(path.name, base, (path.parent,))
    flags = {m: 1 for m in re.findall(r"^\s*#\s*ifdef\s+(\w+)", src, re.M)}
    # a comparison that guards an #error is a limit, not a variant
    flags.update({m: int(n) + 1 for m, n, nxt in re.findall(r"^\s*#\s*if\s+(\w+)\s*>\s*(\d+).*\n\s*(\S*)", src, re.M)
                  if nxt != "#error"})
    flags = {k: v for k, v in flags.items() if not k.startswith("GL_") and not k.endswith("_GLSL")}
    out = [base, {**base, **flags}] if flags else [base]
    off = {m: 0 for m in re.findall(r"^\s*#\s*if\s+(\w+)\s*$", src, re.M)}
    return [*out, {**out[-1], **off}] if off else out


@pytest.mark.skipif(GLSLANG is None, reason="glslangValidator not installed (apt-get install glslang-tools)")
@pytest.mark.parametrize("path", _shader_files(), ids=lambda p: p.name)
def test_shaders_pass_glslang(path, tmp_path):
    """The text ProgramCache compiles (version, pragmas, bindings, defines, includes) passes the
    reference compiler in every variant, without warnings: e.g. int <-> uint assignments, a
    `binding` that is not a constant, an image format that does not fit its type."""
    for k, defines in enumerate(_variants(path)):
        f = tmp_path / f"v{k}{path.suffix}"
        f.write_text(load_shader_source(path.name, defines, (path.parent,)))
        out = subprocess.run([GLSLANG, str(f)], capture_output=True, text=True, timeout=60)
        lines = (out.stdout + out.stderr).splitlines()
        errors = [line for line in lines if "ERROR" in line]
        assert out.returncode == 0 and not errors, f"{path.name} {defines}: " + " | ".join(errors[:6])
        warns = [line for line in lines if "WARNING" in line]
        if warns and _glslang_major() > GLSLANG_CHECKED_MAJOR:
            warnings.warn(f"{path.name} {defines}: glslang {_glslang_major()} warns: " + " | ".join(warns[:6]),
                          stacklevel=1)
            continue
        assert not warns, f"{path.name} {defines}: " + " | ".join(warns[:6])


_GLSL_SIZES = {"float": 4, "int": 4, "uint": 4, "bool": 4, "vec2": 8, "ivec2": 8, "uvec2": 8,
               "vec3": 16, "ivec3": 16, "uvec3": 16, "vec4": 16, "ivec4": 16, "uvec4": 16, "double": 8}


@pytest.mark.parametrize("path", [p for p in _shader_files() if p.suffix == ".comp"], ids=lambda p: p.name)
def test_compute_shaders_fit_nvidia(path):
    """local_size within 1024 invocations and `shared` arrays within 48 KiB (vec3 counted as 16
    bytes, as std430 pads it); a size that is not a literal fails the test so it gets looked at."""
    src = load_shader_source(path.name, _folder_bindings(path.parent), (path.parent,))
    sizes = dict(re.findall(r"local_size_([xyz])\s*=\s*(\d+)", src))
    assert sizes, f"{path.name}: no literal local_size"
    assert np.prod([int(v) for v in sizes.values()]) <= NV_MAX_GROUP, f"{path.name}: local_size {sizes}"
    total = 0
    for typ, names in re.findall(r"^\s*shared\s+(\w+)\s+([^;]+);", src, re.M):
        for decl in names.split(","):
            m = re.fullmatch(r"\s*\w+\s*(?:\[\s*(\d+)\s*\])?\s*", decl)
            assert m and typ in _GLSL_SIZES, f"{path.name}: cannot size 'shared {typ} {decl}'"
            total += _GLSL_SIZES[typ] * int(m.group(1) or 1)
    assert total <= NV_LOCAL_BYTES, f"{path.name}: {total} bytes of shared memory"


# NVIDIA's per-stage limits (GL_MAX_*_SHADER_STORAGE_BLOCKS 16, GL_MAX_*_IMAGE_UNIFORMS and
# GL_MAX_IMAGE_UNITS 8, GL_MAX_*_TEXTURE_IMAGE_UNITS 32; llvmpipe's differ)
NV_STAGE_LIMITS = {"ssbo": 16, "image": 8, "sampler": 32}


@pytest.mark.parametrize("path", _shader_files(), ids=lambda p: p.name)
def test_shader_resources_fit_nvidia(path):
    """Storage blocks, image and sampler uniforms one stage declares (every variant's declarations,
    an upper bound of what is active) within NVIDIA's per-stage limits; image binding points below
    its 8 image units."""
    from viewer.gl.bindings import BACKEND_IMAGE, IMAGE

    src = load_shader_source(path.name, _variants(path)[-1], (path.parent,))
    counts = {"ssbo": len(re.findall(r"\bbuffer\s+\w+\s*\{", src)),
              "image": len(re.findall(r"\buniform\s+(?:\w+\s+)*[iu]?image\w+\s+\w+", src)),
              "sampler": len(re.findall(r"\buniform\s+[iu]?sampler\w+\s+\w+", src))}
    assert all(counts[k] <= v for k, v in NV_STAGE_LIMITS.items()), f"{path.name}: {counts}"
    assert max(*IMAGE.values(), *BACKEND_IMAGE) < NV_STAGE_LIMITS["image"]


# -- OpenCL ----------------------------------------------------------------------------------------

# renders that build every program the CL backends use (with the variants whose sizes differ)
CL_RENDERS = (("clbvh", "", "device"), ("ugrid", "", "sah"), ("pgrid", "chunk=256", "sah"),
              ("voxelwalk", "", "sah"), ("voxelwalk", "sort=global,chunk=128", "sah"), ("voxels", "", "sah"))


@pytest.fixture(scope="module")
def cl_programs(tmp_path_factory) -> list[tuple[str, tuple[tuple[str, str], ...], object]]:
    """(source, defines, built program) of every program the renders built, sized for a 48 KiB
    device (RTWALK_CL_LOCAL_KIB=48, as NVIDIA's OpenCL reports)."""
    from viewer.cl import programs

    out = tmp_path_factory.mktemp("portability")
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(programs, "_cache", {})
        mp.setenv("RTWALK_CL_LOCAL_KIB", "48")
        for k, (backend, params, builder) in enumerate(CL_RENDERS):
            args = ["render", "room", "--backend", backend, "--effects", "all", "--size", "48x32", "--quiet",
                    "--bvh-builder", builder, "--denoise", "off", "-o", str(out / f"{k}-{backend}.png")]
            r = run_cli(*args, *(["--backend-params", params] if params else []))
            assert r.returncode == 0, r.stderr
        return [(src, opts, prog) for (src, opts, _), prog in programs._cache.items()]


@needs_cl
def test_cl_programs_cover_the_backends(cl_programs):
    names = {k.function_name for *_, prog in cl_programs for k in prog.all_kernels()}
    for kernel in ("trace_closest", "raygen", "accumulate", "ec_tile", "ivw_trace"):
        assert kernel in names


@needs_cl
def test_kernels_fit_nvidia_local_memory_and_group_size(cl_programs):
    """CL_KERNEL_LOCAL_MEM_SIZE (the static __local arrays, as the compiler counts them) within
    NVIDIA's 48 KiB and any reqd_work_group_size within 1024 work-items."""
    from viewer.cl import cl_context

    ctx = cl_context()
    info = ctx.cl.kernel_work_group_info
    for _, opts, prog in cl_programs:
        for k in prog.all_kernels():
            local = k.get_work_group_info(info.LOCAL_MEM_SIZE, ctx.device)
            assert local <= NV_LOCAL_BYTES, f"{k.function_name} {opts}: {local} bytes of local memory"
            reqd = k.get_work_group_info(info.COMPILE_WORK_GROUP_SIZE, ctx.device)
            assert int(np.prod(reqd)) <= NV_MAX_GROUP, f"{k.function_name} {opts}: work-group {reqd}"


@needs_cl
@pytest.mark.skipif(CLANG is None, reason="no clang with the NVPTX target (PoCL's apt package brings clang)")
def test_cl_programs_compile_for_nvidia_as_opencl_c_1_2(cl_programs, tmp_path):
    """clang's NVIDIA target with the extensions NVIDIA's driver reports (fp64, 64-bit atomics):
    OpenCL C 1.2 only, warnings are errors; and the optimised PTX holds no fused multiply-add (the
    FP_CONTRACT OFF prelude holds on an LLVM NVPTX back end, which fuses by default: the numeric
    contract, docs/numerics.md)."""
    for n, (src, opts, _) in enumerate(cl_programs):
        f = tmp_path / f"p{n}.cl"
        f.write_text(src)
        defines = [f"-D{k}={v}" if v != "" else f"-D{k}" for k, v in opts]
        cmd = [CLANG, "-target", "nvptx64-nvidia-nvcl", "-x", "cl", "-cl-std=CL1.2", "-Xclang",
               "-finclude-default-header", "-Xclang",
               "-cl-ext=+cl_khr_fp64,+cl_khr_int64_base_atomics,+cl_khr_int64_extended_atomics",
               "-O2", "-S", "-o", str(f.with_suffix(".ptx")), "-Werror", *defines, str(f)]
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
        kernels = re.findall(r"__kernel\b[^(]*?(\w+)\s*\(", src)[:3]
        assert r.returncode == 0, f"{kernels} {defines}: {r.stderr[:1500]}"
        fused = re.findall(r"\b(?:fma|mad)(?:\.\w+)*\.f(?:32|64)\b", f.with_suffix(".ptx").read_text())
        assert not fused, f"{kernels} {defines}: {sorted(set(fused))}"


@needs_cl
def test_voxelwalk_refuses_a_chunk_over_the_local_memory(monkeypatch, tmp_path):
    """chunk=256 needs 62 KiB of local memory per work-group (ec_tile.cl): on a 48 KiB device one
    line naming the chunk that fits, not a build failure."""
    monkeypatch.setenv("RTWALK_CL_LOCAL_KIB", "48")
    r = run_cli("render", "room", "--backend", "voxelwalk", "--backend-params", "chunk=256", "--size", "32x24",
                "--quiet", "-o", str(tmp_path / "x.png"))
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0, r.stderr
    assert r.stderr.startswith("rtwalk: error: voxelwalk chunk=256:") and "choose chunk <= 128" in r.stderr
    monkeypatch.setenv("RTWALK_CL_LOCAL_KIB", "lots")
    r = run_cli("render", "room", "--backend", "voxelwalk", "--size", "32x24", "--quiet", "-o", str(tmp_path / "x.png"))
    assert r.returncode == 2 and "RTWALK_CL_LOCAL_KIB='lots': not a number of KiB" in r.stderr
    from viewer.backends.voxelwalk.engine import check_tile_local
    from viewer.errors import RtwalkError

    check_tile_local(NV_LOCAL_BYTES, 128)
    with pytest.raises(RtwalkError, match=r"chunk=256: .* 62\.0 KiB .* 48\.0 KiB; choose chunk <= 128"):
        check_tile_local(NV_LOCAL_BYTES, 256)


@needs_cl
def test_voxelwalk_on_48_kib_matches_ivw(monkeypatch):
    """The one-launch EC with the partitions a 48 KiB device gets (128 rays instead of PoCL's 1024)
    returns IVW's hits bit for bit; chunk=256 stops with one line there."""
    from tests.test_voxelwalk import EC, _rays, _scene
    from viewer.errors import RtwalkError
    from viewer.tracing import trace_rays

    tris = _scene()
    o, d, lo, hi = _rays(2000, seed=3)
    monkeypatch.setenv("RTWALK_VOXELWALK", "mode=ivw")
    t0, i0 = trace_rays(tris, o, d, lo, hi, backend="voxelwalk")
    monkeypatch.setenv("RTWALK_CL_LOCAL_KIB", "48")
    for chunk in (32, 128):
        monkeypatch.setenv("RTWALK_VOXELWALK", f"{EC},chunk={chunk}")
        t, i = trace_rays(tris, o, d, lo, hi, backend="voxelwalk")
        assert np.array_equal(t.view(np.uint32), t0.view(np.uint32)) and np.array_equal(i, i0)
    monkeypatch.setenv("RTWALK_VOXELWALK", f"{EC},chunk=256")
    with pytest.raises(RtwalkError, match="local memory"):
        trace_rays(tris, o, d, lo, hi, backend="voxelwalk")
