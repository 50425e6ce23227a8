"""The mesh path's blend as one GL fragment-shader pass: image-based shading of a whole frame from its depth map.

The GL twin of the fused shader's frame path (:mod:`omnirecon.mesh.shader`, :meth:`omnirecon.mesh.ibr.MeshRenderer.frame`),
in the GL context of a :class:`~omnirecon.render.raster.MeshRasterizer` (Mesa llvmpipe on the CPU: it JIT-compiles the
shader and shades the frame's tiles on its ``LP_NUM_THREADS`` threads). Tensors in, image out; the weights of the
appearance MLP come in as tensors, no model. The GLSL is the web viewer's shading pass
(``omnirecon/viewer/static/shaders.js``, ``shadeShader``) for desktop GL 4.3 (the sources' colours and folded features
sampled by GL's bilinear filter, their occlusion depths and mask falloff read from storage buffers: on llvmpipe both cost
less than ``texelFetch``), over every source of the renderer or, with the angle blend and
a candidate grid, each tile's candidates (:meth:`GLBlend.candidates`):

per pixel ``(j + 0.5, i + 0.5)``, the point ``o + z d(u, v)`` on its ray (``d`` at camera z = 1: ``u A0 + v A1 + A2``,
:func:`omnirecon.mesh.fill.ray_basis`) at the frame's z-depth ``z`` (after the CPU's nearest/crack fill); where
``z <= 0``, the far layer (the ray's exit from the bounds box, at most ``far``; no occlusion test) or the background
colour; then

* ``blend="angle"``: the ``k`` sources nearest by viewing angle among those that see the point (in front, inside the
  image, and not occluded: :func:`omnirecon.mesh.kernel.unoccluded` against the sources' 2x2 block depth maxima) get
  the unstructured lumigraph's ``(1 - a_i / a_(k+1)) / a_i`` (:func:`omnirecon.mesh.kernel.lumigraph`), normalised, times
  the sources' mask falloff on the mesh (:func:`omnirecon.mesh.kernel.apply_mask_factor`); a point no source weighs
  blends every source alike;
* ``blend="network"``: ``softmax_k MLP([ReLU(W F_k + b); t - d_k])`` with ``-1e9`` where source ``k`` does not see the
  point (the folded appearance branch, bilinear in the ``b``-bordered feature maps);

and the colour is the weighted sum of the sources' colours at the point's projections (bilinear, border padding, as
``grid_sample(align_corners=False, padding_mode="border")``: GL's bilinear filter, clamped to the edge), in float32
(the folded features in half precision; colours within 1e-4 of the torch shader's, ``tests/mesh/test_ibr_gl.py``).

With ``stride`` > 1 (the network blend of at most :attr:`GLBlend.STRIDE_SOURCES` sources), a first pass runs the
MLP only at every ``stride``-th pixel of each axis (the frame's own pixels ``(stride i, stride j)``) and writes their
softmax weights with their z-depth; the colour pass then gives each pixel the bilinear mix of the (up to 4) weight
texels around it whose z-depth is within :attr:`GLBlend.WEIGHT_TOL` of its own (all 4 where none is), blended over
the sources that see the pixel (their weights renormalised; where none of them has weight, those sources alike). On
the pass's own pixels that is the blend at every pixel; elsewhere an interpolation of it: a level of detail, measured
(``MeshRenderOptions.weight_stride``).

Cost on llvmpipe: its SIMD lanes run both sides of every branch, so a source skipped early saves nothing; the cost
per pixel follows the sources ranked (hence the tiles' candidates) and the loads from the maps, and with the network
blend most of it is the MLP (hence the stride).

Size: the GLSL (both blends, the fill's far layer, the occlusion test, bilinear sampling), its generated parts (the
unrolled MLP and ranking) and the host side (uploads, candidate tiles, draw, read-back) are one pass kept together.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from omnirecon.render.raster import gl_flush

_VERTEX = """
#version 330 core
void main() {  // one full-screen triangle
    vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
    gl_Position = vec4(p * 2.0 - 1.0, 0.0, 1.0);
}
"""

_FRAGMENT = """
#version 430 core
#define K {K}
#define KA {KA}
#define C4 {C4}
#define ANGLE {ANGLE}
#define MASKS {MASKS}
#define VISIBILITY {VISIBILITY}
#define WEIGHTS {WEIGHTS}
#define STRIDE {STRIDE}
#define INF 1.0e30
// the maps GL filters are textures, the others storage buffers (plain loads: cheaper than texelFetch on llvmpipe)
uniform sampler2DArray uImages;   // RGBA32F, W x H, layer k: source k's RGB, bilinear
layout(std430, binding = 1) readonly buffer Depth { float depthMax[]; };   // [K, H + 1, W + 1]: block_depth_max
layout(std430, binding = 2) readonly buffer Falloff { float falloff[]; };  // [K, H, W]: mask_falloff
uniform sampler2DArray uFeatures; // RGBA16F, (w + 2) x (h + 2), layer k C4 + j: channels 4j..4j+3 of W F_k + b, bilinear
uniform vec4 uCams[4 * K];        // per source k: rows 0-2 of K_k [R_k | t_k], then (c_k, 1)
layout(std430, binding = 4) readonly buffer Candidates { int cand[]; };  // per tile: its count, then its sources
uniform int uTile;                // the candidate tiles' size in pixels
uniform int uTilesX;              // tiles per row
int gTile;                        // this pixel's tile's first entry in cand
uniform sampler2D uZ;             // RG32F: the frame's z-depth after the fill (<= 0: none), 1 on the mesh
uniform mat3 uA;                  // columns: the ray at camera z = 1 is u A[0] + v A[1] + A[2]
uniform vec3 uOrigin;
uniform vec3 uBoxLo;
uniform vec3 uBoxHi;
uniform int uBox;
uniform float uFar;
uniform vec3 uBackground;
uniform int uFill;                // 0: the background colour where z <= 0, 1: the far layer
uniform vec2 uImageSize;
uniform vec2 uFeatSize;
uniform float uVisTol;
uniform sampler2D uWeights;       // WEIGHTS 2: the weights pass's (w_0, w_1, w_2, z) at every STRIDE-th pixel (z < 0: none)
uniform float uWeightTol;         // WEIGHTS 2: a weight texel counts when its z is within this fraction of the pixel's
out vec4 fragColor;

