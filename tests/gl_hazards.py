"""GL memory hazards: what a shader wrote, read again without the glMemoryBarrier bit its path needs.

GL orders its commands, except for what shaders write through incoherent paths: shader storage
blocks and image stores or atomics. A later command sees those writes only after a
glMemoryBarrier whose bits name the path that command reads (or writes) the memory through: another
shader's SSBO (SHADER_STORAGE) or image (SHADER_IMAGE_ACCESS) access, a texel fetch of a texture or
buffer texture (TEXTURE_FETCH), an indirect command (COMMAND), a buffer's or texture's update, read,
copy or clear (BUFFER_UPDATE, TEXTURE_UPDATE), a framebuffer attachment (FRAMEBUFFER), a vertex or
index buffer (VERTEX_ATTRIB_ARRAY, ELEMENT_ARRAY), a uniform block (UNIFORM). Mesa's llvmpipe runs
most commands in order and forgives a missing bit; an NVIDIA driver need not (the first H100 run of
rtwalk found what Mesa forgave). So this recorder follows every dispatch, draw, copy, clear, host
read and write and barrier of a run, with the buffers and textures bound where each program's
active interface looks (its storage blocks, images, samplers and uniform blocks: from GL's
introspection which are active and where, from the program's source which are readonly or
writeonly), and lists each access to memory a shader wrote, through a path no barrier since has
covered. The same on every device: CI checks on llvmpipe what an NVIDIA GPU would need.

Atomics: a storage block or image that a program touches only through atomic functions (every use
of its members, or of the image, is the first argument of an atomic*/imageAtomic* call) makes
atomic accesses; atomic operations on the same memory are atomic with respect to each other in
any commands (they are performed where every invocation sees them), so an atomic access after
another command's atomic writes needs no barrier (counters that several passes add to). Anything
else after atomic writes does. Monotone images: an image whose declaration says `// hazards:
monotone` only falls (imageAtomicMin) between its stores, and a stale value read through imageLoad
is a looser bound, never a wrong one (chcrt's best hit per pixel: the draws of one pass read and
lower it); a program that only loads it and lowers it makes monotone accesses, which need no
barrier after monotone writes. A store (a new pass's initial values) still needs one on each side.

Not followed: atomic counter buffers and query buffers (rtwalk uses neither), transform feedback,
and client-mapped buffers; programs not made through viewer.gl.programs (their interface is
unknown) are listed in `unknown_programs`.
"""

from __future__ import annotations

import re
import traceback
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

import moderngl
import numpy as np
import pytest

import viewer.gl.textures as gl_textures

PATH_BITS = {
    "ssbo": moderngl.SHADER_STORAGE_BARRIER_BIT,
    "image": moderngl.SHADER_IMAGE_ACCESS_BARRIER_BIT,
    "fetch": moderngl.TEXTURE_FETCH_BARRIER_BIT,
    "command": moderngl.COMMAND_BARRIER_BIT,
    "buffer_update": moderngl.BUFFER_UPDATE_BARRIER_BIT,
    "texture_update": moderngl.TEXTURE_UPDATE_BARRIER_BIT,
    "framebuffer": moderngl.FRAMEBUFFER_BARRIER_BIT,
    "vertex": moderngl.VERTEX_ATTRIB_ARRAY_BARRIER_BIT,
    "element": moderngl.ELEMENT_ARRAY_BARRIER_BIT,
    "uniform": moderngl.UNIFORM_BARRIER_BIT,
}
SHADER_WRITE_PATHS = ("ssbo", "image")  # the paths whose writes need a barrier to be seen

_QUALS = r"((?:(?:readonly|writeonly|coherent|volatile|restrict)\s+)*)"
_BLOCK = re.compile(_QUALS + r"buffer\s+(\w+)\s*\{([^}]*)\}")
_LAYOUT = r"(?:layout\s*\(([^)]*)\)\s*)?"
_IMAGE = re.compile(_LAYOUT + r"\buniform\s+" + _QUALS + r"[iu]?image\w+\s+(\w+)\s*;")
_SAMPLER = re.compile(_LAYOUT + r"\buniform\s+(?:(?:lowp|mediump|highp)\s+)?[iu]?sampler\w+\s+(\w+)\s*;")
_DEFINE = re.compile(r"^\s*#\s*define\s+(\w+)\s+(\S+)\s*$", re.MULTILINE)

