// omnirecon mesh viewer: MeshRenderer's real-time frames (omnirecon.mesh.ibr) in WebGL2, from an `omnirecon export` bundle.
//
// A frame is drawn as MeshRenderer.frame draws it (the passes and the shading: shaders.js): the mesh's depth, the
// fills' geometry (cracks, nearest fill), then every pixel shaded by the image-based blend of the bundle's sources
// (every training view): the network blend over the frame's `frame_sources` nearest sources (picked here per frame,
// as omnirecon.engine.views.select_sources), or the angle blend of each point's nearest sources by viewing angle,
// weighted by the sources' object masks. The bundle's `setting` is what the viewer starts with (finetune's
// real-time setting); the panel and the API switch each part. Baked mode draws the exported per-vertex colours
// instead (also the automatic fallback when float textures or the shaders do not work here).
//
// Cameras are OpenCV pinhole cameras (x right, y down, z forward, camera-to-world, pixel centres at
// +0.5). A fixed camera comes from the URL (?camera=<JSON>) or window.omnirecon.setCamera(...):
//   {"fx", "fy", "cx", "cy", "width", "height", "c2w": 4x4 rows, "frame": "input" (default) | "model"}
// "input" is the frame of mesh.glb (the user's scene); "model" the normalised frame the model works in.
// Other URL parameters: mode=ibr|baked, vis=0|1, fill=nearest|far|background (1: far, 0: background), cracks=0|1,
// masks=0|1, blend=network|angle, ui=0|1, scale=<render resolution factor of the interactive view>.

import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import {
  BAKED_FRAGMENT_SHADER, DEPTH_FRAGMENT_SHADER, JFA_SHADER, SCREEN_VERTEX_SHADER, SEED_INIT_SHADER, VERTEX_SHADER,
  closingShaders, shadeShader,
} from './shaders.js';

const FORMAT = 'omnirecon-viewer';
const VERSION = 2; // omnirecon.viewer.format.VERSION: the bundle layout this viewer reads
const FILLS = ['background', 'far', 'nearest'];

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

function target(width, height, format, type, depthBuffer = false) {
  return new THREE.WebGLRenderTarget(width, height, { format, type, depthBuffer, stencilBuffer: false,
    minFilter: THREE.NearestFilter, magFilter: THREE.NearestFilter, generateMipmaps: false });
}

function screenMaterial(fragmentShader, uniforms) {
  return new THREE.RawShaderMaterial({ glslVersion: THREE.GLSL3, side: THREE.DoubleSide, depthTest: false,
    depthWrite: false, vertexShader: SCREEN_VERTEX_SHADER, fragmentShader, uniforms });
}

