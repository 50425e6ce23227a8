"""Mesh rasterization into a G-buffer: moderngl on a headless EGL context, with a NumPy reference twin.

For one :class:`~omnirecon.cameras.Cameras` view of a triangle mesh, :meth:`MeshRasterizer.rasterize`
returns a :class:`GBuffer`: per pixel the nearest triangle (``-1`` = background), its
perspective-correct barycentrics, the camera z-depth, the world surface point and a normal, all at
the pixel centres ``(j + 0.5, i + 0.5)`` of the library's convention (OpenCV frame, row 0 at the
top; ``docs/conventions.md``).

**GL backend** (``backend="gl"``). One EGL context per rasterizer (Mesa llvmpipe on the CPU, the
vendor driver on a GPU; only ``moderngl.create_standalone_context(backend="egl")`` initialises on a
display-less machine). The mesh is uploaded once as an *unindexed* triangle list, so the vertex
shader derives each corner's barycentric unit vector and the triangle id from ``gl_VertexID``
(no extra attributes, no geometry shader: geometry shaders were far slower and wrong on llvmpipe,
``shared/docs/deps.md`` §1). The surface and depth passes, which need no ``gl_VertexID``, draw the shared vertices
by index instead (each vertex shaded once, the faces in :func:`locality_order`; the same pixels, less CPU on large
meshes: only where two faces tie in the 24-bit depth buffer may the other one's z win), and
:meth:`MeshRasterizer.face_ids` draws only the triangle id, from ``gl_PrimitiveID`` of the indexed mesh (the G-buffer's
ids bit for bit, at a fraction of its CPU: the meshing's visible-face cull). Every frame changes only one ``mat4`` uniform. The fragment shader
writes three float/int targets read back without conversion:

* ``R32I``: triangle id + 1 (cleared to 0, so background reads as -1 after the shift);
* ``RGBA32F``: barycentrics (``smooth``, i.e. perspective-correct; clamped to >= 0 and renormalised
  on readback, as llvmpipe's float32 interpolation is off by up to ~3e-4) and the z-depth
  ``1 / gl_FragCoord.w`` (``w_clip`` is camera z by construction of :func:`projection_matrix`);
* ``RGBA32F``: the interpolated world position.

:meth:`MeshRasterizer.surface` (what a per-pixel shader needs) draws with a second program into one
``RGBA32F`` target, ``(world position, z-depth)``, and compacts the covered pixels: about half the
cost of the full G-buffer on llvmpipe. :meth:`MeshRasterizer.depth` draws only the z-depth into one
``R32F`` target (a quarter of that readback, nothing interpolated): the mesh renderer's frame path
unprojects it, ``origin + z d(u, v)``, inside its parallel shading chunks.

The projection maps camera points ``(x, y, z)`` to clip space with ``w_clip = z`` and
``x_ndc = 2 u / W - 1``, ``y_ndc = 2 v / H - 1`` where ``(u, v) = (fx x / z + cx, fy y / z + cy)``:
window coordinates equal our pixel coordinates, GL samples at window ``(j + 0.5, i + 0.5)`` exactly
like us, and since ``glReadPixels`` returns window row 0 first, the buffers come back top row first
with no flip. Our y-down image makes front faces (normal towards the camera) *clockwise* in window
coordinates; back-face culling uses that. Near/far planes default to the z-range of the mesh's
bounding box in the camera (tight, for the 24-bit depth buffer); triangles crossing the near plane
are clipped by GL.

**Reference backend** (``backend="reference"``): :func:`omnirecon.render.zbuffer.rasterize`, the
vectorised float64 z-buffer the procedural scenes were rendered with. It is the test oracle and the
no-GL fallback (``backend="auto"`` picks it when EGL cannot start). It always culls back faces, so
``cull_back_faces=False`` rasterizes the mesh plus its flipped copy; triangles with a vertex at or
behind the near plane are dropped (no clipping). It is much slower than GL (tenths of a CPU-second per 512^2
frame of a procedural scene's mesh).

Threads: llvmpipe reads ``LP_NUM_THREADS`` when the driver loads (the first context in a process).

The GLSL programs of the passes are in :mod:`omnirecon.render.raster_shaders`.

Size: the GL rasterizer and its context handling, the projection matrix and the reference backend are one interface
with two twins; they are kept together so that they stay interchangeable.
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from omnirecon.cameras import Cameras
from omnirecon.errors import InputError
from omnirecon.render.raster_shaders import PROGRAMS

Backend = Literal["auto", "gl", "reference"]
NormalMode = Literal["face", "vertex", "none"]

@dataclass
class GBuffer:
    """What one camera sees of a mesh, per pixel centre (CPU tensors)."""

    face: Tensor
    """Index of the nearest triangle, -1 where no triangle covers the pixel centre. ``# [H, W]`` int64"""
    bary: Tensor
    """Perspective-correct barycentrics of the hit (sum to 1), 0 on background. ``# [H, W, 3]`` float32"""
    depth: Tensor
    """Camera-frame z of the hit (not NDC depth), 0 on background. ``# [H, W]`` float32"""
    points: Tensor
    """World (mesh-frame) surface point ``sum_k bary_k v_k``, 0 on background. ``# [H, W, 3]`` float32"""
    normals: Tensor | None
    """Unit world normals (geometric per face, or interpolated vertex normals), 0 on background;
    ``None`` when not asked for. ``# [H, W, 3]`` float32"""

    @property
    def mask(self) -> Tensor:
        """Pixels covered by a triangle. ``# [H, W]`` bool"""
        return self.face >= 0


