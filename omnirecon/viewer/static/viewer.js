// omnirecon mesh viewer: real-time image-based rendering of a baked mesh in a WebGL2 fragment shader.
//
// Per pixel (exactly omnirecon.render.mesh_ibr.MeshRenderer.render, the fused path):
//   surface point p (interpolated model-frame vertex positions, perspective-correct)
//   for every source k: (u z, v z, z) = P_k (p, 1); seen = z > 1e-6, 0 <= u < W, 0 <= v < H
//     [and, with the visibility test, z <= (1 + tol) * max of the 4 rasterized source depths around (u, v)]
//     feature f = bilinear sample of (W F_k + b) (align_corners=False, one-texel border of b)
//     logit = MLP([ReLU(f); normalize(p - o) - normalize(p - c_k)]), -1e9 where not seen
//     colour c_k = bilinear sample of source image k (border clamp)
//   omega = softmax_k(logit); rgb = sum_k omega_k c_k.
// With blend=angle (MeshRenderOptions.blend="angle", omnirecon.mesh.ibr.angle_weights): no network; each point's
//   `sources` seen sources with the smallest angle a_k between normalize(p - c_k) and normalize(p - o) get
//   (1 - a_k / a_next) / a_k (a_next: the next seen source's angle, infinite when there is none), normalised.
// Where no triangle covers a pixel, the far fill (omnirecon.mesh.fill, MeshRenderOptions.fill="far"): the
// point where the pixel-centre ray leaves the scene's bounds box, at most at z-depth `far`, shaded by the
// same blend without the occlusion test (a full-screen pass drawn before the mesh); with fill off or in baked
// mode, the background colour. (The Python renderer's fill="nearest" is not drawn here: the far fill instead.)
// Baked mode draws the exported per-vertex colours instead (also the automatic fallback when float
// textures or the IBR shader do not work here).
//
// Cameras are OpenCV pinhole cameras (x right, y down, z forward, camera-to-world, pixel centres at
// +0.5). A fixed camera comes from the URL (?camera=<JSON>) or window.omnirecon.setCamera(...):
//   {"fx", "fy", "cx", "cy", "width", "height", "c2w": 4x4 rows, "frame": "input" (default) | "model"}
// "input" is the frame of mesh.glb (the user's scene); "model" the normalised frame the model works in.
// Other URL parameters: mode=ibr|baked, vis=0|1, fill=0|1, blend=network|angle, ui=0|1, scale=<render resolution
// factor of the interactive view>.

import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';

THREE.ColorManagement.enabled = false; // raw values end to end: images, vertex colours, background

const root = document.documentElement;
root.dataset.state = 'loading';
const params = new URLSearchParams(location.search);
let readyResolve, readyReject;
const ready = new Promise((res, rej) => { readyResolve = res; readyReject = rej; });
ready.catch(() => {});

// ---------------------------------------------------------------- small float64 matrix helpers (row-major)
const mat = {
  mul(A, B) { // 4x4 @ 4x4
    const C = new Array(16).fill(0);
    for (let i = 0; i < 4; i++) for (let j = 0; j < 4; j++) {
      let s = 0;
      for (let k = 0; k < 4; k++) s += A[4 * i + k] * B[4 * k + j];
      C[4 * i + j] = s;
    }
    return C;
  },
  flat(M) { return M.flat ? M.flat() : Array.from(M); },
  det3(M) {
    return M[0] * (M[5] * M[10] - M[6] * M[9]) - M[1] * (M[4] * M[10] - M[6] * M[8]) + M[2] * (M[4] * M[9] - M[5] * M[8]);
  },
  rigidInverse(T) { // [R t; 0 1] -> [R^T, -R^T t]
    const R = [T[0], T[1], T[2], T[4], T[5], T[6], T[8], T[9], T[10]];
    const t = [T[3], T[7], T[11]];
    const out = new Array(16).fill(0);
    for (let i = 0; i < 3; i++) {
      for (let j = 0; j < 3; j++) out[4 * i + j] = R[3 * j + i];
      out[4 * i + 3] = -(R[i] * t[0] + R[3 + i] * t[1] + R[6 + i] * t[2]);
    }
    out[15] = 1;
    return out;
  },
  apply(T, p) {
    return [0, 1, 2].map((i) => T[4 * i] * p[0] + T[4 * i + 1] * p[1] + T[4 * i + 2] * p[2] + T[4 * i + 3]);
  },
  three(M) { return new THREE.Matrix4().set(...M); }, // row-major array -> THREE.Matrix4
};