_COMMENT = re.compile(r"//[^\n]*|/\*.*?\*/", re.DOTALL)
# an image declared with this comment on its line: `uniform ... iimage2D name;  // hazards: monotone`
_MONOTONE = re.compile(r"\b[iu]?image\w*\s+(\w+)\s*;[^\n]*//[^\n]*\bhazards:\s*monotone")

Resource = tuple[str, int]  # ("buf" | "tex", GL name)


@dataclass(frozen=True)
class Access:
    resource: Resource
    path: str  # a PATH_BITS key
    write: bool
    kind: str | None = None  # "atomic" or "monotone" (the module's docstring): no barrier after its own kind
    name: str = ""  # the storage block or uniform it goes through


@dataclass(frozen=True)
class Hazard:
    command: str  # what accessed (its program, or the call), and through which block or uniform
    resource: Resource
    path: str
    writer: str  # the command whose shader write is not yet visible on `path`, and its block or uniform
    where: str = ""  # the caller of the access (file:line in viewer/)
    writer_where: str = ""

    def __str__(self) -> str:
        return (f"{self.command} at {self.where} accesses {self.resource[0]} {self.resource[1]} through "
                f"{self.path} after {self.writer} at {self.writer_where} wrote it, with no {self.path} "
                f"barrier between")


@dataclass
class Interface:
    """A program's active storage blocks (binding -> (writes, kind)), images (unit -> (writes,
    kind)), sampler units and uniform block bindings."""

    ssbo: dict[int, tuple[bool, str | None]] = field(default_factory=dict)
    images: dict[int, tuple[bool, str | None]] = field(default_factory=dict)
    samplers: set[int] = field(default_factory=set)
    ubos: set[int] = field(default_factory=set)
    names: dict[tuple[str, int], str] = field(default_factory=dict)  # (kind, binding or unit) -> name


def _calls(src: str, names: list[str], declared_at: int) -> list[str] | None:
    """The function each use of `names` in `src` is the first argument of (other than their
    declaration, on the line at `declared_at`); None where a use is no such argument."""
    out = []
    for n in names:
        for m in re.finditer(r"\b" + re.escape(n) + r"\b", src):
            if src.rfind("\n", 0, m.start()) < declared_at <= m.start():
                continue  # the declaration itself (on the block's or uniform's line)
            call = re.search(r"\b(\w+)\(\s*$", src[max(0, m.start() - 40):m.start()])
            if call is None:
                return None
            out.append(call.group(1))
    return out


def _kind(calls: list[str] | None, monotone: bool) -> str | None:
    """"atomic": every use is an atomic function's; "monotone" (an image so annotated): every use
    is imageLoad or imageAtomicMin."""
    if not calls:
        return None
    if all(re.match(r"(?:image)?[aA]tomic", c) for c in calls):
        return "atomic"
    if monotone and all(c in ("imageLoad", "imageAtomicMin") for c in calls):
        return "monotone"
    return None


def _preprocess(src: str) -> str:
    """`src` without the lines its #if/#ifdef/#ifndef/#elif/#else blocks leave out (the program's
    #defines applied; an #if this cannot evaluate counts as true: its code is kept, which can only
    find more accesses)."""
    defines: dict[str, str] = {}
    out, stack = [], []  # stack: (this branch on, some branch taken, the enclosing block on)

    def value(expr: str) -> bool:
        e = re.sub(r"\bdefined\s*\(\s*(\w+)\s*\)|\bdefined\s+(\w+)",
                   lambda m: "1" if (m.group(1) or m.group(2)) in defines else "0", expr)
        for _ in range(4):
            e = re.sub(r"\b[A-Za-z_]\w*\b", lambda m: defines.get(m.group(0), "0") or "0", e)
        e = e.replace("&&", " and ").replace("||", " or ")
        e = re.sub(r"!(?!=)", " not ", e)
        try:
            return bool(eval(e, {"__builtins__": {}}))  # (integers and operators only, from our own shaders)
        except Exception:
            return True

    for line in src.splitlines():
        m = re.match(r"\s*#\s*(\w+)\s*(.*)", line)
        on = all(s[0] for s in stack)
        d = m.group(1) if m else ""
        if d in ("ifdef", "ifndef", "if"):
            rest = m.group(2).strip()
            cond = (rest.split()[0] in defines) if d == "ifdef" else (
                rest.split()[0] not in defines) if d == "ifndef" else value(rest)
            stack.append([cond, cond])
        elif d == "elif" and stack:
            cond = not stack[-1][1] and value(m.group(2))
            stack[-1] = [cond, stack[-1][1] or cond]
        elif d == "else" and stack:
            stack[-1] = [not stack[-1][1], True]
        elif d == "endif" and stack:
            stack.pop()
        elif on:
            if d == "define":
                parts = m.group(2).split(None, 1)
                if parts and "(" not in parts[0]:
                    defines[parts[0]] = parts[1].split("//")[0].strip() if len(parts) > 1 else ""
            elif d == "undef":
                defines.pop(m.group(2).strip(), None)
            out.append(line)
    return "\n".join(out)