const unit = (v) => { const n = Math.hypot(...v) || 1e-12; return v.map((x) => x / n); };

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
    const s = bundle.setting;
    this.visibility = !!bundle.visibility.default;
    this.fill = FILLS.includes(s.fill) ? s.fill : 'far';
    this.cracks = (bundle.cracks | 0) > 0;
    this.masks = !!(bundle.source_masks && bundle.source_masks.default);
    this.blend = s.blend === 'angle' ? 'angle' : 'network';
    this.crackRadius = Math.max(0, bundle.cracks | 0);
    this.fallbackReason = null;
    this.ibr = null;
    toModelFrame(geometry, this.toModel);

    const fixed = params.has('camera');
    this.canvas = document.createElement('canvas');
    document.body.appendChild(this.canvas);
    this.renderer = new THREE.WebGLRenderer({ canvas: this.canvas, antialias: false, alpha: false,
      preserveDrawingBuffer: fixed || params.get('preserve') === '1', powerPreference: 'high-performance' });
    this.renderer.outputColorSpace = THREE.LinearSRGBColorSpace;
    this.renderer.toneMapping = THREE.NoToneMapping;
    this.clearColor = new THREE.Color(...this.background);
    this.renderer.setClearColor(this.clearColor, 1);
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
    this.side = this.mirror ? THREE.BackSide : THREE.FrontSide;
    this.common = { modelToClip: { value: new THREE.Matrix4() } };
    this.bakedMaterial = new THREE.RawShaderMaterial({ glslVersion: THREE.GLSL3, side: this.side,
      uniforms: this.common, vertexShader: VERTEX_SHADER, fragmentShader: BAKED_FRAGMENT_SHADER });
    this.mesh = new THREE.Mesh(geometry, this.bakedMaterial);
    this.mesh.frustumCulled = false;
    this.mesh.matrixAutoUpdate = false;
    this.scene.add(this.mesh);
    // the screen-space passes draw one full-screen triangle
    this.screen = new THREE.Scene();
    const tri = new THREE.BufferGeometry();
    tri.setAttribute('position', new THREE.Float32BufferAttribute([-1, -1, 0, 3, -1, 0, -1, 3, 0], 3));
    this.quad = new THREE.Mesh(tri, this.bakedMaterial);
    this.quad.frustumCulled = false;
    this.screen.add(this.quad);

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
    if (!gl.getExtension('EXT_color_buffer_float')) throw new Error('float render targets (EXT_color_buffer_float) are not supported');
    const layers = src.count * Math.ceil(b.mlp.feature_dim / 4);
    const maxLayers = gl.getParameter(gl.MAX_ARRAY_TEXTURE_LAYERS), maxSize = gl.getParameter(gl.MAX_TEXTURE_SIZE);
    if (layers > maxLayers) throw new Error(`${layers} feature layers > MAX_ARRAY_TEXTURE_LAYERS ${maxLayers}`);
    if (Math.max(src.width + 1, src.height + 1, src.count) > maxSize) throw new Error(`source images exceed MAX_TEXTURE_SIZE ${maxSize}`);
    const f = b.textures.features.shape; // [K, C4, h + 2, w + 2, 4]
    const W = src.width, H = src.height;
    const cams = new THREE.DataTexture(new Float32Array(buffers.cameras), 4, src.count, THREE.RGBAFormat, THREE.FloatType);
    cams.minFilter = cams.magFilter = THREE.NearestFilter;
    cams.generateMipmaps = false;
    cams.needsUpdate = true;
    const masks = b.source_masks || { reach: 1, floor: 1 };
    this.depthMaterial = new THREE.RawShaderMaterial({ glslVersion: THREE.GLSL3, side: this.side, uniforms: this.common,
      vertexShader: VERTEX_SHADER, fragmentShader: DEPTH_FRAGMENT_SHADER });
    this.zTarget = null;
    this.uniforms = {
      uImages: { value: arrayTexture(new Uint8Array(buffers.images), W, H, src.count, THREE.RGBAFormat, THREE.UnsignedByteType) },
      uFeatures: { value: arrayTexture(new Float32Array(buffers.features), f[3], f[2], f[0] * f[1], THREE.RGBAFormat, THREE.FloatType) },
      uDepth: { value: arrayTexture(new Float32Array(buffers.depth), W + 1, H + 1, src.count, THREE.RedFormat, THREE.FloatType) },
      uCams: { value: cams }, uZ: { value: null }, uSeed: { value: null }, uCrack: { value: null },
      uSel: { value: [] }, uOrder: { value: [] },
      uC2W: { value: new THREE.Matrix4() }, uIntr: { value: new THREE.Vector4() }, uHeight: { value: 1 },
      uBoxLo: { value: new THREE.Vector3(...(b.fill.box ? b.fill.box[0] : [-1e30, -1e30, -1e30])) },
      uBoxHi: { value: new THREE.Vector3(...(b.fill.box ? b.fill.box[1] : [1e30, 1e30, 1e30])) },
      uFar: { value: b.fill.far }, uBackground: { value: new THREE.Vector3(...this.background) },
      uFill: { value: 1 }, uReach: { value: 0 }, uCracks: { value: 0 },
      uImageSize: { value: new THREE.Vector2(W, H) }, uFeatSize: { value: new THREE.Vector2(f[3] - 2, f[2] - 2) },
      uVisibility: { value: 1 }, uVisTol: { value: b.visibility.tol },
      uMasks: { value: 0 }, uMaskReach: { value: masks.reach }, uMaskFloor: { value: masks.floor },
    };
    this.seedInit = screenMaterial(SEED_INIT_SHADER, { uZ: this.uniforms.uZ });
    this.jfa = screenMaterial(JFA_SHADER, { uSeed: { value: null }, uStep: { value: 1 } });
    this.closing = [];  // [material, target name] of the crack mask's passes, in order
    if (this.crackRadius > 0) {
      const c = closingShaders(this.crackRadius);
      const input = (name) => ({ value: null, name });
      for (const [key, from, to] of [['dilateRows', null, 'dilRows'], ['dilateColumns', 'dilRows', 'dil'],
        ['erodeRows', 'dil', 'eroRows'], ['erodeColumns', 'eroRows', 'crack']]) {
        this.closing.push([screenMaterial(c[key], { uZ: this.uniforms.uZ, uIn: input(from) }), to]);
      }
    }
    this.shadeMaterials = {};
    this.ibr = true;
    // draw every pass of the starting blend once now (a tiny frame), so that a shader this GPU cannot take falls back
    // to the baked colours
    const saved = { fixed: this.fixed, mode: this.mode, fill: this.fill, cracks: this.cracks };
    Object.assign(this, { fixed: { ...this.defaultCamera(), width: 4, height: 4, fx: 2, fy: 2, cx: 2, cy: 2 },
      mode: 'ibr', cracks: true });
    this.resize(false);
    for (const fill of ['nearest', 'far']) { this.fill = fill; this.render(); }  // the jump flooding, the closing
    Object.assign(this, saved);
    if (this.shaderErrors.length) throw new Error(`IBR shader: ${this.shaderErrors[0]}`);
  }

  // the shading pass of a blend (compiled on first use; NSEL, KA and CR are compile-time constants)
  shadeMaterial(blend) {
    if (!this.shadeMaterials[blend]) {
      const b = this.bundle;
      const fragmentShader = shadeShader(b, { blend, frameSources: b.blend.frame_sources | 0,
        angleSources: b.blend.sources | 0, cracks: this.crackRadius });
      this.shadeMaterials[blend] = screenMaterial(fragmentShader, this.uniforms);
    }
    return this.shadeMaterials[blend];
  }

  note(text) { this.notes = (this.notes || []).concat([text]); }

  // ------------------------------------------------ the frame's sources
  // every source, nearest to a frame's camera (model frame) first: by the angle around the bundle's centre on object
  // rigs, by the distance between camera centres otherwise (select_sources)
  sourceOrder(cam) {
    const b = this.bundle.blend, centers = this.bundle.sources.centers;
    const c = [cam.c2w[3], cam.c2w[7], cam.c2w[11]];
    let dist;
    if (b.metric === 'angle') {
      const o = b.center, a = unit(c.map((x, i) => x - o[i]));
      dist = centers.map((ck) => {
        const u = unit(ck.map((x, i) => x - o[i]));
        return Math.acos(Math.min(1, Math.max(-1, a[0] * u[0] + a[1] * u[1] + a[2] * u[2])));
      });
    } else {
      dist = centers.map((ck) => Math.hypot(c[0] - ck[0], c[1] - ck[1], c[2] - ck[2]));
    }
    return dist.map((_, i) => i).sort((i, j) => dist[i] - dist[j] || i - j);
  }

  // the frame's sources when it blends the `frame_sources` nearest, ascending; [] when it blends every source
  frameSources(cam) {
    const n = this.bundle.blend.frame_sources | 0;
    if (!(n > 0 && n < this.bundle.sources.count)) return [];
    return this.sourceOrder(cam).slice(0, n).sort((i, j) => i - j);
  }

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

  resize(redraw = true) {
    if (this.fixed) {  // exactly width x height pixels, whatever the screen's pixel ratio
      this.renderer.setPixelRatio(1);
      this.renderer.setSize(this.fixed.width, this.fixed.height, true);
    } else {
      this.renderer.setPixelRatio((window.devicePixelRatio || 1) * this.scale);
      this.renderer.setSize(window.innerWidth, window.innerHeight, true);
      this.orbit.aspect = window.innerWidth / window.innerHeight;
    }
    if (redraw) this.requestRender();
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
    this.syncUI();
    return this.render();
  }

  setBlend(blend) {
    if (blend !== 'network' && blend !== 'angle') throw new Error(`blend must be network or angle, got ${blend}`);
    this.blend = blend;
    this.syncUI();
    return this.render();
  }

  // 'nearest', 'far' or 'background' (true: far, false: background)
  setFill(fill) {
    const f = fill === true ? 'far' : fill === false ? 'background' : fill;
    if (!FILLS.includes(f)) throw new Error(`fill must be one of ${FILLS.join(', ')}, got ${fill}`);
    this.fill = f;
    this.syncUI();
    return this.render();
  }

  setCracks(on) {
    this.cracks = !!on;
    this.syncUI();
    return this.render();
  }

  setMasks(on) {
    this.masks = !!on;
    this.syncUI();
    return this.render();
  }

  requestRender() {
    if (this.pending) return;
    this.pending = true;
    requestAnimationFrame(() => { this.pending = false; this.render(); });
  }

  // render targets of the passes at the canvas size: depth (with a depth buffer), the nearest seeds, the closing's
  targets(W, H) {
    if (this.zTarget && this.zTarget.width === W && this.zTarget.height === H) return;
    for (const t of [this.zTarget, ...(this.seedTargets || []), ...Object.values(this.closeTargets || {})]) if (t) t.dispose();
    this.zTarget = target(W, H, THREE.RedFormat, THREE.FloatType, true);
    this.seedTargets = [target(W, H, THREE.RGFormat, THREE.FloatType), target(W, H, THREE.RGFormat, THREE.FloatType)];
    const r = this.crackRadius, R8 = (w, h) => target(w, h, THREE.RedFormat, THREE.UnsignedByteType);
    this.closeTargets = r > 0 ? { dilRows: R8(W + 2 * r, H), dil: R8(W + 2 * r, H + 2 * r), eroRows: R8(W, H + 2 * r),
      crack: R8(W, H) } : {};
    this.uniforms.uZ.value = this.zTarget.texture;
    this.uniforms.uSeed.value = this.seedTargets[0].texture;
    this.uniforms.uCrack.value = r > 0 ? this.closeTargets.crack.texture : this.zTarget.texture;
  }

  // the crack mask (closingShaders)
  cracksPass() {
    for (const [material, to] of this.closing) {
      const from = material.uniforms.uIn.name;
      material.uniforms.uIn.value = from ? this.closeTargets[from].texture : this.zTarget.texture;
      this.pass(material, this.closeTargets[to]);
    }
  }

  pass(material, renderTarget) {
    this.quad.material = material;
    this.renderer.setRenderTarget(renderTarget);
    this.renderer.render(this.screen, this.dummyCamera);
  }

  // each pixel's nearest covered pixel by jump flooding, as far as the nearest fill reaches
  jumpFlood(W, H) {
    const reach = this.bundle.fill.reach * Math.max(W, H);
    const m = Math.max(1, Math.ceil(Math.log2(reach + 1)));
    this.pass(this.seedInit, this.seedTargets[0]);
    let src = 0;
    const steps = [];
    for (let s = 1 << (m - 1); s >= 1; s >>= 1) steps.push(s);
    for (const s of [...steps, 1]) {
      this.jfa.uniforms.uSeed.value = this.seedTargets[src].texture;
      this.jfa.uniforms.uStep.value = s;
      this.pass(this.jfa, this.seedTargets[1 - src]);
      src = 1 - src;
    }
    this.uniforms.uSeed.value = this.seedTargets[src].texture;
  }

  // draw one frame; returns what was drawn
  render() {
    const cam = this.toModelCamera(this.fixed || this.orbitCameraCV());
    const w2c = mat.rigidInverse(cam.c2w);
    const [near, far] = this.depthRange(w2c);
    this.common.modelToClip.value.copy(mat.three(mat.mul(clipMatrix(cam, near, far), w2c)));
    const useIBR = this.mode === 'ibr' && !!this.ibr;
    const r = this.renderer, W = this.canvas.width, H = this.canvas.height;
    const cracks = useIBR && this.cracks && this.crackRadius > 0;
    const crackPasses = cracks && this.fill !== 'nearest';  // the nearest fill reaches every crack (shaders.js)
    const masks = useIBR && this.masks && !!this.bundle.source_masks;
    let sources = null;
    if (!useIBR) {
      this.mesh.material = this.bakedMaterial;
      r.setRenderTarget(null);
      r.render(this.scene, this.dummyCamera);
    } else {
      this.targets(W, H);
      this.mesh.material = this.depthMaterial;
      r.setRenderTarget(this.zTarget);
      r.setClearColor(0x000000, 0);
      r.render(this.scene, this.dummyCamera);
      r.setClearColor(this.clearColor, 1);
      if (this.fill === 'nearest') this.jumpFlood(W, H);
      if (crackPasses) this.cracksPass();
      const u = this.uniforms;
      sources = this.frameSources(cam);
      u.uC2W.value.copy(mat.three(cam.c2w));
      u.uIntr.value.set(cam.fx, cam.fy, cam.cx, cam.cy);
      u.uHeight.value = H;
      u.uFill.value = FILLS.indexOf(this.fill);
      u.uReach.value = this.bundle.fill.reach * Math.max(W, H);
      u.uCracks.value = crackPasses ? 1 : 0;
      u.uVisibility.value = this.visibility ? 1 : 0;
      u.uMasks.value = masks ? 1 : 0;
      u.uSel.value = sources;
      if (!sources.length) {  // every source, nearest first, four to an ivec4
        const order = this.sourceOrder(cam);
        while (order.length % 4) order.push(order[order.length - 1]);
        u.uOrder.value = Int32Array.from(order);
      }
      this.pass(this.shadeMaterial(this.blend), null);
    }
    this.frames = (this.frames || 0) + 1;
    return { mode: useIBR ? 'ibr' : 'baked', blend: this.blend, fill: useIBR ? this.fill : 'background', cracks, masks,
      sources: sources && (sources.length ? sources : 'all'), width: W, height: H };
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
      mode: this.ibr && this.mode === 'ibr' ? 'ibr' : 'baked' };
  }

  // ------------------------------------------------ UI
  setupUI() {
    const panel = document.getElementById('panel');
    const show = params.has('ui') ? params.get('ui') !== '0' : !params.has('camera');
    panel.classList.toggle('hidden', !show);
    for (const r of document.querySelectorAll('input[name=mode]')) r.addEventListener('change', () => this.setMode(r.value));
    document.getElementById('blend').addEventListener('change', (e) => this.setBlend(e.target.value));
    document.getElementById('fill').addEventListener('change', (e) => this.setFill(e.target.value));
    document.getElementById('vis').addEventListener('change', (e) => this.setVisibility(e.target.checked));
    document.getElementById('cracks').addEventListener('change', (e) => this.setCracks(e.target.checked));
    document.getElementById('masks').addEventListener('change', (e) => this.setMasks(e.target.checked));
    window.addEventListener('keydown', (e) => {
      if (e.target && e.target.tagName === 'SELECT') return;
      if (e.key === 'b') this.setMode(this.mode === 'ibr' ? 'baked' : 'ibr');
      if (e.key === 'a') this.setBlend(this.blend === 'angle' ? 'network' : 'angle');
      if (e.key === 'v') this.setVisibility(!this.visibility);
      if (e.key === 'f') this.setFill(FILLS[(FILLS.indexOf(this.fill) + 1) % FILLS.length]);
      if (e.key === 'c') this.setCracks(!this.cracks);
      if (e.key === 'm') this.setMasks(!this.masks);
    });
    this.syncUI();
  }

  syncUI() {
    const ibr = !!this.ibr;
    for (const r of document.querySelectorAll('input[name=mode]')) {
      r.checked = r.value === this.mode;
      if (r.value === 'ibr') r.disabled = !ibr;
    }
    const set = (id, key, value, disabled) => { const e = document.getElementById(id); e[key] = value; e.disabled = disabled; };
    set('blend', 'value', this.blend, !ibr);
    set('fill', 'value', this.fill, !ibr);
    set('vis', 'checked', this.visibility, !ibr);
    set('cracks', 'checked', this.cracks && this.crackRadius > 0, !ibr || !(this.crackRadius > 0));
    set('masks', 'checked', this.masks && !!this.bundle.source_masks, !ibr || !this.bundle.source_masks);
    const b = this.bundle, st = document.getElementById('status');
    const parts = [`${b.faces.toLocaleString()} triangles, ${b.sources.count} source views`];
    if (this.fallbackReason) parts.push(`<span class="note">baked colours only: ${this.fallbackReason}</span>`);
    for (const n of this.notes || []) parts.push(`<span class="note">${n}</span>`);
    st.innerHTML = parts.join('<br>');
  }
}