// OpenCV camera frame -> clip space for a canvas whose row 0 is at the top: window (u, H - v), w_clip = z.
// The y flip turns front faces (clockwise in y-down pixels, see omnirecon.render.raster) counter-clockwise,
// GL's default front face, so three.js's FrontSide culls back faces like the Python renderer.
function clipMatrix(cam, near, far) {
  const { fx, fy, cx, cy, width: W, height: H } = cam;
  return [
    2 * fx / W, 0, 2 * cx / W - 1, 0,
    0, -2 * fy / H, 1 - 2 * cy / H, 0,
    0, 0, (far + near) / (far - near), -2 * far * near / (far - near),
    0, 0, 1, 0,
  ];
}

// ---------------------------------------------------------------- loading
async function fetchChecked(url, kind) {
  const r = await fetch(url);
  if (!r.ok) throw new Error(`${url}: HTTP ${r.status}`);
  return kind === 'json' ? r.json() : r.arrayBuffer();
}

function floatTexturesWork() {
  // Probe on a separate context: upload an RGBA32F texel, texelFetch it into the default framebuffer.
  try {
    const c = document.createElement('canvas');
    c.width = c.height = 1;
    const gl = c.getContext('webgl2', { antialias: false });
    if (!gl) return 'WebGL2 is not available';
    const tex = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, tex);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32F, 1, 1, 0, gl.RGBA, gl.FLOAT, new Float32Array([0.25, 0.5, 0.75, 1]));
    if (gl.getError() !== gl.NO_ERROR) return 'RGBA32F textures are not supported';
    const sh = (type, src) => { const s = gl.createShader(type); gl.shaderSource(s, src); gl.compileShader(s); return s; };
    const prog = gl.createProgram();
    gl.attachShader(prog, sh(gl.VERTEX_SHADER, '#version 300 es\nvoid main(){gl_Position=vec4(0,0,0,1);gl_PointSize=1.0;}'));
    gl.attachShader(prog, sh(gl.FRAGMENT_SHADER, '#version 300 es\nprecision highp float;uniform highp sampler2D t;' +
      'out vec4 o;void main(){o=texelFetch(t,ivec2(0),0);}'));
    gl.linkProgram(prog);
    if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) return 'float texture probe did not link';
    gl.useProgram(prog);
    gl.viewport(0, 0, 1, 1);
    gl.drawArrays(gl.POINTS, 0, 1);
    const px = new Uint8Array(4);
    gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px);
    gl.getExtension('WEBGL_lose_context')?.loseContext();
    const ok = Math.abs(px[0] - 64) <= 1 && Math.abs(px[1] - 128) <= 1 && Math.abs(px[2] - 191) <= 1;
    return ok ? null : `float texture probe read ${Array.from(px)}`;
  } catch (e) {
    return `float texture probe failed: ${e}`;
  }
}

// GLSL float literal that parses back to the same float32 (the JSON holds float32 values exactly)
function lit(x) {
  if (!Number.isFinite(x)) throw new Error(`non-finite weight ${x}`);
  const s = String(x);
  return /[.eE]/.test(s) ? s : `${s}.0`;
}