def _block_members(body: str) -> list[str]:
    return [m.group(1) for m in re.finditer(r"(\w+)\s*(?:\[[^\]]*\])?\s*;", body)]


def program_interface(prog) -> Interface | None:
    """`prog`'s active interface, or None for a program without its sources (viewer.gl.inactive.mark)."""
    extra = getattr(prog, "extra", None)
    sources = extra.get("sources") if isinstance(extra, dict) else None
    if not sources:
        return None
    raw = "\n".join(_preprocess(s) for s in sources if s)
    monotone = set(_MONOTONE.findall(raw))
    src = _COMMENT.sub(" ", raw)
    blocks = {m.group(2): ("readonly" not in m.group(1),
                           _kind(_calls(src, _block_members(m.group(3)), m.start()), False))
              for m in _BLOCK.finditer(src)}
    iface = Interface()
    names = set(prog)
    for name in names:
        member = prog[name]
        if isinstance(member, moderngl.StorageBlock):
            iface.ssbo[member.binding] = blocks.get(name, (True, None))
            iface.names["ssbo", member.binding] = name
        elif isinstance(member, moderngl.UniformBlock):
            iface.ubos.add(member.binding)
    defines = dict(_DEFINE.findall(src))
    for m in _IMAGE.finditer(src):
        name = m.group(3)
        if name in names:  # (else declared, but removed by the compiler)
            unit = _unit(prog, name, m.group(1), defines)
            iface.images[unit] = ("readonly" not in m.group(2), _kind(_calls(src, [name], m.start()), name in monotone))
            iface.names["image", unit] = name
    for m in _SAMPLER.finditer(src):
        name = m.group(2)
        if name in names:
            unit = _unit(prog, name, m.group(1), defines)
            iface.samplers.add(unit)
            iface.names["fetch", unit] = name
    return iface


def _unit(prog, name: str, layout: str | None, defines: dict[str, str]) -> int:
    """The unit of an image or sampler uniform: its layout's binding (a number or a #define), else
    the value the program holds (moderngl reads a layout-bound image uniform's value wrongly)."""
    m = re.search(r"\bbinding\s*=\s*(\w+)", layout or "")
    if m is None:
        return int(prog[name].value)
    token = m.group(1)
    for _ in range(8):  # (a define may name another)
        if token.isdigit():
            return int(token)
        token = defines[token]
    raise ValueError(f"binding {m.group(1)} of {name}: no number")