@dataclass
class Surface:
    """The covered pixels of one view, compacted: one surface point per pixel (CPU tensors)."""

    pixels: Tensor
    """Flat indices ``i * W + j`` of the covered pixels, increasing (row-major). ``# [P]`` int64"""
    points: Tensor
    """World surface point at each pixel centre. ``# [P, 3]`` float32"""
    depth: Tensor
    """Camera z-depth of each point. ``# [P]`` float32"""
    height: int
    """Image height of the view."""
    width: int
    """Image width of the view."""

    def image(self, values: Tensor, background) -> Tensor:
        """Scatter per-pixel ``values # [P, C]`` into an image filled with ``background`` (a scalar or
        ``C`` values). ``# [H, W, C]``"""
        C = values.shape[1]
        out = torch.as_tensor(background, dtype=values.dtype, device=values.device).expand(
            self.height * self.width, C).clone()
        out[self.pixels.to(values.device)] = values
        return out.reshape(self.height, self.width, C)


# ---------------------------------------------------------------------- camera matrices
def projection_matrix(fx: float, fy: float, cx: float, cy: float, width: int, height: int, near: float,
                      far: float) -> np.ndarray:
    """OpenCV camera frame -> OpenGL clip space for our pixel convention. ``# [4, 4]`` float64

    ``x_clip = (2 fx / W) x + (2 cx / W - 1) z``, ``y_clip = (2 fy / H) y + (2 cy / H - 1) z``,
    ``w_clip = z``, and ``z_ndc`` runs from -1 at ``z = near`` to +1 at ``z = far``. The viewport
    ``(0, 0, W, H)`` then puts camera point ``(x, y, z)`` at window ``(u, v)``, its pixel coordinates,
    with window row 0 = image row 0 (the top).
    """
    P = np.zeros((4, 4))
    P[0, 0], P[0, 2] = 2 * fx / width, 2 * cx / width - 1
    P[1, 1], P[1, 2] = 2 * fy / height, 2 * cy / height - 1
    P[2, 2], P[2, 3] = (far + near) / (far - near), -2 * far * near / (far - near)
    P[3, 2] = 1.0
    return P


def _camera_arrays(camera: Cameras) -> tuple[np.ndarray, np.ndarray]:
    """``K # [3, 3]`` and ``w2c # [4, 4]`` (float64 NumPy) of a one-camera batch."""
    if len(camera) != 1:
        raise ValueError(f"rasterize one camera at a time, got {len(camera)}")
    cam = camera.to(device="cpu", dtype=torch.float64)
    return cam.K[0].numpy(), cam.w2c[0].numpy()


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (zero for unused vertices). ``# [V, 3]`` float64"""
    v = vertices[faces]  # [F, 3, 3]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])  # [F, 3], |n| = 2 area
    out = np.zeros_like(vertices, dtype=np.float64)
    for k in range(3):
        np.add.at(out, faces[:, k], n)
    return out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-20)