// the mesh's positions from the input frame (mesh.glb) to the model frame, once, in float64
function toModelFrame(geometry, T) {
  const pos = geometry.getAttribute('position');
  const out = new Float32Array(pos.count * 3);
  for (let i = 0; i < pos.count; i++) {
    const p = mat.apply(T, [pos.getX(i), pos.getY(i), pos.getZ(i)]);
    out[3 * i] = p[0];
    out[3 * i + 1] = p[1];
    out[3 * i + 2] = p[2];
  }
  geometry.setAttribute('position', new THREE.BufferAttribute(out, 3));
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
  if (bundle.format !== FORMAT || bundle.version !== VERSION) {
    throw new Error(`bundle.json is ${bundle.format} version ${bundle.version}; this viewer reads ${FORMAT} version ` +
      `${VERSION} (re-export it with omnirecon export)`);
  }
  const geometry = await loadGeometry(bundle.mesh);
  const viewer = new Viewer(bundle, geometry);
  const api = {
    ready, viewer,
    setCamera: (c) => viewer.setCamera(c),
    setMode: (m) => viewer.setMode(m),
    setVisibility: (v) => viewer.setVisibility(v),
    setFill: (f) => viewer.setFill(f),
    setCracks: (c) => viewer.setCracks(c),
    setMasks: (m) => viewer.setMasks(m),
    setBlend: (b) => viewer.setBlend(b),
    render: () => viewer.render(),
    benchmark: (n) => viewer.benchmark(n),
  };
  window.omnirecon = api;
  try {
    const t = bundle.textures;
    const [images, features, depth, cameras] = await Promise.all(
      [t.images.file, t.features.file, t.depth.file, t.cameras.file].map((f) => fetchChecked(f, 'bin')));
    await viewer.initIBR({ images, features, depth, cameras });
  } catch (e) {
    viewer.fallbackReason = String(e.message || e);
    viewer.ibr = null;
    console.warn(`omnirecon viewer: image-based shading unavailable, showing baked colours: ${viewer.fallbackReason}`);
  }
  if (params.get('mode') === 'baked') viewer.mode = 'baked';
  if (params.has('vis')) viewer.visibility = params.get('vis') !== '0';
  if (params.has('fill')) {
    const f = params.get('fill');
    viewer.fill = f === '1' ? 'far' : f === '0' ? 'background' : FILLS.includes(f) ? f : viewer.fill;
  }
  if (params.has('cracks')) viewer.cracks = params.get('cracks') !== '0';
  if (params.has('masks')) viewer.masks = params.get('masks') !== '0';
  if (params.has('blend')) viewer.blend = params.get('blend') === 'angle' ? 'angle' : 'network';
  viewer.setupOrbit();
  viewer.setupUI();
  window.addEventListener('resize', () => viewer.resize());
  if (params.has('camera')) viewer.setCamera(JSON.parse(params.get('camera')));
  else viewer.resize();
  const drawn = viewer.render();
  const info = { mode: drawn.mode, fallback: viewer.fallbackReason, blend: drawn.blend, fill: drawn.fill,
    cracks: drawn.cracks, masks: drawn.masks, width: viewer.canvas.width, height: viewer.canvas.height,
    renderer: rendererName(viewer.renderer) };
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
