// The GLSL of the omnirecon viewer: MeshRenderer.frame (omnirecon.mesh.ibr) as WebGL2 passes.
//
// A frame (Viewer.render in viewer.js) is drawn the way MeshRenderer.frame draws it:
//   1. depth: the mesh's camera z-depth per pixel (1 / gl_FragCoord.w, as omnirecon.render.raster), 0 = no triangle;
//   2. the fills' geometry (omnirecon.mesh.fill), only when on:
//      cracks (MeshRenderOptions.cracks = r): a missed pixel inside the closing of the covered pixels by a
//        (2r + 1)-px square (the image padded by its edge pixels) is a crack (closingShaders: four separable passes);
//        with the nearest fill the cracks need no passes of their own: every crack lies within its reach, and
//        takes the same nearest covered pixel's depth;
//      nearest (fill="nearest"): jump flooding (SEED_INIT, then JFA at steps 2^(m-1) .. 1 and 1 again) finds each
//        pixel's nearest covered pixel, Euclidean, ties to the smaller column, then the smaller image row (as
//        scipy's distance transform);
//   3. shade: per pixel the point o + z d(u, v) on its pixel-centre ray, z the mesh's depth; where the mesh misses,
//      a crack's nearest covered pixel's depth (found exactly in a window of radius ceil(r sqrt 2)), else with the
//      nearest fill the nearest covered pixel's within `reach` of the long side, else the far layer (the ray's exit
//      from the bounds box, at most at z-depth `far`; no occlusion test) or the background colour; then the blend:
//      network (ANGLE 0): omega = softmax_k MLP([ReLU(W F_k + b); u - u_k]) over the frame's sources (the nearest
//        `frame_sources` to its camera, uSel; -1e9 where a source does not see the point);
//      angle (ANGLE 1): the KA sources nearest by viewing angle among those that see the point get
//        (1 - a_k / a_next) / a_k (omnirecon.mesh.kernel.angle_weights), times mask_falloff at their pixel on points of
//        the mesh (MASKS), normalised; a point no source weighs blends every source of the frame alike.
// "Sees": in front, inside the image and, with the visibility test, z <= (1 + tol) * the largest rasterized source
// depth of the 2x2 pixel block around the projection (depth.bin).

// GLSL float literal that parses back to the same float32 (the JSON holds float32 values exactly)
export function lit(x) {
  if (!Number.isFinite(x)) throw new Error(`non-finite weight ${x}`);
  const s = String(x);
  return /[.eE]/.test(s) ? s : `${s}.0`;
}

// The appearance MLP with its weights as literals (unrolled: no uniform limits, no fetches).
export function mlpSource(mlp) {
  const C = mlp.feature_dim, C4 = Math.ceil(C / 4);
  const [h1, h2] = mlp.hidden;
  const lines = [`float appearanceLogit(vec4 z[${C4}], vec3 r) {`];
  for (let o = 0; o < h1; o++) {
    const w = mlp.w1[o];
    const terms = [lit(mlp.b1[o])];
    for (let j = 0; j < C4; j++) {
      const v = [0, 1, 2, 3].map((i) => (4 * j + i < C ? lit(w[4 * j + i]) : '0.0'));
      terms.push(`dot(z[${j}], vec4(${v.join(', ')}))`);
    }
    terms.push(`dot(r, vec3(${lit(w[C])}, ${lit(w[C + 1])}, ${lit(w[C + 2])}))`);
    lines.push(`  float a${o} = max(${terms.join(' + ')}, 0.0);`);
  }
  for (let o = 0; o < h2; o++) {
    const terms = [lit(mlp.b2[o])];
    for (let i = 0; i < h1; i++) terms.push(`${lit(mlp.w2[o][i])} * a${i}`);
    lines.push(`  float b${o} = max(${terms.join(' + ')}, 0.0);`);
  }
  const out = [lit(mlp.b3[0])];
  for (let i = 0; i < h2; i++) out.push(`${lit(mlp.w3[0][i])} * b${i}`);
  lines.push(`  return ${out.join(' + ')};`, '}');
  return lines.join('\n');
}