class HazardRecorder:
    """Follows the GL state and commands of a run (`installed` patches moderngl and the raw GL
    calls of viewer.gl.textures) and collects the hazards."""

    def __init__(self):
        self.ssbo: dict[int, int] = {}  # binding -> buffer
        self.ubo: dict[int, int] = {}
        self.images: dict[int, int] = {}  # unit -> texture
        self.units: dict[int, Resource] = {}  # texture unit -> texture or buffer (a buffer texture)
        self.buffer_textures: dict[int, int] = {}  # buffer texture name -> buffer
        self.vao_buffers: dict[int, tuple[list[int], int | None]] = {}  # vao id -> (vertex buffers, index buffer)
        self.fbo: moderngl.Framebuffer | None = None
        # per resource a shader wrote: the paths not yet fenced, the writer, the kind of its writes, where
        self.pending: dict[Resource, tuple[set[str], str, str | None, str]] = {}
        self.hazards: list[Hazard] = []
        self.unknown_programs: set[str] = set()
        self.commands: dict[str, int] = {}
        self._interfaces: dict[int, Interface | None] = {}
        self._read_args = None  # (buffer, size, offset) -> bytes, unrecorded (installed)

    # ----------------------------------------------------------------------------- the model
    def _command(self, what: str, accesses: list[Access]) -> None:
        self.commands[what] = self.commands.get(what, 0) + 1
        where = _caller()
        for a in accesses:
            pend = self.pending.get(a.resource)
            if pend is not None and a.path in pend[0] and not (a.kind is not None and a.kind == pend[2]):
                self.hazards.append(Hazard(f"{what} ({a.name})" if a.name else what, a.resource, a.path, pend[1],
                                           where, pend[3]))
                pend[0].discard(a.path)  # (one report per write and path)
        for a in accesses:
            if a.write and a.path in SHADER_WRITE_PATHS:
                old = self.pending.get(a.resource)
                # (atomics after a plain write that their path has not seen yet stay unordered with it)
                kind = a.kind if old is None or a.path not in old[0] or old[2] == a.kind else None
                self.pending[a.resource] = (set(PATH_BITS), f"{what} ({a.name})" if a.name else what, kind, where)

    def barrier(self, bits: int) -> None:
        paths = {p for p, b in PATH_BITS.items() if bits & b}
        for pend in self.pending.values():
            pend[0].difference_update(paths)

    def forget(self, resource: Resource) -> None:
        """An object released, or a new one under a reused name: nothing of the old one is pending
        or bound (GL unbinds a deleted object from the current context's binding points)."""
        self.pending.pop(resource, None)
        kind, name = resource
        maps = (self.ssbo, self.ubo) if kind == "buf" else (self.images,)
        for m in maps:
            for k in [k for k, v in m.items() if v == name]:
                del m[k]
        for k in [k for k, v in self.units.items() if v == resource]:
            del self.units[k]

    def _interface(self, prog) -> Interface | None:
        key = id(prog)
        if key not in self._interfaces:
            self._interfaces[key] = program_interface(prog)
        return self._interfaces[key]

    def _shader_accesses(self, prog, label: str) -> list[Access]:
        iface = self._interface(prog)
        if iface is None:
            self.unknown_programs.add(label)
            return []
        out = []
        for binding, (w, kind) in iface.ssbo.items():
            if binding in self.ssbo:
                out.append(Access(("buf", self.ssbo[binding]), "ssbo", w, kind, iface.names["ssbo", binding]))
        for unit, (w, kind) in iface.images.items():
            if unit in self.images:
                out.append(Access(("tex", self.images[unit]), "image", w, kind, iface.names["image", unit]))
        for unit in iface.samplers:
            if unit in self.units:
                out.append(Access(self.units[unit], "fetch", False, name=iface.names["fetch", unit]))
        for binding in iface.ubos:
            if binding in self.ubo:
                out.append(Access(("buf", self.ubo[binding]), "uniform", False))
        return out

    def dispatch(self, prog, indirect: moderngl.Buffer | None, offset: int = 0) -> None:
        label = _label(prog)
        if indirect is not None and self._read_args is not None:
            groups = np.frombuffer(self._read_args(indirect, 12, offset), np.uint32)
            if not groups.all():  # no invocation: nothing is accessed but the command itself
                self._command(f"dispatch {label}", [Access(("buf", indirect.glo), "command", False)])
                return
        acc = self._shader_accesses(prog, label)
        if indirect is not None:
            acc.append(Access(("buf", indirect.glo), "command", False))
        self._command(f"dispatch {label}", acc)

    def draw(self, vao: moderngl.VertexArray, indirect: moderngl.Buffer | None) -> None:
        label = _label(vao.program)
        acc = self._shader_accesses(vao.program, label)
        if indirect is not None:
            acc.append(Access(("buf", indirect.glo), "command", False))
        vbufs, ibuf = self.vao_buffers.get(id(vao), ([], None))
        acc += [Access(("buf", b), "vertex", False) for b in vbufs]
        if ibuf is not None:
            acc.append(Access(("buf", ibuf), "element", False))
        acc += self._attachments(write=True)
        self._command(f"draw {label}", acc)

    def _attachments(self, write: bool) -> list[Access]:
        return [] if self.fbo is None else self._attachments_of(self.fbo, write)

    def buffer_op(self, what: str, buf_glo: int, write: bool) -> None:
        self._command(what, [Access(("buf", buf_glo), "buffer_update", write)])

    def texture_op(self, what: str, tex_glo: int, write: bool) -> None:
        self._command(what, [Access(("tex", tex_glo), "texture_update", write)])

    # ------------------------------------------------------------------------------ the hooks
    @contextmanager
    def installed(self, monkeypatch: pytest.MonkeyPatch) -> Iterator[HazardRecorder]:
        rec = self

        def wrap(cls, name, before):
            orig = getattr(cls, name)

            def wrapped(obj, *a, **k):
                before(obj, *a, **k)
                return orig(obj, *a, **k)
            monkeypatch.setattr(cls, name, wrapped)

        def make(cls, name, after):
            orig = getattr(cls, name)

            def wrapped(obj, *a, **k):
                res = orig(obj, *a, **k)
                after(res)
                return res
            monkeypatch.setattr(cls, name, wrapped)

        def arg(a, k, i, key, default=None):
            return a[i] if len(a) > i else k.get(key, default)

        ctx_cls = moderngl.Context
        orig_read, orig_barrier = moderngl.Buffer.read, ctx_cls.memory_barrier  # (unrecorded)
        wrap(moderngl.Buffer, "bind_to_storage_buffer",
             lambda b, *a, **k: rec.ssbo.__setitem__(arg(a, k, 0, "binding", 0), b.glo))
        wrap(moderngl.Buffer, "bind_to_uniform_block",
             lambda b, *a, **k: rec.ubo.__setitem__(arg(a, k, 0, "binding", 0), b.glo))
        for tcls in (moderngl.Texture, moderngl.Texture3D, moderngl.TextureArray, moderngl.TextureCube):
            hooks = {"bind_to_image": lambda t, *a, **k: rec.images.__setitem__(arg(a, k, 0, "unit"), t.glo),
                     "use": lambda t, *a, **k: rec.units.__setitem__(arg(a, k, 0, "location", 0), ("tex", t.glo)),
                     "read": lambda t, *a, **k: rec.texture_op("texture read", t.glo, False),
                     "read_into": lambda t, *a, **k: rec.texture_op("texture read", t.glo, False),
                     "write": lambda t, *a, **k: rec.texture_op("texture write", t.glo, True),
                     "release": lambda t, *a, **k: rec.forget(("tex", t.glo))}
            for name, hook in hooks.items():
                if hasattr(tcls, name):
                    wrap(tcls, name, hook)
        wrap(moderngl.Buffer, "read", lambda b, *a, **k: rec.buffer_op("buffer read", b.glo, False))
        wrap(moderngl.Buffer, "read_into", lambda b, *a, **k: rec.buffer_op("buffer read", b.glo, False))
        wrap(moderngl.Buffer, "write", lambda b, *a, **k: rec.buffer_op("buffer write", b.glo, True))
        wrap(moderngl.Buffer, "clear", lambda b, *a, **k: rec.buffer_op("buffer clear", b.glo, True))
        wrap(moderngl.Buffer, "orphan", lambda b, *a, **k: rec.pending.pop(("buf", b.glo), None))
        wrap(moderngl.Buffer, "release", lambda b, *a, **k: rec.forget(("buf", b.glo)))
        wrap(moderngl.Framebuffer, "use", lambda f, *a, **k: setattr(rec, "fbo", f))
        wrap(moderngl.Framebuffer, "clear", lambda f, *a, **k: rec._command("framebuffer clear",
                                                                             rec._attachments_of(f, True)))
        wrap(moderngl.Framebuffer, "read", lambda f, *a, **k: rec._command("framebuffer read",
                                                                            rec._attachments_of(f, False)))
        wrap(moderngl.Framebuffer, "read_into", lambda f, *a, **k: rec._command("framebuffer read",
                                                                                 rec._attachments_of(f, False)))
        wrap(moderngl.ComputeShader, "run", lambda p, *a, **k: rec.dispatch(p, None))
        wrap(moderngl.ComputeShader, "run_indirect",
             lambda p, *a, **k: rec.dispatch(p, arg(a, k, 0, "buffer"), arg(a, k, 1, "offset", 0)))

        def read_args(buf: moderngl.Buffer, size: int, offset: int) -> bytes:
            # (a barrier of its own, unrecorded: the arguments a shader wrote, as the dispatch will see them)
            orig_barrier(buf.ctx, moderngl.BUFFER_UPDATE_BARRIER_BIT)
            return orig_read(buf, size, offset)
        self._read_args = read_args
        wrap(moderngl.VertexArray, "render", lambda v, *a, **k: rec.draw(v, None))
        wrap(moderngl.VertexArray, "render_indirect", lambda v, *a, **k: rec.draw(v, arg(a, k, 0, "buffer")))
        wrap(ctx_cls, "memory_barrier",
             lambda c, *a, **k: rec.barrier(int(arg(a, k, 0, "barriers", moderngl.ALL_BARRIER_BITS))))
        wrap(ctx_cls, "copy_buffer", lambda c, dst, src, *a, **k: (rec.buffer_op("buffer copy", src.glo, False),
                                                                    rec.buffer_op("buffer copy", dst.glo, True)))
        make(ctx_cls, "buffer", lambda b: rec.forget(("buf", b.glo)))
        for name in ("texture", "depth_texture", "texture3d", "texture_array", "texture_cube"):
            make(ctx_cls, name, lambda t: rec.forget(("tex", t.glo)))

        def vertex_array(c, program, content=(), index_buffer=None, *a, **k):
            vao = orig_va(c, program, content, index_buffer, *a, **k)
            vbufs = [item[0].glo for item in content or () if item and isinstance(item[0], moderngl.Buffer)]
            ib = index_buffer if index_buffer is not None else k.get("index_buffer")
            rec.vao_buffers[id(vao)] = (vbufs, ib.glo if ib is not None else None)
            return vao
        orig_va = ctx_cls.vertex_array
        monkeypatch.setattr(ctx_cls, "vertex_array", vertex_array)

        # the raw GL calls of viewer.gl.textures (copies, clears, buffer textures)
        gl = dict(gl_textures._gl())

        def raw(name, before):
            f = gl[name]

            def wrapped(*a):
                before(*a)
                return f(*a)
            return wrapped
        patched = dict(gl)
        patched["glCopyImageSubData"] = raw("glCopyImageSubData", lambda *a: (
            rec.texture_op("copy image", a[0], False), rec.texture_op("copy image", a[6], True)))
        patched["glClearTexImage"] = raw("glClearTexImage", lambda *a: rec.texture_op("clear texture", a[0], True))
        patched["glClearNamedBufferSubData"] = raw("glClearNamedBufferSubData",
                                                   lambda *a: rec.buffer_op("clear buffer", a[0], True))
        patched["glTextureBufferRange"] = raw("glTextureBufferRange",
                                              lambda *a: rec.buffer_textures.__setitem__(int(a[0]), int(a[2])))
        patched["glBindTextureUnit"] = raw("glBindTextureUnit", lambda *a: rec._bind_unit(int(a[0]), int(a[1])))
        monkeypatch.setattr(gl_textures, "_gl_funcs", patched)
        try:
            yield self
        finally:
            monkeypatch.setattr(gl_textures, "_gl_funcs", gl)

    def _bind_unit(self, unit: int, name: int) -> None:
        buf = self.buffer_textures.get(name)
        self.units[unit] = ("buf", buf) if buf is not None else ("tex", name)

    def _attachments_of(self, fbo: moderngl.Framebuffer, write: bool) -> list[Access]:
        atts = [*fbo.color_attachments, fbo.depth_attachment]
        return [Access(("tex", t.glo), "framebuffer", write) for t in atts if isinstance(t, moderngl.Texture)]


def _caller() -> str:
    """file:line of the innermost frame in viewer/ outside viewer/gl/ (who issued the command)."""
    for frame in reversed(traceback.extract_stack()[:-2]):
        f = frame.filename.replace("\\", "/")
        if "/viewer/" in f and "/viewer/gl/" not in f:
            return f"{f.split('/viewer/')[-1]}:{frame.lineno}"
    return "?"


def _label(prog) -> str:
    extra = getattr(prog, "extra", None)
    name = extra.get("name") if isinstance(extra, dict) else None
    return name or f"program {prog.glo}"