def locality_order(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The same triangles, drawn in an order that keeps neighbours together: faces sorted by the Morton code of their
    centroids (10 bits per axis of the mesh's box), vertices renumbered by first use. llvmpipe shades an indexed draw's
    vertices in chunks with a small cache, so a mesh in the scattered order of meshing and decimation shades its shared
    vertices many times over; this order cuts that front end (the depth pass's CPU, most of it on one thread).
    ``(vertices # [V', 3], faces # [F, 3])`` (``V'``: the used vertices)"""
    if not len(faces):
        return vertices, faces
    c = vertices[faces].mean(1)  # [F, 3] centroids
    lo, hi = c.min(0), c.max(0)
    q = ((c - lo) / np.maximum(hi - lo, 1e-12) * 1023).astype(np.uint64)  # [F, 3] in 0..1023
    code = np.zeros(len(faces), np.uint64)
    for bit in range(10):  # interleave the axes' bits
        for axis in range(3):
            code |= ((q[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
    ordered = faces[np.argsort(code, kind="stable")]  # [F, 3]
    flat = ordered.reshape(-1)
    _, first = np.unique(flat, return_index=True)
    used = flat[np.sort(first)]  # [V'] old ids by first use
    remap = np.empty(len(vertices), np.int64)
    remap[used] = np.arange(len(used))
    return vertices[used], remap[ordered]


# ---------------------------------------------------------------------- EGL
_EGL_ERROR: list[str | None] = []


def _make_context():
    """A standalone EGL context; raises the driver's exception when EGL cannot start."""
    if importlib.util.find_spec("triton") is not None:
        # Two LLVMs in one process: importing triton after Mesa's EGL context exists segfaults
        # (deps.md §1); import it (via torch._dynamo, which optimizers pull in) first.
        import torch._dynamo  # noqa: F401
    import moderngl

    return moderngl.create_standalone_context(backend="egl")


_GL: list = []


def gl_flush() -> None:
    """``glFlush`` in the current context (moderngl has none): llvmpipe starts rasterizing and shading what was drawn
    on its threads now, not at the next read-back or framebuffer change. A no-op where libOpenGL cannot be loaded."""
    if not _GL:
        import ctypes
        import ctypes.util

        try:
            _GL.append(ctypes.CDLL(ctypes.util.find_library("OpenGL") or "libOpenGL.so.0").glFlush)
        except (OSError, AttributeError):
            _GL.append(None)
    if _GL[0] is not None:
        _GL[0]()


def gl_unavailable_reason() -> str | None:
    """Why the GL backend cannot run here (``None`` when it can). The probe runs once per process."""
    if not _EGL_ERROR:
        try:
            _make_context().release()
            _EGL_ERROR.append(None)
        except ImportError as e:
            _EGL_ERROR.append(f"moderngl is not installed ({e})")
        except Exception as e:  # noqa: BLE001 - moderngl/glcontext raise plain Exception
            _EGL_ERROR.append(f"no headless EGL context ({str(e).splitlines()[0] if str(e) else type(e).__name__})")
    return _EGL_ERROR[0]


def gl_available() -> bool:
    """Whether ``backend="gl"`` works in this process."""
    return gl_unavailable_reason() is None


# ---------------------------------------------------------------------- the rasterizer
class MeshRasterizer:
    """Rasterizes one fixed triangle mesh from any number of cameras.

    The GL backend keeps one EGL context, the uploaded triangle list, the shader programs and one
    framebuffer per image size and pass for the object's lifetime, so a new frame only uploads a
    camera matrix, draws and reads back. Call :meth:`close` (or use ``with``) to free the context early.

    Args:
        vertices: Vertex positions in the world frame. ``# [V, 3]`` (NumPy or tensor)
        faces: Triangle vertex indices. ``# [F, 3]`` int
        backend: ``"gl"`` (raise :class:`InputError` when EGL is unavailable), ``"reference"``
            (NumPy z-buffer) or ``"auto"`` (GL when it starts, else the reference).
        cull_back_faces: Skip triangles whose geometric normal ``(v1 - v0) x (v2 - v0)`` points away
            from the camera (closed, outward-facing meshes: faster on llvmpipe).
    """

    def __init__(self, vertices, faces, backend: Backend = "auto", cull_back_faces: bool = True):
        self.vertices = np.ascontiguousarray(np.asarray(vertices, dtype=np.float64).reshape(-1, 3))  # [V, 3]
        self.faces = np.ascontiguousarray(np.asarray(faces, dtype=np.int64).reshape(-1, 3))  # [F, 3]
        if len(self.faces) and (self.faces.min() < 0 or self.faces.max() >= len(self.vertices)):
            raise InputError("mesh faces index vertices that do not exist", None, "pass a valid triangle mesh")
        self.cull_back_faces = bool(cull_back_faces)
        self._torch_faces = torch.from_numpy(self.faces)  # [F, 3]
        self._face_normals: Tensor | None = None
        self._vertex_normals: Tensor | None = None
        used = np.unique(self.faces) if len(self.faces) else np.zeros(0, dtype=np.int64)
        pts = self.vertices[used] if len(used) else np.zeros((1, 3))
        lo, hi = pts.min(0), pts.max(0)
        self._corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        self._ctx = None
        if backend not in ("auto", "gl", "reference"):
            raise ValueError(f"unknown rasterizer backend {backend!r}; use 'auto', 'gl' or 'reference'")
        if backend in ("auto", "gl"):
            reason = gl_unavailable_reason()
            if reason is None:
                self._init_gl()
            elif backend == "gl":
                raise InputError(f"the GL rasterizer cannot start: {reason}", None,
                                 "install moderngl (pip install 'omnirecon[raster]') and the Debian packages "
                                 "libegl1 libegl-mesa0 libgl1-mesa-dri, or use backend 'reference'")
        self.backend: str = "gl" if self._ctx is not None else "reference"
        """The backend in use: ``"gl"`` or ``"reference"``."""

    @property
    def context(self):
        """The GL backend's moderngl context (``None`` on the reference backend or once closed): other passes
        (:class:`omnirecon.render.glblend.GLBlend`) draw in it."""
        return self._ctx

    @classmethod
    def from_trimesh(cls, mesh, **kwargs) -> MeshRasterizer:
        """Build from a ``trimesh.Trimesh`` (its vertices and faces as they are)."""
        return cls(np.asarray(mesh.vertices), np.asarray(mesh.faces), **kwargs)

    # ------------------------------------------------------------------ GL setup
    def _init_gl(self) -> None:
        import moderngl

        ctx = _make_context()
        self._ctx = ctx
        self._moderngl = moderngl
        self._programs = {name: ctx.program(vertex_shader=vs, fragment_shader=fs)
                          for name, (vs, fs) in PROGRAMS.items()}
        soup = self.vertices[self.faces].astype("f4")  # [F, 3, 3] unindexed triangle list
        self._vbo = ctx.buffer(soup.tobytes()) if len(self.faces) else None
        self._vaos = {} if self._vbo is None else {"gbuffer": ctx.vertex_array(self._programs["gbuffer"],
                                                                              [(self._vbo, "3f", "in_pos")])}
        # the passes that need no gl_VertexID draw the shared vertices by index (each vertex shaded once, not once per
        # face: less CPU per depth pass, the same depths but for ties in the depth buffer); the face pass
        # reads the triangle id from gl_PrimitiveID (the index of the face in the draw)
        self._indexed = []  # the face pass's mesh as given, the surface and depth passes' in locality_order (less CPU)
        if self._vbo is not None:
            arrays = (self.vertices, self.faces, *locality_order(self.vertices, self.faces))
            self._indexed = [ctx.buffer(a.astype(t).tobytes()) for a, t in zip(arrays, ("f4", "i4") * 2, strict=True)]
        for name in () if self._vbo is None else ("surface", "depth", "face"):
            v, f = self._indexed[:2] if name == "face" else self._indexed[2:]
            self._vaos[name] = ctx.vertex_array(self._programs[name], [(v, "3f", "in_pos")],
                                                index_buffer=f, index_element_size=4)
        self._targets: dict[tuple, tuple] = {}
        ctx.front_face = "cw"  # y-down window coordinates: front faces wind clockwise (module docstring)
        ctx.cull_face = "back"

    def _framebuffer(self, width: int, height: int, kind: str):
        """Framebuffer, its textures and host arrays for one image size and program (created on first
        use, then reused)."""
        key = (width, height, kind)
        if key not in self._targets:
            ctx = self._ctx
            if kind == "gbuffer":
                colors = [ctx.texture((width, height), 1, dtype="i4"), ctx.texture((width, height), 4, dtype="f4"),
                          ctx.texture((width, height), 4, dtype="f4")]
                host = (np.empty((height, width), np.int32), np.empty((height, width, 4), np.float32),
                        np.empty((height, width, 4), np.float32))
            elif kind == "depth":
                colors = [ctx.texture((width, height), 1, dtype="f4")]
                host = (np.empty((height, width), np.float32),)
            elif kind == "face":
                colors = [ctx.texture((width, height), 1, dtype="i4")]
                host = (np.empty((height, width), np.int32),)
            else:
                colors = [ctx.texture((width, height), 4, dtype="f4")]
                host = (np.empty((height, width, 4), np.float32),)
            depth = ctx.depth_texture((width, height))
            fbo = ctx.framebuffer(color_attachments=colors, depth_attachment=depth)
            self._targets[key] = (fbo, (*colors, depth), host)
        return self._targets[key]

    def _draw(self, K, w2c, width, height, near, far, surface: bool | str = False):
        """Draw with GL into reused host buffers (valid until the next draw): ``face + 1 # [H, W]``
        int32 (0 = background), ``(bary, depth) # [H, W, 4]`` and ``(world, 1) # [H, W, 4]`` float32;
        with ``surface``, only ``(world, depth) # [H, W, 4]`` (depth 0 = background); with
        ``surface="depth"``, only the z-depth ``# [H, W]``; with ``surface="face"``, only ``face + 1 # [H, W]``.

        This rasterizer's context is made current first: with several rasterizers alive, the last
        created context would otherwise receive the draw calls (and draw the wrong mesh)."""
        with self._ctx:
            return self._draw_current(K, w2c, width, height, near, far, surface)

    def _draw_current(self, K, w2c, width, height, near, far, surface: bool | str = False, read: bool = True):
        kind = surface if surface in ("depth", "face") else "surface" if surface else "gbuffer"
        auto_near, auto_far = self.depth_range(w2c)
        near = auto_near if near is None else near
        far = auto_far if far is None else far
        P = projection_matrix(K[0, 0], K[1, 1], K[0, 2], K[1, 2], width, height, near, far)
        fbo, _, host = self._framebuffer(width, height, kind)
        ctx, mgl = self._ctx, self._moderngl
        fbo.use()
        ctx.viewport = (0, 0, width, height)
        fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        if self._vaos:
            ctx.enable(mgl.DEPTH_TEST)
            if self.cull_back_faces:
                ctx.enable(mgl.CULL_FACE)
            else:
                ctx.disable(mgl.CULL_FACE)
            self._programs[kind]["world_to_clip"].write((P @ w2c).T.astype("f4").tobytes())  # column-major
            self._vaos[kind].render(mgl.TRIANGLES)
        if kind in ("depth", "face"):
            dtype = "f4" if kind == "depth" else "i4"
            def read_back() -> np.ndarray:
                fbo.read_into(host[0], components=1, attachment=0, dtype=dtype)
                return host[0]

            if not read:  # handed to llvmpipe's threads now, read back by the caller later (depth_ahead)
                gl_flush()
                return read_back
            return read_back()
        if surface:
            fbo.read_into(host[0], components=4, attachment=0, dtype="f4")
            return host[0]
        fbo.read_into(host[0], components=1, attachment=0, dtype="i4")
        fbo.read_into(host[1], components=4, attachment=1, dtype="f4")
        fbo.read_into(host[2], components=4, attachment=2, dtype="f4")
        return host

    def close(self) -> None:
        """Release the GL context and its buffers (the rasterizer is unusable for GL afterwards)."""
        if self._ctx is not None:
            with self._ctx:  # current first: GL ids are per context, another live rasterizer's would be deleted
                for fbo, textures, _ in self._targets.values():
                    fbo.release()
                    for t in textures:
                        t.release()
                self._targets.clear()
                for obj in [*self._vaos.values(), self._vbo, *self._indexed, *self._programs.values()]:
                    if obj is not None:
                        obj.release()
            self._ctx.release()
            self._ctx = None

    def __enter__(self) -> MeshRasterizer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # noqa: BLE001 - interpreter shutdown: moderngl may already be gone
            pass

    # ------------------------------------------------------------------ rasterization
    def _use_gl(self) -> bool:
        if self.backend == "gl" and self._ctx is None:
            raise RuntimeError("this MeshRasterizer was closed")
        return self.backend == "gl"

    def depth_range(self, w2c: np.ndarray) -> tuple[float, float]:
        """Tight ``(near, far)`` z-range of the mesh's bounding box in a camera (``w2c # [4, 4]``)."""
        z = self._corners @ w2c[2, :3] + w2c[2, 3]  # [8]
        far = max(float(z.max()), 1e-6) * 1.01 + 1e-6
        near = max(float(z.min()) * 0.99, far * 1e-4)
        return near, far

    def rasterize(self, camera: Cameras, normals: NormalMode = "face", near: float | None = None,
                  far: float | None = None) -> GBuffer:
        """G-buffer of the mesh seen by ``camera`` (one camera, its ``width x height``).

        Args:
            normals: ``"face"`` (geometric normal of the hit triangle), ``"vertex"`` (barycentric
                interpolation of area-weighted vertex normals, renormalised) or ``"none"``.
            near, far: Clip planes in camera z (GL backend; default: the mesh's bounding-box range).
                The reference backend drops triangles with a vertex at z <= ``near`` (default 1e-6).
        """
        K, w2c = _camera_arrays(camera)
        width, height = camera.width, camera.height
        if self._use_gl():
            h_face, h_bary, h_world = self._draw(K, w2c, width, height, near, far)
            face = torch.from_numpy(h_face.astype(np.int64)) - 1  # [H, W]
            bd = torch.from_numpy(h_bary.copy())  # [H, W, 4]
            bary, depth = bd[..., :3], bd[..., 3]
            # llvmpipe interpolates each component in float32 (off by up to ~3e-4); GL only covers
            # pixel centres inside the triangle, so the true values are >= 0: clamp and renormalise
            bary = bary.clamp_min(0)
            bary = bary / bary.sum(-1, keepdim=True).clamp_min(1e-12)
            points = torch.from_numpy(h_world[..., :3].copy())  # [H, W, 3]
        else:
            face, bary, depth, points = self._rasterize_reference(K, w2c, width, height, near)
        normal = None if normals == "none" else self.shading_normals(face, bary, normals)
        return GBuffer(face, bary, depth, points, normal)

    def surface(self, camera: Cameras, near: float | None = None, far: float | None = None) -> Surface:
        """The covered pixels of ``camera``'s view with their surface points and depths, compacted:
        what a per-pixel shader needs, at about half the cost of :meth:`rasterize` (GL: one
        ``RGBA32F`` target; the reference backend compacts its full G-buffer)."""
        if not self._use_gl():
            g = self.rasterize(camera, normals="none", near=near)
            pixels = (g.face.reshape(-1) >= 0).nonzero()[:, 0]
            return Surface(pixels, g.points.reshape(-1, 3)[pixels], g.depth.reshape(-1)[pixels], camera.height,
                           camera.width)
        K, w2c = _camera_arrays(camera)
        host = self._draw(K, w2c, camera.width, camera.height, near, far, surface=True).reshape(-1, 4)
        covered = host[:, 3] > 0  # z-depth, 0 = background
        pixels = np.flatnonzero(covered)  # [P]
        world = np.compress(covered, host, axis=0)  # [P, 4] (far faster than fancy indexing)
        return Surface(torch.from_numpy(pixels), torch.from_numpy(world[:, :3].copy()),
                       torch.from_numpy(world[:, 3].copy()), camera.height, camera.width)

    def face_ids(self, camera: Cameras, near: float | None = None) -> np.ndarray:
        """The nearest triangle at ``camera``'s pixel centres, ``-1`` = background: :meth:`rasterize`'s ``face`` alone.
        ``# [H, W]`` int64

        GL: one ``R32I`` target written with ``gl_PrimitiveID`` from the indexed mesh (no barycentrics, points or depth
        read back). Reference backend: :meth:`rasterize`'s (its twin)."""
        if not self._use_gl():
            return self.rasterize(camera, normals="none", near=near).face.numpy()
        K, w2c = _camera_arrays(camera)
        return self._draw(K, w2c, camera.width, camera.height, near, None, surface="face").astype(np.int64) - 1

    def depth(self, camera: Cameras, near: float | None = None, far: float | None = None) -> Tensor:
        """Camera z-depth of the mesh at ``camera``'s pixel centres, 0 = background. ``# [H, W]`` float32

        GL: one ``R32F`` target; the returned tensor shares the rasterizer's host buffer, so it is valid
        until this rasterizer's next draw at the same size (copy it to keep it). Reference backend: the
        full G-buffer's depth (:meth:`rasterize`, its twin)."""
        if not self._use_gl():
            return self.rasterize(camera, normals="none", near=near).depth
        K, w2c = _camera_arrays(camera)
        return torch.from_numpy(self._draw(K, w2c, camera.width, camera.height, near, far, surface="depth"))

    def depth_ahead(self, camera: Cameras, near: float | None = None, far: float | None = None):
        """:meth:`depth` drawn now and read back later: returns a function that returns what :meth:`depth` returns (the
        same host buffer, valid until this rasterizer's next draw at that size). Meanwhile llvmpipe's threads
        rasterize it (after whatever this context drew before), and the caller's thread is free. Reference backend:
        drawn at once."""
        if not self._use_gl():
            out = self.depth(camera, near, far)
            return lambda: out
        K, w2c = _camera_arrays(camera)
        with self._ctx:
            read = self._draw_current(K, w2c, camera.width, camera.height, near, far, surface="depth", read=False)

        def result() -> Tensor:
            with self._ctx:
                return torch.from_numpy(read())

        return result

    def _rasterize_reference(self, K, w2c, width, height, near):
        from omnirecon.render.zbuffer import (
            rasterize,  # lazy: the NumPy reference runs only when the GL backend is not used
        )

        near = 1e-6 if near is None else near
        F = len(self.faces)
        z = self.vertices @ w2c[2, :3] + w2c[2, 3]  # [V]
        keep = np.flatnonzero((z[self.faces] > near).all(1)) if F else np.zeros(0, dtype=np.int64)
        face = np.full((height, width), -1, dtype=np.int64)
        bary = np.zeros((height, width, 3))
        depth = np.zeros((height, width))
        if len(keep):
            tris = self.faces[keep]  # [F', 3]
            used, local = np.unique(tris, return_inverse=True)
            local = local.reshape(-1, 3)
            if not self.cull_back_faces:
                local = np.concatenate([local, local[:, [0, 2, 1]]])  # both windings
            frags = rasterize(self.vertices[used], local, K, w2c, width, height, near=near)
            hit = frags.face >= 0
            f = frags.face[hit]
            b = frags.bary[hit]
            flipped = f >= len(keep)
            b[flipped] = b[flipped][:, [0, 2, 1]]
            face[hit] = keep[np.where(flipped, f - len(keep), f)]
            bary[hit] = b
            depth[hit] = frags.depth[hit]
        face_t = torch.from_numpy(face)
        bary_t = torch.from_numpy(bary)
        points = torch.zeros(height, width, 3, dtype=torch.float64)
        hit = face_t >= 0
        v = torch.from_numpy(self.vertices)[torch.from_numpy(self.faces)[face_t[hit]]]  # [P, 3, 3]
        points[hit] = (bary_t[hit][:, :, None] * v).sum(1)
        return face_t, bary_t.float(), torch.from_numpy(depth).float(), points.float()

    # ------------------------------------------------------------------ normals
    @property
    def face_normals(self) -> Tensor:
        """Unit geometric normals ``(v1 - v0) x (v2 - v0)`` per triangle. ``# [F, 3]`` float32"""
        if self._face_normals is None:
            v = self.vertices[self.faces]
            n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-20)
            self._face_normals = torch.from_numpy(n.astype(np.float32))
        return self._face_normals

    def shading_normals(self, face: Tensor, bary: Tensor, mode: NormalMode = "face") -> Tensor:
        """Normals at G-buffer pixels ``face # [H, W]``, ``bary # [H, W, 3]``. ``# [H, W, 3]`` float32"""
        out = torch.zeros(*face.shape, 3)
        hit = face >= 0
        f = face[hit]
        if mode == "face":
            out[hit] = self.face_normals[f]
        elif mode == "vertex":
            if self._vertex_normals is None:
                self._vertex_normals = torch.from_numpy(vertex_normals(self.vertices, self.faces).astype(np.float32))
            n = (bary[hit][:, :, None] * self._vertex_normals[self._torch_faces[f]]).sum(1)  # [P, 3]
            out[hit] = torch.nn.functional.normalize(n, dim=-1)
        else:
            raise ValueError(f"unknown normal mode {mode!r}; use 'face', 'vertex' or 'none'")
        return out