// The appearance MLP with its weights as literals (unrolled: no uniform limits, no fetches).
function mlpSource(mlp) {
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

const VERTEX_SHADER = `
precision highp float;
uniform mat4 toModel;
uniform mat4 modelToClip;
in vec3 position;
in vec4 color;
out vec3 vModel;
out vec3 vColor;
void main() {
  vec4 pm = toModel * vec4(position, 1.0);
  vModel = pm.xyz;
  vColor = color.rgb;
  gl_Position = modelToClip * pm;
}`;

const BAKED_FRAGMENT_SHADER = `
precision highp float;
in vec3 vModel;
in vec3 vColor;
out vec4 fragColor;
// mesh.glb's COLOR_0 is linear (glTF); the canvas is written without colour management, so encode sRGB here
vec3 toSrgb(vec3 c) {
  c = clamp(c, 0.0, 1.0);
  return mix(12.92 * c, 1.055 * pow(c, vec3(1.0 / 2.4)) - 0.055, step(vec3(0.0031308), c));
}
void main() { fragColor = vec4(toSrgb(vColor), 1.0); }`;

// fill=false: the mesh's fragments (p = interpolated surface point); fill=true: the far fill's full-screen pass
function ibrFragmentShader(bundle, fill = false) {
  const K = bundle.sources.count, C4 = Math.ceil(bundle.mlp.feature_dim / 4);
  const main = fill ? `
uniform mat4 uC2W;    // target camera-to-world, model frame (orthonormal rotation)
uniform vec4 uIntr;   // fx, fy, cx, cy (pixels)
uniform float uHeight; // canvas height (pixels): row v = H - gl_FragCoord.y
uniform vec3 uBoxLo;
uniform vec3 uBoxHi;
uniform float uFar;
void main() {
  // omnirecon.mesh.fill.fill_points: the ray's exit from the box, at most at z-depth far (direction with z = 1)
  vec2 uv = vec2(gl_FragCoord.x, uHeight - gl_FragCoord.y);
  vec3 d = mat3(uC2W) * vec3((uv.x - uIntr.z) / uIntr.x, (uv.y - uIntr.w) / uIntr.y, 1.0);
  vec3 o = uC2W[3].xyz;
  vec3 safe = mix(d, vec3(1e-12), lessThan(abs(d), vec3(1e-12)));
  vec3 t1 = (uBoxLo - o) / safe, t2 = (uBoxHi - o) / safe;
  vec3 tmin = min(t1, t2), tmax = max(t1, t2);
  float tIn = max(max(tmin.x, tmin.y), tmin.z), tOut = min(min(tmax.x, tmax.y), tmax.z);
  float z = (tOut > max(tIn, 0.0) && tOut > 0.0) ? min(tOut, uFar) : uFar;
  fragColor = vec4(shade(o + z * d, true), 1.0);
}` : `
in vec3 vModel;
in vec3 vColor;
void main() { fragColor = vec4(shade(vModel, false), 1.0); }`;
  return `
precision highp float;
precision highp int;
precision highp sampler2DArray;
#define K ${K}
#define C4 ${C4}
uniform sampler2DArray uImages;   // RGBA8, W x H, layer k
uniform sampler2DArray uFeatures; // RGBA32F, (w + 2) x (h + 2), layer k * C4 + j: channels 4j..4j+3 of W F_k + b
uniform sampler2DArray uDepth;    // R32F, (W + 1) x (H + 1): max rasterized depth of each 2x2 pixel block
uniform mat4 uProj[K];            // model point -> (u z, v z, z, 1)
uniform vec3 uCenter[K];
uniform vec3 uOrigin;             // target camera centre, model frame
uniform vec2 uImageSize;          // W, H
uniform vec2 uFeatSize;           // w, h (unpadded)
uniform int uVisibility;
uniform float uVisTol;
uniform int uBlend;               // 0: the appearance network, 1: the angle blend
uniform int uAngleK;              // the angle blend's sources per point (0: all)
out vec4 fragColor;

${mlpSource(bundle.mlp)}

vec3 unit(vec3 d) { return d / max(length(d), 1e-12); }

// grid_sample(images, align_corners=False, padding_mode="border")
vec3 sampleImage(int k, vec2 st) {
  vec2 hi = uImageSize - 1.0;
  vec2 xy = clamp(st * uImageSize - 0.5, vec2(0.0), hi);
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

// angle_weights: the blend weights from each source's viewing angle (1e30 = not seen)
void angleWeights(float ang[K], out float w[K]) {
  int kk = uAngleK > 0 ? min(uAngleK, K) : K;
  float aK = 1.0e30, aNext = 1.0e30;  // the kk-th and (kk + 1)-th smallest angles
  for (int i = 0; i < K; i++) {
    int rank = 0;
    for (int j = 0; j < K; j++) rank += (ang[j] < ang[i] || (ang[j] == ang[i] && j < i)) ? 1 : 0;
    if (rank == kk - 1) aK = ang[i];
    if (rank == kk) aNext = ang[i];
  }
  float total = 0.0;
  for (int k = 0; k < K; k++) {
    float a = ang[k];
    float fall = aNext >= 1.0e29 ? 1.0 : max(1.0 - a / aNext, 0.0);
    w[k] = (a < 1.0e29 && a <= aK) ? fall / max(a, 1e-3) : 0.0;
    total += w[k];
  }
  for (int k = 0; k < K; k++) w[k] = total > 0.0 ? w[k] / total : 1.0 / float(K);
}

vec3 shade(vec3 p, bool layer) {
  vec3 u = unit(p - uOrigin);
  float logits[K];
  float ang[K];
  vec3 colours[K];
  float top = -3.0e38;
  for (int k = 0; k < K; k++) {
    vec3 uvz = (uProj[k] * vec4(p, 1.0)).xyz;
    float z = uvz.z;
    vec2 uv = uvz.xy / max(z, 1e-6);
    vec2 st = uv / uImageSize;
    bool seen = z > 1e-6 && uv.x >= 0.0 && uv.y >= 0.0 && uv.x < uImageSize.x && uv.y < uImageSize.y;
    if (seen && uVisibility != 0 && !layer) {
      int b = int(clamp(floor(uv.x - 0.5), -1.0, uImageSize.x - 1.0)) + 1;
      int a = int(clamp(floor(uv.y - 0.5), -1.0, uImageSize.y - 1.0)) + 1;
      seen = z <= texelFetch(uDepth, ivec3(b, a, k), 0).r * (1.0 + uVisTol);
    }
    colours[k] = sampleImage(k, st);
    ang[k] = seen ? acos(clamp(dot(u, unit(p - uCenter[k])), -1.0, 1.0)) : 1.0e30;
    float l = -1.0e9;
    if (seen && uBlend == 0) {
      vec2 xy = st * uFeatSize + 0.5;  // texel-centre coordinates in the padded map
      vec2 c = floor(xy);
      vec2 f = xy - c;
      vec2 g = 1.0 - f;
      ivec2 i0 = clamp(ivec2(c), ivec2(0), ivec2(uFeatSize) + 1);
      ivec2 i1 = min(i0 + 1, ivec2(uFeatSize) + 1);
      vec4 z4[C4];
      for (int j = 0; j < C4; j++) {
        int layer = k * C4 + j;
        vec4 t00 = texelFetch(uFeatures, ivec3(i0.x, i0.y, layer), 0);
        vec4 t01 = texelFetch(uFeatures, ivec3(i1.x, i0.y, layer), 0);
        vec4 t10 = texelFetch(uFeatures, ivec3(i0.x, i1.y, layer), 0);
        vec4 t11 = texelFetch(uFeatures, ivec3(i1.x, i1.y, layer), 0);
        z4[j] = max(t00 * (g.x * g.y) + t01 * (f.x * g.y) + t10 * (g.x * f.y) + t11 * (f.x * f.y), 0.0);
      }
      l = appearanceLogit(z4, u - unit(p - uCenter[k]));
    }
    logits[k] = l;
    top = max(top, l);
  }
  vec3 rgb = vec3(0.0);
  if (uBlend == 1) {
    float w[K];
    angleWeights(ang, w);
    for (int k = 0; k < K; k++) rgb += w[k] * colours[k];
    return rgb;
  }
  float total = 0.0;
  for (int k = 0; k < K; k++) {
    float e = exp(logits[k] - top);
    total += e;
    rgb += e * colours[k];
  }
  return rgb / total;
}
${main}`;
}

const FILL_VERTEX_SHADER = `
precision highp float;
in vec3 position;
void main() { gl_Position = vec4(position.xy, 0.0, 1.0); }`;

function arrayTexture(data, width, height, depth, format, type) {
  const t = new THREE.DataArrayTexture(data, width, height, depth);
  t.format = format;
  t.type = type;
  t.minFilter = t.magFilter = THREE.NearestFilter;
  t.generateMipmaps = false;
  t.unpackAlignment = 1;
  t.needsUpdate = true;
  return t;
}

// ---------------------------------------------------------------- the viewer
class Viewer {
  constructor(bundle, geometry) {
    this.bundle = bundle;
    this.toModel = mat.flat(bundle.to_model);
    this.toInput = mat.flat(bundle.to_input);
    this.modelScale = Math.cbrt(Math.abs(mat.det3(this.toModel)));
    this.mirror = mat.det3(this.toModel) < 0;
    this.box = bundle.mesh_box; // model frame [[lo], [hi]]
    this.background = bundle.background;
    this.fixed = null;
    this.mode = 'ibr';
    this.visibility = !!bundle.visibility.default;
    this.fill = !!(bundle.fill && bundle.fill.default);
    this.blend = bundle.blend && bundle.blend.default === 'angle' ? 'angle' : 'network';
    this.fallbackReason = null;

    const fixed = params.has('camera');
    this.canvas = document.createElement('canvas');
    document.body.appendChild(this.canvas);
    this.renderer = new THREE.WebGLRenderer({ canvas: this.canvas, antialias: false, alpha: false,
      preserveDrawingBuffer: fixed || params.get('preserve') === '1', powerPreference: 'high-performance' });
    this.renderer.outputColorSpace = THREE.LinearSRGBColorSpace;
    this.renderer.toneMapping = THREE.NoToneMapping;
    this.renderer.setClearColor(new THREE.Color(...this.background), 1);
    // ?scale=0.5 renders the interactive view at half resolution (software WebGL is slow)
    this.scale = Math.min(Math.max(parseFloat(params.get('scale') || '1') || 1, 0.1), 4);
    this.renderer.setPixelRatio(fixed ? 1 : (window.devicePixelRatio || 1) * this.scale);
    this.shaderErrors = [];
    this.renderer.debug.checkShaderErrors = true;
    this.renderer.debug.onShaderError = (gl, program, vs, fs) => {
      this.shaderErrors.push(gl.getShaderInfoLog(fs) || gl.getProgramInfoLog(program) || 'shader error');
    };

    this.scene = new THREE.Scene();
    this.dummyCamera = new THREE.Camera(); // our materials use their own camera uniforms
    const side = this.mirror ? THREE.BackSide : THREE.FrontSide;
    const common = { toModel: { value: mat.three(this.toModel) }, modelToClip: { value: new THREE.Matrix4() } };
    this.bakedMaterial = new THREE.RawShaderMaterial({ glslVersion: THREE.GLSL3, side, uniforms: common,
      vertexShader: VERTEX_SHADER, fragmentShader: BAKED_FRAGMENT_SHADER });
    this.mesh = new THREE.Mesh(geometry, this.bakedMaterial);
    this.mesh.frustumCulled = false;
    this.mesh.matrixAutoUpdate = false;
    this.scene.add(this.mesh);
    this.ibrMaterial = null;
    this.fillMesh = null;
    this.common = common;

    // orbit camera (three.js convention, input frame)
    this.orbit = new THREE.PerspectiveCamera(50, 1, 1e-3, 1e3);
    this.controls = null;
  }

  async initIBR(buffers) {
    const b = this.bundle, src = b.sources;
    if (!geometryHasColor(this.mesh.geometry)) this.note('mesh.glb has no vertex colours');
    const reason = floatTexturesWork();
    if (reason) throw new Error(reason);
    const gl = this.renderer.getContext();
    const layers = src.count * Math.ceil(b.mlp.feature_dim / 4);
    const maxLayers = gl.getParameter(gl.MAX_ARRAY_TEXTURE_LAYERS), maxSize = gl.getParameter(gl.MAX_TEXTURE_SIZE);
    if (layers > maxLayers) throw new Error(`${layers} feature layers > MAX_ARRAY_TEXTURE_LAYERS ${maxLayers}`);
    if (Math.max(src.width + 1, src.height + 1) > maxSize) throw new Error(`source images exceed MAX_TEXTURE_SIZE ${maxSize}`);
    const f = b.textures.features.shape; // [K, C4, h + 2, w + 2, 4]
    const W = src.width, H = src.height;
    const images = arrayTexture(new Uint8Array(buffers.images), W, H, src.count, THREE.RGBAFormat, THREE.UnsignedByteType);
    const features = arrayTexture(new Float32Array(buffers.features), f[3], f[2], f[0] * f[1], THREE.RGBAFormat,
      THREE.FloatType);
    const depth = arrayTexture(new Float32Array(buffers.depth), W + 1, H + 1, src.count, THREE.RedFormat, THREE.FloatType);
    const proj = src.proj.map((P) => mat.three(mat.flat(P)));
    const centers = src.centers.map((c) => new THREE.Vector3(...c));
    this.ibrMaterial = new THREE.RawShaderMaterial({
      glslVersion: THREE.GLSL3, side: this.bakedMaterial.side, vertexShader: VERTEX_SHADER,
      fragmentShader: ibrFragmentShader(b),
      uniforms: {
        ...this.common,
        uImages: { value: images }, uFeatures: { value: features }, uDepth: { value: depth },
        uProj: { value: proj }, uCenter: { value: centers }, uOrigin: { value: new THREE.Vector3() },
        uImageSize: { value: new THREE.Vector2(W, H) }, uFeatSize: { value: new THREE.Vector2(f[3] - 2, f[2] - 2) },
        uVisibility: { value: this.visibility ? 1 : 0 }, uVisTol: { value: b.visibility.tol },
        uBlend: { value: this.blend === 'angle' ? 1 : 0 }, uAngleK: { value: b.blend ? b.blend.sources : 0 },
      },
    });
    if (b.fill) { // the far fill: a full-screen triangle drawn first, the mesh over it
      const box = b.fill.box || [[-1e30, -1e30, -1e30], [1e30, 1e30, 1e30]];
      const tri = new THREE.BufferGeometry();
      tri.setAttribute('position', new THREE.Float32BufferAttribute([-1, -1, 0, 3, -1, 0, -1, 3, 0], 3));
      const fillMaterial = new THREE.RawShaderMaterial({
        glslVersion: THREE.GLSL3, side: THREE.DoubleSide, depthTest: false, depthWrite: false,
        vertexShader: FILL_VERTEX_SHADER, fragmentShader: ibrFragmentShader(b, true),
        uniforms: {
          ...this.ibrMaterial.uniforms,
          uC2W: { value: new THREE.Matrix4() }, uIntr: { value: new THREE.Vector4() }, uHeight: { value: 1 },
          uBoxLo: { value: new THREE.Vector3(...box[0]) }, uBoxHi: { value: new THREE.Vector3(...box[1]) },
          uFar: { value: b.fill.far },
        },
      });
      this.fillMesh = new THREE.Mesh(tri, fillMaterial);
      this.fillMesh.frustumCulled = false;
      this.fillMesh.renderOrder = -1;
      this.fillMesh.visible = false;
      this.scene.add(this.fillMesh);
    }
    // compile now, so that a shader this GPU cannot take falls back to the baked colours
    this.mesh.material = this.ibrMaterial;
    if (this.fillMesh) this.fillMesh.visible = true;
    this.renderer.compile(this.scene, this.dummyCamera);
    this.renderer.render(this.scene, this.dummyCamera);
    this.mesh.material = this.bakedMaterial;
    if (this.fillMesh) this.fillMesh.visible = false;
    if (this.shaderErrors.length) throw new Error(`IBR shader: ${this.shaderErrors[0]}`);
  }

  note(text) { this.notes = (this.notes || []).concat([text]); }

  // ------------------------------------------------ cameras
  defaultCamera() {
    return { ...this.bundle.camera, frame: 'input' };
  }

  // an OpenCV camera in either frame -> model frame (as Cameras.transformed: scale removed from the rotation)
  toModelCamera(cam) {
    const c2w = mat.flat(cam.c2w);
    if ((cam.frame || 'input') === 'model') return { ...cam, c2w };
    const m = mat.mul(this.toModel, c2w);
    for (const i of [0, 1, 2]) for (const j of [0, 1, 2]) m[4 * i + j] /= this.modelScale;
    return { ...cam, c2w: m, frame: 'model' };
  }

  // tight near/far of the mesh box in the camera (MeshRasterizer.depth_range)
  depthRange(w2c) {
    const [lo, hi] = this.box;
    let zmin = Infinity, zmax = -Infinity;
    for (const x of [lo[0], hi[0]]) for (const y of [lo[1], hi[1]]) for (const z of [lo[2], hi[2]]) {
      const d = w2c[8] * x + w2c[9] * y + w2c[10] * z + w2c[11];
      zmin = Math.min(zmin, d);
      zmax = Math.max(zmax, d);
    }
    const far = Math.max(zmax, 1e-6) * 1.01 + 1e-6;
    const near = Math.max(zmin * 0.99, far * 1e-4);
    return [near, far];
  }

  orbitCameraCV() {
    // three.js camera (looks down -z, y up) -> OpenCV c2w in the input frame; intrinsics from its fov
    const W = this.canvas.width, H = this.canvas.height;
    this.orbit.updateMatrixWorld();
    const e = this.orbit.matrixWorld.elements; // column-major
    const c2w = [e[0], -e[4], -e[8], e[12], e[1], -e[5], -e[9], e[13], e[2], -e[6], -e[10], e[14], 0, 0, 0, 1];
    const fy = 0.5 * H / Math.tan(THREE.MathUtils.degToRad(this.orbit.fov) / 2);
    return { fx: fy, fy, cx: W / 2, cy: H / 2, width: W, height: H, c2w, frame: 'input' };
  }

  setupOrbit() {
    const cam = this.defaultCamera();
    const c2w = mat.flat(cam.c2w);
    const up = new THREE.Vector3(...this.bundle.up);
    this.orbit.fov = THREE.MathUtils.radToDeg(2 * Math.atan(0.5 * cam.height / cam.fy));
    this.orbit.position.set(c2w[3], c2w[7], c2w[11]);
    this.orbit.up.copy(up);
    const lo = this.bundle.mesh_box_input[0], hi = this.bundle.mesh_box_input[1];
    const target = new THREE.Vector3((lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, (lo[2] + hi[2]) / 2);
    const span = new THREE.Vector3(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]).length();
    this.orbit.near = span * 1e-3;
    this.orbit.far = span * 1e3;
    this.orbit.lookAt(target);
    this.controls = new OrbitControls(this.orbit, this.canvas);
    this.controls.target.copy(target);
    this.controls.update();
    this.controls.addEventListener('change', () => this.requestRender());
  }

  resize() {
    if (this.fixed) {  // exactly width x height pixels, whatever the screen's pixel ratio
      this.renderer.setPixelRatio(1);
      this.renderer.setSize(this.fixed.width, this.fixed.height, true);
    } else {
      this.renderer.setPixelRatio((window.devicePixelRatio || 1) * this.scale);
      this.renderer.setSize(window.innerWidth, window.innerHeight, true);
      this.orbit.aspect = window.innerWidth / window.innerHeight;
    }
    this.requestRender();
  }

  setCamera(cam) {
    if (cam == null) {
      this.fixed = null;
      if (this.controls) this.controls.enabled = true;
    } else {
      for (const k of ['fx', 'fy', 'cx', 'cy', 'width', 'height', 'c2w']) {
        if (cam[k] === undefined) throw new Error(`camera needs ${k}`);
      }
      this.fixed = { ...cam, width: Math.round(cam.width), height: Math.round(cam.height) };
      if (this.controls) this.controls.enabled = false;
    }
    this.resize();
    return this.render();
  }

  setMode(mode) {
    if (mode !== 'ibr' && mode !== 'baked') throw new Error(`mode must be ibr or baked, got ${mode}`);
    this.mode = mode;
    this.syncUI();
    return this.render();
  }

  setVisibility(on) {
    this.visibility = !!on;
    if (this.ibrMaterial) this.ibrMaterial.uniforms.uVisibility.value = on ? 1 : 0;
    this.syncUI();
    return this.render();
  }

  setBlend(blend) {
    if (blend !== 'network' && blend !== 'angle') throw new Error(`blend must be network or angle, got ${blend}`);
    this.blend = blend;
    for (const m of [this.ibrMaterial, this.fillMesh && this.fillMesh.material]) {
      if (m && m.uniforms.uBlend) m.uniforms.uBlend.value = blend === 'angle' ? 1 : 0;
    }
    return this.render();
  }

  setFill(on) {
    this.fill = !!on;
    this.syncUI();
    return this.render();
  }

  requestRender() {
    if (this.pending) return;
    this.pending = true;
    requestAnimationFrame(() => { this.pending = false; this.render(); });
  }

  // draw one frame; returns what was drawn
  render() {
    const cam = this.toModelCamera(this.fixed || this.orbitCameraCV());
    const w2c = mat.rigidInverse(cam.c2w);
    const [near, far] = this.depthRange(w2c);
    this.common.modelToClip.value.copy(mat.three(mat.mul(clipMatrix(cam, near, far), w2c)));
    const useIBR = this.mode === 'ibr' && this.ibrMaterial;
    if (useIBR) this.ibrMaterial.uniforms.uOrigin.value.set(cam.c2w[3], cam.c2w[7], cam.c2w[11]);
    this.mesh.material = useIBR ? this.ibrMaterial : this.bakedMaterial;
    if (this.fillMesh) {
      this.fillMesh.visible = !!(useIBR && this.fill);
      const u = this.fillMesh.material.uniforms;
      u.uC2W.value.copy(mat.three(cam.c2w));
      u.uIntr.value.set(cam.fx, cam.fy, cam.cx, cam.cy);
      u.uHeight.value = this.canvas.height;
    }
    this.renderer.render(this.scene, this.dummyCamera);
    this.frames = (this.frames || 0) + 1;
    return { mode: useIBR ? 'ibr' : 'baked', fill: !!(useIBR && this.fillMesh && this.fill), blend: this.blend, width: this.canvas.width,
      height: this.canvas.height };
  }

  // frames per second of the current mode at the current size, orbiting the camera a little each frame
  benchmark(frames = 60) {
    const gl = this.renderer.getContext();
    const px = new Uint8Array(4);
    const saved = this.fixed;
    const base = this.toModelCamera(saved || this.orbitCameraCV());
    const centre = [0, 1].map((i) => (this.box[0][i] + this.box[1][i]) / 2);
    this.render();
    gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px);
    const t0 = performance.now();
    for (let i = 0; i < frames; i++) {
      // rotate the model-frame camera about the box centre's z axis by a small angle per frame
      const a = 0.01 * (i + 1), c = Math.cos(a), s = Math.sin(a);
      const R = [c, -s, 0, centre[0] - c * centre[0] + s * centre[1], s, c, 0, centre[1] - s * centre[0] - c * centre[1],
        0, 0, 1, 0, 0, 0, 0, 1];
      this.fixed = { ...base, c2w: mat.mul(R, base.c2w), frame: 'model', width: this.canvas.width, height: this.canvas.height };
      this.render();
      gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px); // wait for the frame
    }
    const ms = (performance.now() - t0) / frames;
    this.fixed = saved;
    this.render();
    return { fps: 1000 / ms, ms_per_frame: ms, frames, width: this.canvas.width, height: this.canvas.height,
      mode: this.ibrMaterial && this.mode === 'ibr' ? 'ibr' : 'baked' };
  }

  // ------------------------------------------------ UI
  setupUI() {
    const panel = document.getElementById('panel');
    const show = params.has('ui') ? params.get('ui') !== '0' : !params.has('camera');
    panel.classList.toggle('hidden', !show);
    for (const r of document.querySelectorAll('input[name=mode]')) {
      r.addEventListener('change', () => this.setMode(r.value));
    }
    document.getElementById('vis').addEventListener('change', (e) => this.setVisibility(e.target.checked));
    document.getElementById('fill').addEventListener('change', (e) => this.setFill(e.target.checked));
    window.addEventListener('keydown', (e) => {
      if (e.key === 'b') this.setMode(this.mode === 'ibr' ? 'baked' : 'ibr');
      if (e.key === 'v') this.setVisibility(!this.visibility);
      if (e.key === 'f') this.setFill(!this.fill);
    });
    this.syncUI();
  }

  syncUI() {
    for (const r of document.querySelectorAll('input[name=mode]')) {
      r.checked = r.value === this.mode;
      if (r.value === 'ibr') r.disabled = !this.ibrMaterial;
    }
    const vis = document.getElementById('vis');
    vis.checked = this.visibility;
    vis.disabled = !this.ibrMaterial;
    const fill = document.getElementById('fill');
    fill.checked = this.fill && !!this.fillMesh;
    fill.disabled = !this.fillMesh;
    const b = this.bundle, st = document.getElementById('status');
    const parts = [`${b.faces.toLocaleString()} triangles, ${b.sources.count} source views`];
    if (this.fallbackReason) parts.push(`<span class="note">baked colours only: ${this.fallbackReason}</span>`);
    for (const n of this.notes || []) parts.push(`<span class="note">${n}</span>`);
    st.innerHTML = parts.join('<br>');
  }
}