{MLP}

vec3 centre(int k) { return uCams[4 * k + 3].xyz; }

vec3 project(int k, vec3 p) {  // (u z, v z, z) of world point p in source k
  vec4 q = vec4(p, 1.0);
  return vec3(dot(uCams[4 * k], q), dot(uCams[4 * k + 1], q), dot(uCams[4 * k + 2], q));
}

bool framed(float z, vec2 uv) {
  return z > 1e-6 && uv.x >= 0.0 && uv.y >= 0.0 && uv.x < uImageSize.x && uv.y < uImageSize.y;
}

bool unoccluded(int k, vec2 uv, float z) {  // omnirecon.mesh.kernel.unoccluded
#if VISIBILITY
  int b = int(clamp(floor(uv.x - 0.5), -1.0, uImageSize.x - 1.0)) + 1;
  int a = int(clamp(floor(uv.y - 0.5), -1.0, uImageSize.y - 1.0)) + 1;
  int W1 = int(uImageSize.x) + 1;
  return z <= depthMax[(k * (int(uImageSize.y) + 1) + a) * W1 + b] * (1.0 + uVisTol);
#else
  return true;
#endif
}

vec3 sampleImage(int k, vec2 uv) {  // grid_sample(align_corners=False, padding_mode="border"): GL's bilinear, clamped
  return texture(uImages, vec3(uv / uImageSize, float(k))).rgb;
}

float maskFactor(int k, vec2 uv) {  // omnirecon.mesh.kernel.mask_factor
  ivec2 q = ivec2(clamp(floor(uv), vec2(0.0), uImageSize - 1.0));
  return falloff[(k * int(uImageSize.y) + q.y) * int(uImageSize.x) + q.x];
}

#if ANGLE == 0
float logit(int k, vec3 p, vec3 t, bool layer, out vec2 uv, out bool seen) {  // -1e9 where source k does not see p
  vec3 uvz = project(k, p);
  uv = uvz.xy / max(uvz.z, 1e-6);
  seen = framed(uvz.z, uv) && (layer || unoccluded(k, uv, uvz.z));
  float l = -1.0e9;
  if (seen) {
    vec2 st = (uv / uImageSize * uFeatSize + 1.0) / (uFeatSize + 2.0);  // in the padded map (GL's bilinear, clamped)
    vec4 z4[C4];
    for (int j = 0; j < C4; j++) z4[j] = max(texture(uFeatures, vec3(st, float(k * C4 + j))), 0.0);
    vec3 dk = p - centre(k);
    l = appearanceLogit(z4, t - dk / max(length(dk), 1e-12));
  }
  return l;
}