// mesh positions are in the model frame already (viewer.js transforms them once, in float64)
export const VERTEX_SHADER = `
precision highp float;
uniform mat4 modelToClip;
in vec3 position;
in vec4 color;
out vec3 vColor;
void main() {
  vColor = color.rgb;
  gl_Position = modelToClip * vec4(position, 1.0);
}`;

export const BAKED_FRAGMENT_SHADER = `
precision highp float;
in vec3 vColor;
out vec4 fragColor;
// mesh.glb's COLOR_0 is linear (glTF); the canvas is written without colour management, so encode sRGB here
vec3 toSrgb(vec3 c) {
  c = clamp(c, 0.0, 1.0);
  return mix(12.92 * c, 1.055 * pow(c, vec3(1.0 / 2.4)) - 0.055, step(vec3(0.0031308), c));
}
void main() { fragColor = vec4(toSrgb(vColor), 1.0); }`;

// pass 1: camera z-depth of the mesh (R32F target cleared to 0)
export const DEPTH_FRAGMENT_SHADER = `
precision highp float;
out vec4 fragColor;
void main() { fragColor = vec4(1.0 / gl_FragCoord.w, 0.0, 0.0, 1.0); }`;

// full-screen triangle of the screen-space passes
export const SCREEN_VERTEX_SHADER = `
precision highp float;
in vec3 position;
void main() { gl_Position = vec4(position.xy, 0.0, 1.0); }`;

// pass 2a: the crack mask, the closing of the covered pixels by a (2 CR + 1)-px square minus the covered pixels, as
// four separable passes (a square's dilation and erosion are a row pass and a column pass each). The closing is
// taken over the image padded by CR on each side with its edge pixels (omnirecon.mesh.fill.crack_pixels): the
// dilation runs over the padded domain, the erosion only at the image's pixels. Textures: DILATE_ROWS (W + 2 CR) x H,
// texel (i, j) for padded column i - CR, image row j; DILATE_COLUMNS (W + 2 CR) x (H + 2 CR), texel (i, j) for the
// padded pixel (i - CR, j - CR); ERODE_ROWS W x (H + 2 CR); ERODE_COLUMNS W x H: 1 at the cracks.
export function closingShaders(radius) {
  const head = `
precision highp float;
precision highp sampler2D;
#define CR ${radius}
uniform sampler2D uIn;
uniform sampler2D uZ;  // pass 1's depth, W x H: its size is the image's
out vec4 fragColor;`;
  const pass = (body) => `${head}
void main() {
  ivec2 size = textureSize(uZ, 0);
  ivec2 t = ivec2(gl_FragCoord.xy);
  float v = ${body.init};
  for (int d = -CR; d <= CR; d++) {
${body.loop}
  }
  fragColor = vec4(${body.out}, 0.0, 0.0, 1.0);
}`;
  return {
    dilateRows: pass({ init: '0.0', out: 'v', loop: `
    int sx = t.x - CR + d;  // padded column
    if (sx < -CR || sx >= size.x + CR) continue;
    if (texelFetch(uZ, ivec2(clamp(sx, 0, size.x - 1), t.y), 0).r > 0.0) v = 1.0;` }),
    dilateColumns: pass({ init: '0.0', out: 'v', loop: `
    int sy = t.y - CR + d;  // padded row
    if (sy < -CR || sy >= size.y + CR) continue;
    v = max(v, texelFetch(uIn, ivec2(t.x, clamp(sy, 0, size.y - 1)), 0).r);` }),
    erodeRows: pass({ init: '1.0', out: 'v', loop: `
    v = min(v, texelFetch(uIn, ivec2(t.x + CR + d, t.y), 0).r);` }),
    erodeColumns: pass({ init: '1.0', out: 'texelFetch(uZ, t, 0).r > 0.0 ? 0.0 : v', loop: `
    v = min(v, texelFetch(uIn, ivec2(t.x, t.y + CR + d), 0).r);` }),
  };
}

