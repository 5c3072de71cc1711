"""The one OpenGL context (moderngl, headless EGL) and everything made in it.

All GL state lives in a `GLContext` that the caller creates once and passes first
(as nvdiffrast's `RasterizeGLContext`): `ctx = GLContext(); rasterize(ctx, ...)`. Nothing
is kept at module level; a worker process creates its own context.
"""

from __future__ import annotations

from collections import OrderedDict
from contextlib import contextmanager
from functools import lru_cache
from typing import Iterator

from mvtex.util.errors import InputError
from mvtex.util.resources import resource_path


@lru_cache(maxsize=None)
def _shader_source(name: str) -> str:

    return resource_path("shaders", name).read_text()


class GLContext:
    """An OpenGL 3.3 context (moderngl, standalone) and everything made in it: compiled
    programs, framebuffers, the fabric texture and the buffers of `rasterize_pair`.

    Create one per process (or thread) and pass it to every rasterization function;
    `release()` frees it. Every function makes it current for its own duration, so several
    contexts can live in one process.

    Args:
        backend: moderngl backend; "egl" (default) works headless. If the EGL context
            cannot be created, the platform default is tried before giving up.

    Raises:
        RuntimeError: no OpenGL 3.3 context could be created (with install hints).
    """

    def __init__(self, backend: str | None = "egl"):
        import moderngl  # noqa: PLC0415 (loaded on use)

        errors = []
        mgl = None
        for kwargs in ({"backend": backend} if backend else {}, {}):
            try:
                mgl = moderngl.create_standalone_context(require=330, **kwargs)
                break
            except Exception as err:  # moderngl/glcontext raise plain Exceptions
                errors.append(f"{kwargs or 'default'}: {err}")
        if mgl is None:
            raise RuntimeError("no OpenGL 3.3 context could be created (needs EGL: on Debian "
                               "libegl1 libegl-mesa0 libgl1-mesa-dri libgbm1, or an NVIDIA driver): "
                               + "; ".join(errors))
        self.mgl: moderngl.Context = mgl
        with self.mgl:  # read once here: leaving a nested `with` would release a caller's current context
            info = self.mgl.info
            self._max_size = int(min(info["GL_MAX_TEXTURE_SIZE"], info["GL_MAX_RENDERBUFFER_SIZE"],
                                     *info["GL_MAX_VIEWPORT_DIMS"]))
        self._programs: dict = {}
        self._targets: OrderedDict = OrderedDict()
        self._pairs: OrderedDict = OrderedDict()
        self._fabric: dict = {}

    @property
    def renderer(self) -> str:
        """The GL renderer string (e.g. 'llvmpipe (...)' or an NVIDIA GPU)."""
        with self.mgl:
            return str(self.mgl.info["GL_RENDERER"])

    @property
    def max_size(self) -> int:
        """The largest framebuffer side this GL draws into (texture, renderbuffer and
        viewport limits together; 16384 on llvmpipe)."""
        return self._max_size

    @property
    def error(self) -> str:
        """The GL error flag ("GL_NO_ERROR" when none; reading it clears it)."""
        with self.mgl:
            return str(self.mgl.error)

    def release(self) -> None:
        """Free the context and everything made in it; the object is unusable afterwards."""
        if self.mgl is not None:
            self.mgl.release()
            self.mgl = None
        self._programs.clear(), self._targets.clear(), self._pairs.clear(), self._fabric.clear()

    def __enter__(self) -> "GLContext":
        return self

    def __exit__(self, *exc) -> None:
        self.release()

    # -- cached GL objects (call with the context current) ------------------------------
    def _program(self, vertex: str, fragment: str):
        key = (vertex, fragment)
        if key not in self._programs:
            self._programs[key] = self.mgl.program(vertex_shader=_shader_source(vertex),
                                                   fragment_shader=_shader_source(fragment))
        return self._programs[key]

    def _target(self, kind: str, width: int, height: int, slot: int = 0):
        """A framebuffer of `kind` "ids" (R32I ids + RGBA32F attributes + depth), "pair"
        (R32I ids twice as wide + depth) or "color" (RGBA8 + depth), kept for reuse:
        releasing the bound framebuffer leaves GL with no valid draw target. `slot` tells
        apart framebuffers of one kind and size that are used together."""
        key = (kind, width, height, slot)
        if key not in self._targets:
            wide = 2 * width if kind == "pair" else width
            if max(wide, height) > self.max_size:

                raise InputError(None, f"an image of {width}x{height} pixels is larger than this OpenGL draws "
                                 f"({self.max_size} pixels a side at most); use smaller camera images")
            ctx = self.mgl
            if kind == "ids":
                attachments = [ctx.texture((width, height), 1, dtype="i4"), ctx.texture((width, height), 4, dtype="f4")]
            elif kind == "pair":
                attachments = [ctx.texture((2 * width, height), 1, dtype="i4")]
            else:
                attachments = [ctx.texture((width, height), 4)]
            size = attachments[0].size
            self._targets[key] = ctx.framebuffer(color_attachments=attachments,
                                                 depth_attachment=ctx.depth_renderbuffer(size))
            if len(self._targets) > 8:
                _, old = self._targets.popitem(last=False)
                _release_framebuffer(ctx, old)
        self._targets.move_to_end(key)
        return self._targets[key]


@contextmanager
def context_or_new(ctx: GLContext | None) -> Iterator[GLContext]:
    """`ctx` itself when given; otherwise a new `GLContext`, released when the block ends.

    For library functions whose `ctx` argument is optional:
    `with context_or_new(ctx) as ctx: rasterize(ctx, ...)`.
    """
    if ctx is not None:
        yield ctx
        return
    with GLContext() as own:
        yield own


def _release_framebuffer(mgl, fbo) -> None:
    # moderngl rebinds its last used framebuffer when it creates the next one: binding a
    # released one is GL_INVALID_OPERATION. Leave the default framebuffer bound instead.
    if mgl.fbo is fbo:
        mgl.detect_framebuffer(0).use()
    for attachment in list(fbo.color_attachments) + [fbo.depth_attachment]:
        if attachment is not None:
            attachment.release()
    fbo.release()