#if WEIGHTS == 1
vec3 blendWeights(vec3 p, vec3 t, bool layer) {  // the softmax over the (at most 3) sources
  float l[3] = float[3](-3.0e38, -3.0e38, -3.0e38);
  float top = -3.0e38;
  for (int k = 0; k < K; k++) {
    vec2 uv;
    bool seen;
    l[k] = logit(k, p, t, layer, uv, seen);
    top = max(top, l[k]);
  }
  vec3 e = vec3(exp(l[0] - top), K > 1 ? exp(l[1] - top) : 0.0, K > 2 ? exp(l[2] - top) : 0.0);
  return e / (e.x + e.y + e.z);
}
#elif WEIGHTS == 2
vec3 shade(vec3 p, vec3 t, bool layer, bool onMesh, float z) {  // the weights pass's weights, depth-aware bilinear
  ivec2 px = ivec2(gl_FragCoord.xy);
  ivec2 lo = px / STRIDE;
  vec2 f = vec2(px - lo * STRIDE) / float(STRIDE);
  ivec2 last = textureSize(uWeights, 0) - 1;
  vec3 near = vec3(0.0), all = vec3(0.0);
  float nearSum = 0.0;
  for (int n = 0; n < 4; n++) {
    ivec2 o = ivec2(n & 1, n >> 1);
    float b = (o.x == 1 ? f.x : 1.0 - f.x) * (o.y == 1 ? f.y : 1.0 - f.y);
    vec4 s = texelFetch(uWeights, min(lo + o, last), 0);
    all += b * s.rgb;
    float m = abs(s.a - z) <= uWeightTol * z ? b : 0.0;
    near += m * s.rgb;
    nearSum += m;
  }
  vec3 w = nearSum > 0.0 ? near / nearSum : all;
  vec3 acc = vec3(0.0), seenRgb = vec3(0.0), plain = vec3(0.0);
  float total = 0.0, seenCount = 0.0;
  for (int k = 0; k < K; k++) {
    vec3 uvz = project(k, p);
    vec2 uv = uvz.xy / max(uvz.z, 1e-6);
    bool seen = framed(uvz.z, uv) && (layer || unoccluded(k, uv, uvz.z));
    vec3 c = sampleImage(k, uv);
    float wk = seen ? (k == 0 ? w.x : k == 1 ? w.y : w.z) : 0.0;
    acc += wk * c;
    total += wk;
    seenRgb += seen ? c : vec3(0.0);
    seenCount += seen ? 1.0 : 0.0;
    plain += c;
  }
  // no weight on the sources that see p (the texels around saw it from none of them): those sources alike; none sees
  // p: every source alike, as the softmax over -1e9 gives
  return total > 0.0 ? acc / total : seenCount > 0.0 ? seenRgb / seenCount : plain / float(K);
}
#else
vec3 shade(vec3 p, vec3 t, bool layer, bool onMesh, float z) {  // softmax over the sources, accumulated online
  float top = -3.0e38, total = 0.0;
  vec3 rgb = vec3(0.0);
  for (int k = 0; k < K; k++) {
    vec2 uv;
    bool seen;
    float l = logit(k, p, t, layer, uv, seen);
    float m = max(top, l);
    float a = exp(top - m), e = exp(l - m);
    total = total * a + e;
    rgb = rgb * a + e * sampleImage(k, uv);
    top = m;
  }
  return rgb / total;
}
#endif
#else
{ANGLE_SHADE}  // no source weighs p: every source alike (times the mask factor on the mesh)
  float u2 = 0.0;
  vec3 acc = vec3(0.0), plain = vec3(0.0);
  for (int k = 0; k < K; k++) {
    vec3 uvz = project(k, p);
    vec2 uv = uvz.xy / max(uvz.z, 1e-6);
    vec3 c = sampleImage(k, uv);
    float f = 1.0;
#if MASKS
    if (onMesh) f = maskFactor(k, uv);
#endif
    acc += f * c;
    u2 += f;
    plain += c;
  }
  return u2 > 0.0 ? acc / u2 : plain / float(K);
}
#endif

float exitDepth(vec3 o, vec3 d) {  // omnirecon.mesh.fill.exit_depth
  if (uBox == 0) return uFar;
  vec3 safe = max(abs(d), vec3(1e-12)) * mix(vec3(1.0), vec3(-1.0), lessThan(d, vec3(0.0)));
  vec3 t1 = (uBoxLo - o) / safe, t2 = (uBoxHi - o) / safe;
  vec3 tmin = min(t1, t2), tmax = max(t1, t2);
  float tIn = max(max(tmin.x, tmin.y), tmin.z), tOut = min(min(tmax.x, tmax.y), tmax.z);
  return (tOut > max(tIn, 0.0) && tOut > 0.0) ? min(tOut, uFar) : uFar;
}