function geometryHasColor(g) { return !!g.getAttribute('color'); }

async function loadGeometry(url) {
  const gltf = await new GLTFLoader().loadAsync(url);
  let found = null;
  gltf.scene.updateMatrixWorld(true);
  gltf.scene.traverse((o) => { if (!found && o.isMesh) found = o; });
  if (!found) throw new Error(`${url} holds no mesh`);
  const g = found.geometry.clone();
  if (!found.matrixWorld.equals(new THREE.Matrix4())) g.applyMatrix4(found.matrixWorld);
  return g;
}

async function main() {
  const bundle = await fetchChecked('bundle.json', 'json');
  const geometry = await loadGeometry(bundle.mesh);
  const viewer = new Viewer(bundle, geometry);
  const api = {
    ready, viewer,
    setCamera: (c) => viewer.setCamera(c),
    setMode: (m) => viewer.setMode(m),
    setVisibility: (v) => viewer.setVisibility(v),
    setFill: (f) => viewer.setFill(f),
    setBlend: (b) => viewer.setBlend(b),
    render: () => viewer.render(),
    benchmark: (n) => viewer.benchmark(n),
  };
  window.omnirecon = api;
  if (params.get('mode') === 'baked') viewer.mode = 'baked';
  if (params.has('vis')) viewer.visibility = params.get('vis') !== '0';
  if (params.has('fill')) viewer.fill = params.get('fill') !== '0';
  if (params.has('blend')) viewer.blend = params.get('blend') === 'angle' ? 'angle' : 'network';
  try {
    const t = bundle.textures;
    const [images, features, depth] = await Promise.all([t.images.file, t.features.file, t.depth.file]
      .map((f) => fetchChecked(f, 'bin')));
    await viewer.initIBR({ images, features, depth });
  } catch (e) {
    viewer.fallbackReason = String(e.message || e);
    viewer.ibrMaterial = null;
    console.warn(`omnirecon viewer: image-based shading unavailable, showing baked colours: ${viewer.fallbackReason}`);
  }
  viewer.setupOrbit();
  viewer.setupUI();
  window.addEventListener('resize', () => viewer.resize());
  if (params.has('camera')) viewer.setCamera(JSON.parse(params.get('camera')));
  else viewer.resize();
  viewer.render();
  const info = { mode: viewer.ibrMaterial && viewer.mode === 'ibr' ? 'ibr' : 'baked', fallback: viewer.fallbackReason,
    width: viewer.canvas.width, height: viewer.canvas.height, renderer: rendererName(viewer.renderer) };
  api.info = info;
  root.dataset.state = 'ready';
  readyResolve(info);
}

function rendererName(r) {
  const gl = r.getContext();
  const ext = gl.getExtension('WEBGL_debug_renderer_info');
  return ext ? gl.getParameter(ext.UNMASKED_RENDERER_WEBGL) : gl.getParameter(gl.RENDERER);
}

main().catch((e) => {
  console.error(e);
  root.dataset.state = 'error';
  root.dataset.error = String(e && e.message ? e.message : e);
  const st = document.getElementById('status');
  if (st) { st.textContent = `error: ${root.dataset.error}`; document.getElementById('panel').classList.remove('hidden'); }
  readyReject(e);
});