// the order of equally near covered pixels: the smaller column, then the smaller image row (the larger GL row)
const NEARER = `
bool nearer(vec2 a, float da, vec2 b, float db) {
  return da < db || (da == db && (a.x < b.x || (a.x == b.x && a.y > b.y)));
}`;

// pass 2b: jump flooding seeds (RG32F): a covered pixel is its own nearest, the others have none (-1)
export const SEED_INIT_SHADER = `
precision highp float;
precision highp sampler2D;
uniform sampler2D uZ;
out vec4 fragColor;
void main() {
  ivec2 p = ivec2(gl_FragCoord.xy);
  fragColor = texelFetch(uZ, p, 0).r > 0.0 ? vec4(vec2(p), 0.0, 1.0) : vec4(-1.0, -1.0, 0.0, 1.0);
}`;

// pass 2c: one jump-flooding step
export const JFA_SHADER = `
precision highp float;
precision highp sampler2D;
uniform sampler2D uSeed;
uniform int uStep;
out vec4 fragColor;
${NEARER}
void main() {
  ivec2 size = textureSize(uSeed, 0);
  ivec2 p = ivec2(gl_FragCoord.xy);
  vec2 best = vec2(-1.0);
  float bestD = 3.0e38;
  for (int dy = -1; dy <= 1; dy++) {
    for (int dx = -1; dx <= 1; dx++) {
      ivec2 q = p + uStep * ivec2(dx, dy);
      if (q.x < 0 || q.y < 0 || q.x >= size.x || q.y >= size.y) continue;
      vec2 s = texelFetch(uSeed, q, 0).xy;
      if (s.x < 0.0) continue;
      vec2 e = s - vec2(p);
      float d = dot(e, e);
      if (nearer(s, d, best, bestD)) { best = s; bestD = d; }
    }
  }
  fragColor = vec4(best, 0.0, 1.0);
}`;