void main() {
#if WEIGHTS == 1
  ivec2 px = min(ivec2(gl_FragCoord.xy) * STRIDE, textureSize(uZ, 0) - 1);  // the frame pixel this texel stands for
#else
  ivec2 px = ivec2(gl_FragCoord.xy);  // window row = image row (omnirecon.render.raster)
#endif
  vec2 zh = texelFetch(uZ, px, 0).rg;
  float z = zh.r;
  bool layer = false;
  vec3 d = uA * vec3(vec2(px) + 0.5, 1.0);  // the pixel centre's ray at camera z = 1
  if (z <= 0.0) {
    if (uFill == 0) {
#if WEIGHTS == 1
      fragColor = vec4(0.0, 0.0, 0.0, -1.0);
#else
      fragColor = vec4(uBackground, 1.0);
#endif
      return;
    }
    z = exitDepth(uOrigin, d);
    layer = true;
  }
  ivec2 tile = px / uTile;
  gTile = (tile.y * uTilesX + tile.x) * (K + 1);
  vec3 p = uOrigin + z * d;
  vec3 t = d / max(length(d), 1e-12);
#if WEIGHTS == 1
  fragColor = vec4(blendWeights(p, t, layer), z);
#else
  fragColor = vec4(shade(p, t, layer, zh.g > 0.5, z), 1.0);
#endif
}
"""


def _lit(x: float) -> str:
    """A GLSL float literal that parses back to the same float32."""
    return repr(float(np.float32(x)))


def angle_source(ka: int) -> str:
    """GLSL of the angle blend's ranking and weights for ``ka`` sources per point (``KA``), unrolled: the ``ka + 1``
    nearest sources in plain variables (``c0 >= c1 >= ...``), no arrays (llvmpipe keeps dynamically indexed arrays in
    memory); first over the pixel's tile's candidates, then (where none of them weighs it) over every source."""
    J = range(ka + 1)
    decl = "\n".join(f"float c{j} = -2.0; int i{j} = 0; vec2 v{j} = vec2(0.0);" for j in J)
    insert = "\n".join(f"      if (c > c{j}) {{ float oc = c{j}; int ok = i{j}; vec2 ov = v{j}; "
                        f"c{j} = c; i{j} = k; v{j} = uv; c = oc; k = ok; uv = ov; }}" for j in J)
    angles = "\n".join(f"    float a{j} = c{j} >= -1.5 ? acos(clamp(c{j}, -1.0, 1.0)) : INF;" for j in J)
    thresh = f"float thresh = n > {ka} ? a{ka} : INF;"
    weights = "\n".join(f"    float w{j} = a{j} < INF ? max(1.0 - a{j} / thresh, 0.0) / max(a{j}, 1e-3) : 0.0;"
                         for j in range(ka))
    total = " + ".join(f"w{j}" for j in range(ka))
    norm = " ".join(f"w{j} /= total;" for j in range(ka))
    masks = "\n".join(f"      float u{j} = w{j} * maskFactor(i{j}, v{j});" for j in range(ka))
    utotal = " + ".join(f"u{j}" for j in range(ka))
    unorm = " ".join(f"w{j} = u{j} / t2;" for j in range(ka))
    colour = " + ".join(f"w{j} * sampleImage(i{j}, v{j})" for j in range(ka))
    return f"""vec3 shade(vec3 p, vec3 t, bool layer, bool onMesh, float z) {{
  // the KA + 1 sources that see p with the largest cosines, descending: among the candidates, then (where none of
  // them weighs p) among every source
  for (int pass = 0; pass < 2; pass++) {{
    int n = pass == 0 ? cand[gTile] : K;
    if (pass == 1 && cand[gTile] == K) break;
{decl}
    for (int i = 0; i < n; i++) {{
      int k = pass == 0 ? cand[gTile + 1 + i] : i;
      vec3 dk = p - centre(k);
      float c = dot(t, dk) / max(length(dk), 1e-12);
      vec3 uvz = project(k, p);
      vec2 uv = uvz.xy / max(uvz.z, 1e-6);
      // only a source that would enter the list is tested (the same list: below c{ka} no swap happens), so most
      // of the occlusion test's loads, per lane on llvmpipe, are skipped; no continue: the loop stays uniform
      if (c > c{ka} && framed(uvz.z, uv) && (layer || unoccluded(k, uv, uvz.z))) {{
{insert}
      }}
    }}
{angles}
    {thresh}
{weights}
    float total = {total};
    if (total > 0.0) {{
      {norm}
#if MASKS
      if (onMesh) {{
{masks}
        float t2 = {utotal};
        if (t2 > 0.0) {{ {unorm} }}
      }}
#endif
      return {colour};
    }}
  }}
"""


def mlp_source(mlp: list[Tensor]) -> str:
    """GLSL ``float appearanceLogit(vec4 z[C4], vec3 r)`` of the folded appearance MLP ``mlp``: ``W1 # [h1, C + 3]``
    (feature then direction columns), ``b1 # [h1]``, ``W2 # [h2, h1]``, ``b2 # [h2]``, ``W3 # [1, h2]``, ``b3 # [1]``,
    its weights as literals (unrolled: no uniform limits, no fetches); the viewer's ``mlpSource``."""
    w1, b1, w2, b2, w3, b3 = (t.detach().double().cpu().numpy() for t in mlp)
    h1, C = w1.shape[0], w1.shape[1] - 3
    C4 = -(-C // 4)
    lines = [f"float appearanceLogit(vec4 z[{C4}], vec3 r) {{"]
    for o in range(h1):
        terms = [_lit(b1.reshape(-1)[o])]
        for j in range(C4):
            v = [_lit(w1[o, 4 * j + i]) if 4 * j + i < C else "0.0" for i in range(4)]
            terms.append(f"dot(z[{j}], vec4({', '.join(v)}))")
        terms.append(f"dot(r, vec3({_lit(w1[o, C])}, {_lit(w1[o, C + 1])}, {_lit(w1[o, C + 2])}))")
        lines.append(f"  float a{o} = max({' + '.join(terms)}, 0.0);")
    for o in range(w2.shape[0]):
        terms = [_lit(b2.reshape(-1)[o])] + [f"{_lit(w2[o, i])} * a{i}" for i in range(h1)]
        lines.append(f"  float b{o} = max({' + '.join(terms)}, 0.0);")
    out = [_lit(b3.reshape(-1)[0])] + [f"{_lit(w3.reshape(-1)[i])} * b{i}" for i in range(w2.shape[0])]
    lines += [f"  return {' + '.join(out)};", "}"]
    return "\n".join(lines)


def _f32(t: Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().to("cpu", torch.float32).numpy())


class GLBlend:
    """The blend of one set of ``K`` sources as a fragment shader (module docstring), in the GL context ``ctx`` (a
    :class:`~omnirecon.render.raster.MeshRasterizer`'s ``context``): textures uploaded once, then per frame one upload
    of the depth map, one full-screen draw and one read-back.

    Args:
        ctx: A moderngl context (made current around every call here).
        images: The sources' colours. ``# [K, H, W, 3]``
        proj: World -> ``(u z, v z, z)`` of each source (``K [R | t]``). ``# [K, 3, 4]``
        centers: The sources' camera centres. ``# [K, 3]``
        angle_sources: ``blend="angle"`` over this many sources per point (0: every source); ``None``: the network blend
            (``mlp`` and ``features`` then required).
        depth_max: With the occlusion test: :func:`omnirecon.mesh.kernel.block_depth_max` of each source
            ``# [K, H + 1, W + 1]`` (``inf``: background); ``None``: no test.
        tol: The occlusion test's relative depth tolerance.
        falloff: With the angle blend: :func:`omnirecon.mesh.kernel.mask_falloff` of each source ``# [K, H, W]``.
        mlp: The folded appearance MLP (:func:`mlp_source`).
        features: The folded feature maps ``W F_k + b`` with a one-texel border of ``b`` (what zero padding samples
            before the fold). ``# [K, C, h + 2, w + 2]``
        stride: The network blend's MLP at every ``stride``-th pixel (module docstring; 1: every pixel, also where
            it does not apply).
    """

    STRIDE_SOURCES = 3
    """``stride`` applies to the network blend of at most this many sources (their weights and the z-depth: one RGBA
    texel)."""
    MAX_SOURCES = 512
    """The most sources one pass takes (their cameras are uniforms: llvmpipe holds 4096 ``vec4`` per shader)."""
    PROPOSED = 3
    """:meth:`candidates`: each grid point proposes the ``KA + PROPOSED`` sources nearest by angle that frame it (the
    shader's loop runs over a tile's candidates: fewer proposed, less work per pixel; ``python -m bench mesh_lod``
    times it and scores its held-out PSNR against the reference path, ``--proposed`` at other counts)."""

    WEIGHT_TOL = 0.02
    """``stride`` > 1: a weight texel counts for a pixel when its z-depth is within this fraction of the pixel's (the
    same surface; across a depth edge the texels of the pixel's side only)."""

    def __init__(self, ctx, images: Tensor, proj: Tensor, centers: Tensor, angle_sources: int | None,
                 depth_max: Tensor | None = None, tol: float = 0.01, falloff: Tensor | None = None,
                 mlp: list[Tensor] | None = None, features: Tensor | None = None, stride: int = 1):
        self.ctx = ctx
        K, H, W, _ = images.shape
        angle = angle_sources is not None
        C = 4 if angle else features.shape[1]
        KA = max(1, min(angle_sources or K, K)) if angle else 1
        self.stride = stride if stride > 1 and not angle and K <= self.STRIDE_SOURCES else 1
        defines = dict(K=K, KA=KA, C4=-(-C // 4), ANGLE=int(angle),
                       MASKS=int(angle and falloff is not None), VISIBILITY=int(depth_max is not None),
                       MLP="" if angle else mlp_source(mlp), ANGLE_SHADE=angle_source(KA) if angle else "",
                       STRIDE=self.stride)
        self._objects: list = []
        self._cand = None  # the candidate tiles' storage buffer (grown as needed)
        self._frames: dict[tuple[int, int, int], tuple] = {}
        self._slot = 0  # the framebuffer of the last submit
        with ctx:
            programs = ctx.extra if isinstance(ctx.extra, dict) else {}  # compiled once per context and source
            ctx.extra = programs
            passes = []  # (program, vertex array): the weights pass first when there is one, the colour pass last
            for weights in ((1, 2) if self.stride > 1 else (0,)):
                source = _FRAGMENT
                for key, value in {**defines, "WEIGHTS": weights}.items():
                    source = source.replace("{" + key + "}", str(value))
                if source not in programs:  # released with the context (a video's source sets share them)
                    program = ctx.program(vertex_shader=_VERTEX, fragment_shader=source)
                    programs[source] = (program, ctx.vertex_array(program, []))
                passes.append(programs[source])
            self._passes = passes
            self.program, self._vao = passes[-1]
            rgba = torch.cat([images.detach().cpu().float(), torch.ones(K, H, W, 1)], -1)  # [K, H, W, 4]
            buffers = {1: depth_max, 2: falloff if angle else None}
            self._images = self._keep(ctx.texture_array((W, H, K), 4, _f32(rgba).tobytes(), dtype="f4"))
            self._images.repeat_x = self._images.repeat_y = False  # clamp to the edge: border padding
            cams = torch.cat([proj.detach().cpu().float(), torch.cat([centers.detach().cpu().float(),
                                                                      torch.ones(K, 1)], 1)[:, None]], 1)  # [K, 4, 4]
            self._write("uCams", _f32(cams))
            self._centers = centers.detach().cpu().double()  # [K, 3]
            self._proj = proj.detach().cpu().float()  # [K, 3, 4]
            self._size = (float(W), float(H))
            self.K, self.KA = K, KA
            self._features = None
            if not angle:
                C4, (h2, w2) = defines["C4"], features.shape[2:]
                maps = torch.cat([features.detach().cpu().float(),
                                  torch.zeros(K, 4 * C4 - C, h2, w2)], 1)  # [K, 4 C4, h + 2, w + 2]
                layers = maps.reshape(K, C4, 4, h2, w2).permute(0, 1, 3, 4, 2).half()  # [K, C4, h + 2, w + 2, 4]
                self._features = self._keep(ctx.texture_array((w2, h2, K * C4), 4, layers.contiguous().numpy().tobytes(),
                                                              dtype="f2"))
                self._features.repeat_x = self._features.repeat_y = False  # clamp to the edge: the border texels
                self._set("uFeatSize", (float(w2 - 2), float(h2 - 2)))
            self._buffers = {i: self._keep(ctx.buffer((b if b.dtype == torch.float16 else b.float()).detach()
                                                      .cpu().contiguous().numpy().tobytes()))
                             for i, b in buffers.items() if b is not None}
            self._set("uImageSize", (float(W), float(H)))
            self._set("uVisTol", float(tol))

    def _keep(self, obj):
        self._objects.append(obj)
        return obj

    def _nearest(self):
        import moderngl

        return moderngl.NEAREST

    def _write(self, name: str, values: np.ndarray) -> None:
        for program, _ in self._passes:
            if name in program:  # the linker may trim an array's unused tail (the colour pass reads no last centre)
                uniform = program[name]
                program[name].write(values.tobytes()[:4 * uniform.dimension * uniform.array_length])  # float32

    def _set(self, name: str, value) -> None:
        for program, _ in self._passes:
            if name in program:
                program[name].value = value

    def _frame(self, width: int, height: int, slot: int) -> tuple:
        """The depth texture, framebuffer and host arrays of one frame size and slot (made on first use)."""
        key = (width, height, slot)
        if key not in self._frames:
            z = self._keep(self.ctx.texture((width, height), 2, dtype="f4"))
            z.filter = (self._nearest(), self._nearest())
            colour = self._keep(self.ctx.texture((width, height), 4, dtype="f4"))
            fbo = self._keep(self.ctx.framebuffer(color_attachments=[colour]))
            low = None  # the weights pass's target: (w_0, w_1, w_2, z) at every stride-th pixel
            if self.stride > 1:
                texels = (-(-width // self.stride), -(-height // self.stride))
                weights = self._keep(self.ctx.texture(texels, 4, dtype="f4"))
                weights.filter = (self._nearest(), self._nearest())
                low = (weights, self._keep(self.ctx.framebuffer(color_attachments=[weights])), texels)
            self._frames[key] = (z, fbo, np.empty((height, width, 2), np.float32), np.empty((height, width, 4), np.float32),
                                 low)
        return self._frames[key]

    def shade(self, depth: np.ndarray, on_mesh: np.ndarray, A: Tensor, origin: Tensor, fill: bool,
              background=(1.0, 1.0, 1.0), far: float = 1.0, box: Tensor | None = None, grid: int = 0,
              far_z=None) -> Tensor:
        """The blended colour of one frame: :meth:`submit` then :meth:`result`, ``rgb # [H, W, 3]`` float32."""
        return self.result(*self.submit(depth, on_mesh, A, origin, fill, background, far, box, grid, far_z))

    def result(self, width: int, height: int, slot: int) -> Tensor:
        """The colour of the frame :meth:`submit` drew (its ``(W, H, slot)``; waits for llvmpipe's threads to shade it):
        ``rgb # [H, W, 3]`` float32, a tensor over a host buffer this object reuses (valid until the second
        :meth:`submit` after it at that size)."""
        _, fbo, _, host_rgb, _ = self._frame(width, height, slot)
        with self.ctx:
            fbo.read_into(host_rgb, components=4, attachment=0, dtype="f4")
        return torch.from_numpy(host_rgb)[..., :3]

    def submit(self, depth: np.ndarray, on_mesh: np.ndarray, A: Tensor, origin: Tensor, fill: bool,
               background=(1.0, 1.0, 1.0), far: float = 1.0, box: Tensor | None = None, grid: int = 0,
               far_z=None) -> tuple[int, int, int]:
        """Draw the blend of one frame and hand it to llvmpipe's threads without waiting (:meth:`result` reads it
        back; meanwhile the caller's thread may e.g. draw the next frame's depth pass). Frames go to two framebuffers in
        turn, so one may be read while the next is drawn. Returns ``(W, H, slot)``.

        ``depth # [H, W]`` float32: each pixel's z-depth (after the fill; ``<= 0``: none, then with ``fill`` the far
        layer at :func:`omnirecon.mesh.fill.exit_depth` of ``box # [2, 3]`` and ``far``, else ``background``);
        ``on_mesh # [H, W]`` bool: the pixels on the mesh itself (the only ones the mask falloff weighs); ``A # [3, 3]``
        and ``origin # [3]``: :func:`omnirecon.mesh.fill.ray_basis` of the frame's camera. With the angle blend and
        ``grid`` > 0, each tile of ``2 grid`` pixels ranks only its candidate sources (:meth:`candidates`, with
        ``far_z``), its pixels that none of them weighs every source; 0: every pixel ranks every source."""
        H, W = depth.shape
        self._slot = slot = 1 - self._slot
        with self.ctx:
            z_tex, fbo, host_z, _, low = self._frame(W, H, slot)
            host_z[..., 0] = depth
            host_z[..., 1] = on_mesh
            z_tex.write(host_z.tobytes())
            z_tex.use(0)
            self._set("uZ", 0)
            self._images.use(2)
            self._set("uImages", 2)
            if self._features is not None:
                self._features.use(1)
                self._set("uFeatures", 1)
            for binding, buffer in self._buffers.items():  # other passes in this context may bind theirs
                buffer.bind_to_storage_buffer(binding)
            self._set("uA", tuple(_f32(A).reshape(-1).tolist()))  # mat3 column-major: columns A[0], A[1], A[2]
            self._set("uOrigin", tuple(_f32(origin).tolist()))
            self._set("uFill", int(fill))
            self._set("uFar", float(far))
            self._set("uBackground", tuple(float(c) for c in background))
            self._set("uBox", int(box is not None))
            if box is not None:
                self._set("uBoxLo", tuple(_f32(box[0]).tolist()))
                self._set("uBoxHi", tuple(_f32(box[1]).tolist()))
            import moderngl

            self.ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE)
            fbo.use()
            self.ctx.viewport = (0, 0, W, H)
            if "uTile" in self.program:  # the angle blend: each tile's candidates
                tile, table = 1 << 20, np.concatenate([[self.K], np.arange(self.K)])[None]  # one tile, every source
                if grid > 0 and self.K > self.KA + 1:
                    tile, table = 2 * grid, self.candidates(depth, A, origin, grid, far_z if fill else None)
                self._set("uTile", tile)
                self._set("uTilesX", -(-W // tile))
                data = table.astype(np.int32).tobytes()
                if self._cand is None or self._cand.size < len(data):
                    self._cand = self._keep(self.ctx.buffer(reserve=len(data)))
                self._cand.write(data)
                self._cand.bind_to_storage_buffer(4)
            if low is not None:  # the network's weights at every stride-th pixel, then the colour pass reads them
                weights, low_fbo, texels = low
                low_fbo.use()
                self.ctx.viewport = (0, 0, *texels)
                self._passes[0][1].render(moderngl.TRIANGLES, vertices=3)
                weights.use(3)
                self._set("uWeights", 3)
                self._set("uWeightTol", self.WEIGHT_TOL)
                fbo.use()
                self.ctx.viewport = (0, 0, W, H)
            self._vao.render(moderngl.TRIANGLES, vertices=3)
            gl_flush()
        return W, H, slot

    def candidates(self, depth: np.ndarray, A: Tensor, origin: Tensor, grid: int, far_z=None) -> np.ndarray:
        """The angle blend's candidate sources per tile of a frame (``MeshRenderOptions.frame_grid``): at every ``grid``-th
        pixel (its depth of ``depth # [H, W]``; where none, ``far_z(rays # [3, g]) # [g]``, the far layer, unless
        ``None``), the ``KA +`` :attr:`PROPOSED` sources nearest by angle that frame it; a ``2 grid``-px tile takes those of the grid pixels within ``grid`` px of it
        (every source when no grid pixel has any). Per tile, row-major: its count ``M`` and its sources by their best
        cosine at those grid pixels, descending (the shader's list fills with its likely members first), then the rest.
        ``# [tiles, K + 1]`` int"""
        H, W = depth.shape
        rows, cols = np.arange(grid // 2, H, grid), np.arange(grid // 2, W, grid)
        z = torch.from_numpy(depth[rows][:, cols].reshape(-1).astype(np.float32))  # [G]
        uv = torch.from_numpy(np.stack(np.meshgrid(cols + 0.5, rows + 0.5), 0).reshape(2, -1).astype(np.float32))
        d = A.float().T @ torch.cat([uv, torch.ones(1, uv.shape[1])])  # [3, G] rays at camera z = 1
        o = origin.float()
        if far_z is not None:
            z = torch.where(z > 0, z, far_z(d))
        p = o[:, None] + d * z  # [3, G]
        uvz = self._proj @ torch.cat([p, torch.ones(1, p.shape[1])])  # [K, 3, G]
        px = uvz[:, :2] / uvz[:, 2:].clamp_min(1e-6)
        framed = (uvz[:, 2] > 1e-6) & (px[:, 0] >= 0) & (px[:, 1] >= 0) & (px[:, 0] < self._size[0]) & (px[:, 1] < self._size[1])
        ds = p[None] - self._centers.float()[:, :, None]  # [K, 3, G] sources -> points
        t = d / d.square().sum(0).sqrt().clamp_min(1e-12)  # [3, G] unit rays
        cos = (ds * t).sum(1) / ds.square().sum(1).sqrt().clamp_min(1e-12)  # [K, G] (a plain sum: norm over 3 is slow)
        cos = cos.masked_fill(~framed | (z <= 0)[None], -2.0)
        c, idx = cos.topk(min(self.KA + self.PROPOSED, self.K), dim=0)  # [m, G]
        member = torch.zeros(self.K, len(z)).scatter_(0, idx, (c > -1.5).float()).reshape(1, self.K, len(rows), len(cols))
        th, tw = -(-H // (2 * grid)), -(-W // (2 * grid))
        member = torch.nn.functional.pad(member, (1, 2 * tw + 1 - len(cols), 1, 2 * th + 1 - len(rows)))
        member = torch.nn.functional.max_pool2d(member, 4, stride=2)[0] > 0  # [K, th, tw]
        member = member.reshape(self.K, -1)  # [K, tiles]
        count = member.sum(0)
        member[:, count == 0] = True  # no candidate: every source
        # the candidates by their best cosine near the tile, descending: the shader's list fills with its likely
        # members first, and the sources after them seldom pass its cheap test before the occlusion test's loads
        best = torch.nn.functional.pad(cos.reshape(1, self.K, len(rows), len(cols)),
                                       (1, 2 * tw + 1 - len(cols), 1, 2 * th + 1 - len(rows)), value=-2.0)
        best = torch.nn.functional.max_pool2d(best, 4, stride=2)[0].reshape(self.K, -1)  # [K, tiles]
        order = torch.argsort(torch.where(member, -best, 3.0), dim=0, stable=True)  # [K, tiles]: candidates first
        return torch.cat([member.sum(0)[None], order]).T.numpy()

    def close(self) -> None:
        """Free the program, textures and framebuffers (the context stays with its owner)."""
        if self._objects:
            with self.ctx:
                for obj in reversed(self._objects):
                    obj.release()
            self._objects.clear()
            self._frames.clear()