// pass 3: the image-based shading of every pixel (module comment)
export function shadeShader(bundle, opts) {
  const K = bundle.sources.count, C4 = Math.ceil(bundle.mlp.feature_dim / 4);
  const nsel = opts.frameSources > 0 && opts.frameSources < K ? opts.frameSources : 0;  // 0: every source
  const n = nsel || K;
  const ka = Math.max(1, Math.min(opts.angleSources || n, n));
  const cr = Math.max(0, opts.cracks | 0);
  return `
precision highp float;
precision highp int;
precision highp sampler2D;
precision highp sampler2DArray;
#define K ${K}
#define C4 ${C4}
#define NSEL ${nsel}
#define NMAX ${n}
#define KA ${ka}
#define ANGLE ${opts.blend === 'angle' ? 1 : 0}
#define CR ${cr}
#define CRS ${Math.ceil(cr * Math.SQRT2 - 1e-9)}
#define INF 1.0e30
uniform sampler2DArray uImages;   // RGBA8, W x H, layer k: RGB and min(d^2, 255) of the object mask (bundle.py)
uniform sampler2DArray uFeatures; // RGBA32F, (w + 2) x (h + 2), layer k * C4 + j: channels 4j..4j+3 of W F_k + b
uniform sampler2DArray uDepth;    // R32F, (W + 1) x (H + 1): max rasterized depth of each 2x2 pixel block
uniform sampler2D uCams;          // RGBA32F, 4 x K: rows 0-2 of K_k [R_k | t_k], then (c_k, 1)
uniform sampler2D uZ;             // this frame's z-depth, 0 = no triangle
uniform sampler2D uSeed;          // the nearest covered pixel (GL pixel coordinates), -1 = none
uniform sampler2D uCrack;         // 1 at the cracks (the closing's passes)
#if NSEL > 0
uniform int uSel[NSEL];           // the frame's sources
#else
uniform ivec4 uOrder[${Math.ceil(K / 4)}];       // every source, nearest to the frame's camera first
#endif
uniform mat4 uC2W;                // target camera-to-world, model frame (orthonormal rotation)
uniform vec4 uIntr;               // fx, fy, cx, cy (pixels)
uniform float uHeight;            // canvas height (pixels): row v = H - gl_FragCoord.y
uniform vec3 uBoxLo;
uniform vec3 uBoxHi;
uniform float uFar;
uniform vec3 uBackground;
uniform int uFill;                // 0: background colour, 1: far layer, 2: nearest, then the far layer
uniform float uReach;             // the nearest fill's reach in pixels
uniform int uCracks;
uniform vec2 uImageSize;          // W, H of the sources
uniform vec2 uFeatSize;           // w, h (unpadded)
uniform int uVisibility;
uniform float uVisTol;
uniform int uMasks;
uniform float uMaskReach;
uniform float uMaskFloor;
out vec4 fragColor;

${mlpSource(bundle.mlp)}
${NEARER}

// the i-th source of the frame: its NSEL nearest, or every source, nearest to the frame's camera first (uOrder:
// the angle blend then finds each point's nearest sources early and skips the rest by their cosine alone)
int sourceAt(int i) {
#if NSEL > 0
  return uSel[i];
#else
  return uOrder[i / 4][i % 4];
#endif
}

vec3 centre(int k) { return texelFetch(uCams, ivec2(3, k), 0).xyz; }

// (u z, v z, z) of model point p in source k
vec3 project(int k, vec3 p) {
  vec4 q = vec4(p, 1.0);
  return vec3(dot(texelFetch(uCams, ivec2(0, k), 0), q), dot(texelFetch(uCams, ivec2(1, k), 0), q),
              dot(texelFetch(uCams, ivec2(2, k), 0), q));
}

bool framed(float z, vec2 uv) {
  return z > 1e-6 && uv.x >= 0.0 && uv.y >= 0.0 && uv.x < uImageSize.x && uv.y < uImageSize.y;
}

// the occlusion test (omnirecon.mesh.kernel.unoccluded)
bool unoccluded(int k, vec2 uv, float z) {
  int b = int(clamp(floor(uv.x - 0.5), -1.0, uImageSize.x - 1.0)) + 1;
  int a = int(clamp(floor(uv.y - 0.5), -1.0, uImageSize.y - 1.0)) + 1;
  return z <= texelFetch(uDepth, ivec3(b, a, k), 0).r * (1.0 + uVisTol);
}

// grid_sample(images, align_corners=False, padding_mode="border") at source pixel coordinates uv
vec3 sampleImage(int k, vec2 uv) {
  vec2 hi = uImageSize - 1.0;
  vec2 xy = clamp(uv - 0.5, vec2(0.0), hi);
  vec2 c = floor(xy);
  vec2 f = xy - c;
  vec2 g = 1.0 - f;
  ivec2 i0 = ivec2(c);
  ivec2 i1 = min(i0 + 1, ivec2(hi));
  vec3 t00 = texelFetch(uImages, ivec3(i0.x, i0.y, k), 0).rgb;
  vec3 t01 = texelFetch(uImages, ivec3(i1.x, i0.y, k), 0).rgb;
  vec3 t10 = texelFetch(uImages, ivec3(i0.x, i1.y, k), 0).rgb;
  vec3 t11 = texelFetch(uImages, ivec3(i1.x, i1.y, k), 0).rgb;
  return t00 * (g.x * g.y) + t01 * (f.x * g.y) + t10 * (g.x * f.y) + t11 * (f.x * f.y);
}

// mask_falloff at the pixel uv falls in (omnirecon.mesh.kernel.mask_factor): clip(d / reach, floor, 1)
float maskFactor(int k, vec2 uv) {
  ivec2 q = ivec2(clamp(floor(uv), vec2(0.0), uImageSize - 1.0));
  float d2 = floor(texelFetch(uImages, ivec3(q, k), 0).a * 255.0 + 0.5);
  return clamp(sqrt(d2) / uMaskReach, uMaskFloor, 1.0);
}

#if ANGLE == 0
vec3 shadeNetwork(vec3 p, vec3 t, bool layer) {
  float logits[NMAX];
  vec3 colours[NMAX];
  float top = -3.0e38;
  for (int i = 0; i < NMAX; i++) {
    int k = sourceAt(i);
    vec3 uvz = project(k, p);
    vec2 uv = uvz.xy / max(uvz.z, 1e-6);
    bool seen = framed(uvz.z, uv) && (layer || uVisibility == 0 || unoccluded(k, uv, uvz.z));
    colours[i] = sampleImage(k, uv);
    float l = -1.0e9;
    if (seen) {
      vec2 xy = uv / uImageSize * uFeatSize + 0.5;  // texel-centre coordinates in the padded map
      vec2 c = floor(xy);
      vec2 f = xy - c;
      vec2 g = 1.0 - f;
      ivec2 i0 = clamp(ivec2(c), ivec2(0), ivec2(uFeatSize) + 1);
      ivec2 i1 = min(i0 + 1, ivec2(uFeatSize) + 1);
      vec4 z4[C4];
      for (int j = 0; j < C4; j++) {
        int layerIndex = k * C4 + j;
        vec4 t00 = texelFetch(uFeatures, ivec3(i0.x, i0.y, layerIndex), 0);
        vec4 t01 = texelFetch(uFeatures, ivec3(i1.x, i0.y, layerIndex), 0);
        vec4 t10 = texelFetch(uFeatures, ivec3(i0.x, i1.y, layerIndex), 0);
        vec4 t11 = texelFetch(uFeatures, ivec3(i1.x, i1.y, layerIndex), 0);
        z4[j] = max(t00 * (g.x * g.y) + t01 * (f.x * g.y) + t10 * (g.x * f.y) + t11 * (f.x * f.y), 0.0);
      }
      vec3 dk = p - centre(k);
      l = appearanceLogit(z4, t - dk / max(length(dk), 1e-12));
    }
    logits[i] = l;
    top = max(top, l);
  }
  vec3 rgb = vec3(0.0);
  float total = 0.0;
  for (int i = 0; i < NMAX; i++) {
    float e = exp(logits[i] - top);
    total += e;
    rgb += e * colours[i];
  }
  return rgb / total;
}
#else
vec3 shadeAngle(vec3 p, vec3 t, bool layer, bool onMesh) {
  // the KA + 1 sources that see p with the largest cosines, descending
  float bc[KA + 1];
  int bi[KA + 1];
  vec2 buv[KA + 1];
  int k1 = min(KA + 1, NMAX);
  for (int j = 0; j <= KA; j++) { bc[j] = -2.0; bi[j] = 0; buv[j] = vec2(0.0); }
  for (int i = 0; i < NMAX; i++) {
    int k = sourceAt(i);
    vec3 dk = p - centre(k);
    float c = dot(t, dk) / max(length(dk), 1e-12);
    if (c <= bc[k1 - 1]) continue;  // not among the nearest so far: neither projected nor tested
    vec3 uvz = project(k, p);
    vec2 uv = uvz.xy / max(uvz.z, 1e-6);
    if (!framed(uvz.z, uv)) continue;
    if (!layer && uVisibility != 0 && !unoccluded(k, uv, uvz.z)) continue;
    int j = k1 - 1;
    for (; j > 0 && bc[j - 1] < c; j--) { bc[j] = bc[j - 1]; bi[j] = bi[j - 1]; buv[j] = buv[j - 1]; }
    bc[j] = c;
    bi[j] = k;
    buv[j] = uv;
  }
  float ang[KA + 1];
  for (int j = 0; j <= KA; j++) ang[j] = bc[j] < -1.5 ? INF : acos(clamp(bc[j], -1.0, 1.0));
  float thresh = NMAX > KA ? ang[KA] : INF;
  float w[KA];
  float total = 0.0;
  for (int j = 0; j < KA; j++) {
    float a = ang[j];
    w[j] = a < INF ? max(1.0 - a / thresh, 0.0) / max(a, 1e-3) : 0.0;
    total += w[j];
  }
  vec3 rgb = vec3(0.0);
  if (total > 0.0) {
    for (int j = 0; j < KA; j++) w[j] /= total;
    if (uMasks != 0 && onMesh) {
      float u[KA];
      float t2 = 0.0;
      for (int j = 0; j < KA; j++) { u[j] = w[j] * maskFactor(bi[j], buv[j]); t2 += u[j]; }
      if (t2 > 0.0) for (int j = 0; j < KA; j++) w[j] = u[j] / t2;
    }
    for (int j = 0; j < KA; j++) if (w[j] > 0.0) rgb += w[j] * sampleImage(bi[j], buv[j]);
    return rgb;
  }
  // no source weighs p: every source of the frame alike (times the mask factor on the mesh)
  float u2 = 0.0;
  vec3 acc = vec3(0.0), plain = vec3(0.0);
  for (int i = 0; i < NMAX; i++) {
    int k = sourceAt(i);
    vec3 uvz = project(k, p);
    vec2 uv = uvz.xy / max(uvz.z, 1e-6);
    vec3 c = sampleImage(k, uv);
    float f = (uMasks != 0 && onMesh) ? maskFactor(k, uv) : 1.0;
    acc += f * c;
    u2 += f;
    plain += c;
  }
  return u2 > 0.0 ? acc / u2 : plain / float(NMAX);
}
#endif

// the depth of the nearest covered pixel within CRS (a crack's is: it lies within CR in each axis)
float nearestInWindow(ivec2 p) {
  ivec2 size = textureSize(uZ, 0);
  vec2 best = vec2(-1.0);
  float bestD = 3.0e38, z = 0.0;
  for (int dy = -CRS; dy <= CRS; dy++) {
    for (int dx = -CRS; dx <= CRS; dx++) {
      ivec2 q = p + ivec2(dx, dy);
      if (q.x < 0 || q.y < 0 || q.x >= size.x || q.y >= size.y) continue;
      float zq = texelFetch(uZ, q, 0).r;
      float d = float(dx * dx + dy * dy);
      if (zq > 0.0 && nearer(vec2(q), d, best, bestD)) { best = vec2(q); bestD = d; z = zq; }
    }
  }
  return z;
}

// the far layer's z-depth (omnirecon.mesh.fill.exit_depth): where the ray leaves the box, at most far
float exitDepth(vec3 o, vec3 d) {
  vec3 safe = mix(d, vec3(1e-12), lessThan(abs(d), vec3(1e-12)));
  vec3 t1 = (uBoxLo - o) / safe, t2 = (uBoxHi - o) / safe;
  vec3 tmin = min(t1, t2), tmax = max(t1, t2);
  float tIn = max(max(tmin.x, tmin.y), tmin.z), tOut = min(min(tmax.x, tmax.y), tmax.z);
  return (tOut > max(tIn, 0.0) && tOut > 0.0) ? min(tOut, uFar) : uFar;
}

void main() {
  ivec2 px = ivec2(gl_FragCoord.xy);
  float z = texelFetch(uZ, px, 0).r;
  bool hit = z > 0.0, layer = false;
  vec2 uv = vec2(gl_FragCoord.x, uHeight - gl_FragCoord.y);  // pixel centre, image row from the top
  vec3 d = mat3(uC2W) * vec3((uv.x - uIntr.z) / uIntr.x, (uv.y - uIntr.w) / uIntr.y, 1.0);  // camera z = 1
  vec3 o = uC2W[3].xyz;
  if (!hit) {
    float zn = 0.0;
#if CR > 0
    if (uCracks != 0 && texelFetch(uCrack, px, 0).r > 0.5) zn = nearestInWindow(px);
#endif
    if (zn <= 0.0 && uFill == 2) {
      vec2 s = texelFetch(uSeed, px, 0).xy;
      if (s.x >= 0.0 && length(s - vec2(px)) <= uReach) zn = texelFetch(uZ, ivec2(s), 0).r;
    }
    if (zn > 0.0) {
      z = zn;
    } else if (uFill == 0) {
      fragColor = vec4(uBackground, 1.0);
      return;
    } else {
      z = exitDepth(o, d);
      layer = true;
    }
  }
  vec3 p = o + z * d;
  vec3 t = d / max(length(d), 1e-12);
#if ANGLE == 1
  fragColor = vec4(shadeAngle(p, t, layer, hit), 1.0);
#else
  fragColor = vec4(shadeNetwork(p, t, layer), 1.0);
#endif
}`;
}
