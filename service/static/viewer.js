// probegrid viewer: the baked scene, the probe grid and a moving object lit by the service.
//
// Plain ES module (three.js through the page's import map; no build step). Conventions are the
// service's (see GET /v1/grids/{grid}): glTF world frame (+Y up), real SH bands 0-2 without
// Condon-Shortley phase, index l(l+1)+m, stored coefficients are radiance L_lm; irradiance
// E(n) = sum A_l L_lm Y_lm(n) with A0 = pi, A1 = 2pi/3, A2 = pi/4; a Lambertian surface of albedo
// a shows a E(n) / pi. Cube faces +X,-X,+Y,-Y,+Z,-Z in the OpenGL layout, so a GLSL
// texture(samplerCube, worldDir) returns what the service stored for worldDir.
//
// What is drawn:
// * the scene (GET /v1/grids/{grid}/scene) with its glTF materials, its diffuse light replaced by
//   the grid's: a trilinear blend of the valid probes' SH at every fragment (the service's blend
//   without a normal), plus the materials' emission; the glTF punctual lights are not added
//   (the probes already hold their light);
// * every probe (GET /v1/grids/{grid}/probes) as an instanced sphere shaded E(n)/pi by its own SH;
// * a sphere you can drag: each move queries /sh and /maps/specular at its centre with the normal
//   toward the camera, at most one query in flight, the latest position winning; it is shaded
//   with the split sum, out = albedo (1 - s) E(n)/pi + s Prefiltered(R), s = F0 A + B. The
//   specular map is asked with method=trace (a probe traced at the object's centre: a mirror
//   shows each light once, where it is) unless the "reflections" choice says blend (the
//   surrounding probes' maps blended: a light seen from up to 8 places);
// * side by side (the "three.js LightProbeGridWebGL" toggle): right of the object's centre the
//   view shows the same sphere drawn by three.js itself, a MeshLambertMaterial (albedo 0.8) lit
//   by the vendored LightProbeGridWebGL whose texture is the service's three.js export of the
//   grid (GET /v1/grids/{grid}/export/threejs.json and .bin: the SH atlas as half floats). Three
//   samples the grid at the fragment moved half a cell along its normal and blends probes
//   trilinearly without validity (invalid probes were filled by the export), so the two halves
//   differ where the service's blend does (leaks, near invalid probes).
//
// window.probegrid exposes the state and hooks the browser tests use.

import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';

const $ = (id) => document.getElementById(id);
const api = {
  grids: () => '/v1/grids',
  grid: (g) => `/v1/grids/${encodeURIComponent(g)}`,
};

const PG = {
  ready: false,
  tti: null,            // ms from navigation start to interactive
  grid: null,           // GridDetail of the shown grid
  probeCount: 0,
  lastQuery: null,      // {position, normal, sh: SHOut, level, method: the map's X-Probegrid-Method}
  mapMethod: 'trace',   // method= of the specular map query: 'trace' or 'blend'
  stats: { sh: 0, maps: 0, coalesced: 0 },
  errors: [],
  timings: {},          // ms from navigation start at each loading stage
};
const mark = (name) => { PG.timings[name] = Math.round(performance.now()); };
mark('module');
window.probegrid = PG;

// ---------------------------------------------------------------------------- helpers
async function fetchOk(url) {
  const r = await fetch(url);
  if (!r.ok) {
    let msg = `${r.status}`;
    try { msg = (await r.json()).message || msg; } catch (e) { /* not JSON */ }
    throw new Error(`${url}: ${msg}`);
  }
  return r;
}
const getJSON = async (url) => (await fetchOk(url)).json();

function base64Array(text, Type) {
  const bin = atob(text);
  const bytes = new Uint8Array(bin.length);
  for (let i = 0; i < bin.length; i++) bytes[i] = bin.charCodeAt(i);
  return new Type(bytes.buffer);
}

// A float32 little-endian C-ordered .npy (format 1 or 2): {shape, data: Float32Array}.
function parseNpy(buffer) {
  const u8 = new Uint8Array(buffer);
  const major = u8[6];
  const dv = new DataView(buffer);
  const hlen = major === 1 ? dv.getUint16(8, true) : dv.getUint32(8, true);
  const start = major === 1 ? 10 : 12;
  const header = new TextDecoder().decode(u8.subarray(start, start + hlen));
  if (!/'descr':\s*'<f4'/.test(header) || /'fortran_order':\s*True/.test(header)) {
    throw new Error(`unexpected npy header ${header}`);
  }
  const shape = header.match(/'shape':\s*\(([^)]*)\)/)[1].split(',')
    .map((s) => s.trim()).filter(Boolean).map(Number);
  const offset = start + hlen;
  const data = new Float32Array(buffer.slice(offset));
  return { shape, data };
}

function setStatus(text, error = false) {
  $('status').textContent = text;
  $('status').classList.toggle('error', error);
}

// ---------------------------------------------------------------------------- GLSL
const SH_GLSL = /* glsl */`
// E(n) = sum_l A_l sum_m L_lm Y_lm(n), real SH without Condon-Shortley phase (probegrid.sh)
vec3 pgIrradiance(vec3 L[9], vec3 n) {
  const float K0 = 0.28209479177387814, K1 = 0.4886025119029199, K2 = 1.0925484305920792;
  const float K3 = 0.31539156525252005, K4 = 0.5462742152960396;
  const float A0 = 3.141592653589793, A1 = 2.0943951023931953, A2 = 0.7853981633974483;
  float x = n.x, y = n.y, z = n.z;
  return A0 * K0 * L[0]
       + A1 * K1 * (y * L[1] + z * L[2] + x * L[3])
       + A2 * (K2 * (x * y * L[4] + y * z * L[5] + x * z * L[7])
               + K3 * (3.0 * z * z - 1.0) * L[6] + K4 * (x * x - y * y) * L[8]);
}`;

// The grid's SH in a 3D texture (nx, ny, 7 nz), linearly filtered: the 28 numbers
// (v L_0 .. v L_8 as RGB, then v) of probe (i, j, k), v its validity (0 or 1), fill the RGBA
// texels (i, j, t nz + k), t = 0..6. Hardware trilinear filtering inside each block of nz slices
// gives sum_i w_i v_i L_i and sum_i w_i v_i, whose ratio is the trilinear blend of the valid
// probes (the service's blend without a normal), in 7 fetches.
const GRID_GLSL = /* glsl */`
uniform highp sampler3D pgGridSH;
uniform vec3 pgGridMin;
uniform vec3 pgGridSpacing;
uniform vec3 pgGridCounts;
${SH_GLSL}
vec3 pgGridIrradiance(vec3 p, vec3 n) {
  vec3 g = clamp((p - pgGridMin) / max(pgGridSpacing, vec3(1e-12)), vec3(0.0), pgGridCounts - 1.0);
  vec3 uvw = (g + 0.5) / vec3(pgGridCounts.xy, 7.0 * pgGridCounts.z);
  float dz = 1.0 / 7.0;
  vec4 t0 = texture(pgGridSH, uvw);
  vec4 t1 = texture(pgGridSH, uvw + vec3(0.0, 0.0, dz));
  vec4 t2 = texture(pgGridSH, uvw + vec3(0.0, 0.0, 2.0 * dz));
  vec4 t3 = texture(pgGridSH, uvw + vec3(0.0, 0.0, 3.0 * dz));
  vec4 t4 = texture(pgGridSH, uvw + vec3(0.0, 0.0, 4.0 * dz));
  vec4 t5 = texture(pgGridSH, uvw + vec3(0.0, 0.0, 5.0 * dz));
  vec4 t6 = texture(pgGridSH, uvw + vec3(0.0, 0.0, 6.0 * dz));
  if (t6.w <= 1e-6) return vec3(0.0);
  vec3 L[9];
  L[0] = t0.xyz; L[1] = vec3(t0.w, t1.xy); L[2] = vec3(t1.zw, t2.x); L[3] = t2.yzw;
  L[4] = t3.xyz; L[5] = vec3(t3.w, t4.xy); L[6] = vec3(t4.zw, t5.x); L[7] = t5.yzw;
  L[8] = t6.xyz;
  for (int c = 0; c < 9; c++) L[c] /= t6.w;
  return pgIrradiance(L, normalize(n));
}`;

// the grid list and the first grid's data were asked for by the page (index.html) already
const prefetch = window.probegridPrefetch || {};
const gridsLoading = (prefetch.grids || Promise.reject(new Error('no prefetch')))
  .catch(() => getJSON(api.grids()));

// ---------------------------------------------------------------------------- renderer, scene
const canvas = $('canvas');
// no MSAA: it doubles the cost of a frame on software WebGL (SwiftShader) for little gain
const renderer = new THREE.WebGLRenderer({ canvas, antialias: false, preserveDrawingBuffer: true });
renderer.setPixelRatio(Math.min(window.devicePixelRatio, 2));
renderer.outputColorSpace = THREE.SRGBColorSpace;
const TONEMAPS = {
  aces: THREE.ACESFilmicToneMapping, agx: THREE.AgXToneMapping,
  neutral: THREE.NeutralToneMapping, none: THREE.NoToneMapping,
};
renderer.toneMapping = THREE.ACESFilmicToneMapping;

const world = new THREE.Scene();
world.background = new THREE.Color(0x101216);
const camera = new THREE.PerspectiveCamera(50, 1, 0.01, 1000);
const controls = new OrbitControls(camera, canvas);
controls.enableDamping = false;

const sceneRoot = new THREE.Group();
const probeRoot = new THREE.Group();
world.add(sceneRoot, probeRoot);

// shared grid uniforms (the scene's materials read them)
const gridUniforms = {
  pgGridSH: { value: null },
  pgGridMin: { value: new THREE.Vector3() },
  pgGridSpacing: { value: new THREE.Vector3(1, 1, 1) },
  pgGridCounts: { value: new THREE.Vector3(1, 1, 1) },  // as floats
};

let renderQueued = false;
function requestRender() {
  if (renderQueued) return;
  renderQueued = true;
  requestAnimationFrame(() => { renderQueued = false; draw(); });
}

// ---------------------------------------------------------------------------- three.js' own grid
// A second scene: three's LightProbeGridWebGL (fed by the export) and a Lambertian sphere at the
// object's place; drawn over the right part of the view (from the object's centre) when on.
const threeWorld = new THREE.Scene();
const threeObject = new THREE.Mesh(undefined, new THREE.MeshLambertMaterial({ color: new THREE.Color(0.8, 0.8, 0.8) }));
threeObject.name = 'three-object';
threeWorld.add(threeObject);
const compare = { on: false, grid: null, light: null, header: null, loading: null, cache: new Map() };

async function threeExport(name) {
  // the export of a grid (header and atlas) is asked for once per page
  if (!compare.cache.has(name)) {
    const base = `${api.grid(name)}/export/threejs`;
    compare.cache.set(name, Promise.all([
      getJSON(`${base}.json`),
      fetchOk(`${base}.bin?dtype=float16`).then((r) => r.arrayBuffer()),
      import('three/addons/lighting/LightProbeGridWebGL.js'),
    ]).catch((e) => { compare.cache.delete(name); throw e; }));
  }
  return compare.cache.get(name);
}

async function loadThreeGrid(name) {
  const [header, buffer, { LightProbeGridWebGL }] = await threeExport(name);
  const [nx, ny, nz] = header.resolution;
  const [w, h, d] = header.atlas_size;
  const tex = new THREE.Data3DTexture(new Uint16Array(buffer), w, h, d);
  tex.format = THREE.RGBAFormat;
  tex.type = THREE.HalfFloatType;  // filterable in every WebGL2
  tex.minFilter = tex.magFilter = THREE.LinearFilter;
  tex.wrapS = tex.wrapT = tex.wrapR = THREE.ClampToEdgeWrapping;
  tex.generateMipmaps = false;
  tex.unpackAlignment = 1;
  tex.needsUpdate = true;
  const [sx, sy, sz] = header.size;
  const light = new LightProbeGridWebGL(sx, sy, sz, nx, ny, nz);
  light.position.fromArray(header.position);
  light.updateBoundingBox();
  light.texture = tex;  // what bake() would have rendered: the atlas of seven SH sub-volumes
  if (compare.light) {
    threeWorld.remove(compare.light);
    compare.light.texture.dispose();
  }
  threeWorld.add(light);
  compare.light = light;
  compare.header = header;
  compare.grid = name;
}

async function setCompare(on) {
  compare.on = on;
  $('compare').checked = on;
  if (!PG.grid) return;  // showGrid loads the export once the grid is there
  if (on && compare.grid !== PG.grid.name) {
    const name = PG.grid.name;
    compare.loading = loadThreeGrid(name);
    try { await compare.loading; } finally { compare.loading = null; }
    if (PG.grid.name !== name) return setCompare(compare.on);  // the grid changed meanwhile
    syncThreeObject();
    renderer.compile(threeWorld, camera);
  }
  requestRender();
}

function syncThreeObject() {
  threeObject.geometry = object.geometry;
  threeObject.position.copy(object.position);
  threeObject.scale.copy(object.scale);
}

// The split's x in CSS pixels (the object's centre on screen, inside the canvas).
function splitX() {
  const w = canvas.clientWidth;
  const v = object.position.clone().project(camera);
  return Math.round(THREE.MathUtils.clamp((v.x + 1) / 2, 0, 1) * w);
}

function draw() {
  const split = $('split');
  if (!compare.on || !compare.light || compare.grid !== PG.grid?.name) {
    split.hidden = true;
    renderer.render(world, camera);
    return;
  }
  syncThreeObject();
  const w = canvas.clientWidth, h = canvas.clientHeight;
  const x = splitX();
  renderer.setScissorTest(true);
  renderer.setScissor(0, 0, x, h);
  renderer.render(world, camera);
  renderer.setScissor(x, 0, w - x, h);
  object.visible = false;
  renderer.render(world, camera);
  renderer.autoClear = false;
  renderer.render(threeWorld, camera);  // on the world's depth: the scene still hides it
  renderer.autoClear = true;
  object.visible = true;
  renderer.setScissorTest(false);
  split.hidden = false;
  split.style.left = `${x}px`;
}
controls.addEventListener('change', () => { requestRender(); scheduleQuery(); });

function resize() {
  const { clientWidth: w, clientHeight: h } = canvas.parentElement;
  renderer.setSize(w, h, false);
  camera.aspect = w / Math.max(h, 1);
  camera.updateProjectionMatrix();
  requestRender();
}
window.addEventListener('resize', resize);

// ---------------------------------------------------------------------------- grid SH texture
function gridTexture(grid, probes) {
  const [nx, ny, nz] = grid.counts;
  const data = new Float32Array(nx * ny * nz * 7 * 4);
  for (let i = 0; i < nx; i++) for (let j = 0; j < ny; j++) for (let k = 0; k < nz; k++) {
    const p = (i * ny + j) * nz + k;
    const v = probes.valid[p] ? 1 : 0;
    for (let e = 0; e < 28; e++) {
      const t = e >> 2;  // texel layer
      data[4 * (((t * nz + k) * ny + j) * nx + i) + (e & 3)] = e < 27 ? v * probes.sh[27 * p + e] : v;
    }
  }
  // float where it can be filtered (OES_texture_float_linear), else half float (always can)
  const floatLinear = renderer.extensions.has('OES_texture_float_linear');
  const texels = floatLinear ? data : Uint16Array.from(data, THREE.DataUtils.toHalfFloat);
  const tex = new THREE.Data3DTexture(texels, nx, ny, nz * 7);
  tex.format = THREE.RGBAFormat;
  tex.type = floatLinear ? THREE.FloatType : THREE.HalfFloatType;
  tex.minFilter = tex.magFilter = THREE.LinearFilter;
  tex.wrapS = tex.wrapT = tex.wrapR = THREE.ClampToEdgeWrapping;
  tex.unpackAlignment = 1;
  tex.needsUpdate = true;
  return tex;
}

// ---------------------------------------------------------------------------- probes
let probeMesh = null;
function probeMaterial(shTexture, perRow) {
  return new THREE.ShaderMaterial({
    uniforms: { pgProbeSH: { value: shTexture } },
    vertexShader: /* glsl */`
      attribute vec2 aFlags;
      varying vec3 vNormalW;
      varying vec3 vViewW;
      varying vec3 vObj;
      flat varying int vProbe;
      flat varying vec2 vFlags;
      void main() {
        vec4 wp = modelMatrix * instanceMatrix * vec4(position, 1.0);
        vNormalW = normal;  // instances are uniformly scaled and not rotated
        vViewW = cameraPosition - wp.xyz;
        vObj = position;
        vProbe = gl_InstanceID;
        vFlags = aFlags;
        gl_Position = projectionMatrix * viewMatrix * wp;
      }`,
    fragmentShader: /* glsl */`
      uniform highp sampler2D pgProbeSH;
      varying vec3 vNormalW;
      varying vec3 vViewW;
      varying vec3 vObj;
      flat varying int vProbe;
      flat varying vec2 vFlags;
      ${SH_GLSL}
      void main() {
        vec3 L[9];
        int row = vProbe / ${perRow};
        int col = (vProbe - row * ${perRow}) * 9;
        for (int c = 0; c < 9; c++) L[c] = texelFetch(pgProbeSH, ivec2(col + c, row), 0).rgb;
        vec3 n = normalize(vNormalW);
        vec3 color = max(pgIrradiance(L, n), vec3(0.0)) / 3.141592653589793;
        float rim = pow(1.0 - abs(dot(n, normalize(vViewW))), 3.0);
        if (vFlags.x < 0.5) {          // invalid: red, striped
          float stripe = step(0.5, fract(6.0 * (vObj.x + vObj.y)));
          color = mix(vec3(0.9, 0.1, 0.1), vec3(0.25, 0.0, 0.0), stripe);
        } else if (vFlags.y > 0.5) {   // relocated: yellow rim
          color = mix(color, vec3(1.0, 0.82, 0.25), smoothstep(0.2, 0.6, rim));
        }
        gl_FragColor = vec4(color, 1.0);
        #include <tonemapping_fragment>
        #include <colorspace_fragment>
      }`,
  });
}

function buildProbes(grid, probes) {
  if (probeMesh) {
    probeRoot.remove(probeMesh);
    probeMesh.geometry.dispose();
    probeMesh.material.dispose();
  }
  const n = probes.count;
  const perRow = 64;
  const rows = Math.ceil(n / perRow);
  const data = new Float32Array(perRow * 9 * rows * 4);
  for (let p = 0; p < n; p++) {
    const base = 4 * ((Math.floor(p / perRow) * perRow * 9) + (p % perRow) * 9);
    for (let c = 0; c < 9; c++) data.set(probes.sh.subarray(27 * p + 3 * c, 27 * p + 3 * c + 3), base + 4 * c);
  }
  const tex = new THREE.DataTexture(data, perRow * 9, rows, THREE.RGBAFormat, THREE.FloatType);
  tex.needsUpdate = true;
  const geo = n > 4096 ? new THREE.SphereGeometry(1, 10, 7) : new THREE.SphereGeometry(1, 20, 14);
  const flags = new Float32Array(2 * n);
  for (let p = 0; p < n; p++) { flags[2 * p] = probes.valid[p]; flags[2 * p + 1] = probes.relocated[p]; }
  geo.setAttribute('aFlags', new THREE.InstancedBufferAttribute(flags, 2));
  probeMesh = new THREE.InstancedMesh(geo, probeMaterial(tex, perRow), n);
  probeMesh.frustumCulled = false;
  probeMesh.name = 'probes';
  probeRoot.add(probeMesh);
  setProbeSize(Number($('probe-size').value));
}

function setProbeSize(size) {
  $('probe-size-out').textContent = `${size.toFixed(2)} × spacing`;
  if (!probeMesh || !PG.probes) return;
  const sp = PG.grid.spacing.filter((s) => s > 0);
  const r = size * (sp.length ? Math.min(...sp) : 1) * 0.5;
  const m = new THREE.Matrix4();
  const pos = PG.probes.positions;
  for (let p = 0; p < PG.probes.count; p++) {
    m.makeScale(r, r, r).setPosition(pos[3 * p], pos[3 * p + 1], pos[3 * p + 2]);
    probeMesh.setMatrixAt(p, m);
  }
  probeMesh.instanceMatrix.needsUpdate = true;
  requestRender();
}

// ---------------------------------------------------------------------------- scene
function litByGrid(material) {
  // the glTF material keeps its base colour, textures, metalness and emission; its diffuse
  // irradiance comes from the grid (after three's own light chunks, which add nothing here)
  material.onBeforeCompile = (shader) => {
    Object.assign(shader.uniforms, gridUniforms);
    shader.fragmentShader = shader.fragmentShader
      .replace('#include <common>', `#include <common>\n${GRID_GLSL}`)
      .replace('#include <lights_fragment_maps>', `#include <lights_fragment_maps>
        #if defined( RE_IndirectDiffuse )
          irradiance += pgGridIrradiance(((vec4(geometryPosition, 1.0) - viewMatrix[3]) * viewMatrix).xyz,
                                         inverseTransformDirection(geometryNormal, viewMatrix));
        #endif`);
  };
  material.customProgramCacheKey = () => 'probegrid-lit';
  material.needsUpdate = true;
}

async function loadScene(grid, prefetched) {
  sceneRoot.clear();
  if (!grid.manifest.scene_file) return false;  // the store keeps no copy of its scene
  const buffer = prefetched || await (await fetchOk(api.grid(grid.name) + '/scene')).arrayBuffer();
  const gltf = await new GLTFLoader().parseAsync(buffer, '');
  const lights = [];
  gltf.scene.traverse((o) => {
    if (o.isLight) lights.push(o);
    if (o.isMesh) {
      const mats = Array.isArray(o.material) ? o.material : [o.material];
      mats.forEach(litByGrid);
    }
  });
  lights.forEach((l) => l.removeFromParent());
  sceneRoot.add(gltf.scene);
  return true;
}

// ---------------------------------------------------------------------------- moving object
const MATERIALS = {
  matte: { albedo: [0.8, 0.8, 0.8], f0: [0, 0, 0], roughness: 1.0, specular: false },
  rough: { albedo: [0, 0, 0], f0: [0.91, 0.92, 0.92], roughness: 0.5, specular: true },
  smooth: { albedo: [0, 0, 0], f0: [0.95, 0.93, 0.88], roughness: 0.0, specular: true },
};
const objUniforms = {
  uSH: { value: Array.from({ length: 9 }, () => new THREE.Vector3()) },
  uAlbedo: { value: new THREE.Vector3(0.8, 0.8, 0.8) },
  uF0: { value: new THREE.Vector3() },
  uRoughness: { value: 1.0 },
  uSpecOn: { value: 0 },
  uSpec: { value: null },
  uDFG: { value: null },
  uOutput: { value: 0 },  // 0 shaded, 1 world normal, 2 world position (the tests' read-back)
};
const objMaterial = new THREE.ShaderMaterial({
  uniforms: objUniforms,
  vertexShader: /* glsl */`
    varying vec3 vNormalW;
    varying vec3 vPosW;
    void main() {
      vec4 wp = modelMatrix * vec4(position, 1.0);
      vPosW = wp.xyz;
      vNormalW = normal;  // the object is translated only
      gl_Position = projectionMatrix * viewMatrix * wp;
    }`,
  fragmentShader: /* glsl */`
    uniform vec3 uSH[9];
    uniform vec3 uAlbedo;
    uniform vec3 uF0;
    uniform float uRoughness;
    uniform float uSpecOn;
    uniform samplerCube uSpec;
    uniform sampler2D uDFG;
    uniform int uOutput;
    varying vec3 vNormalW;
    varying vec3 vPosW;
    ${SH_GLSL}
    void main() {
      vec3 n = normalize(vNormalW);
      if (uOutput == 1) { gl_FragColor = vec4(n, 1.0); return; }
      if (uOutput == 2) { gl_FragColor = vec4(vPosW, 1.0); return; }
      vec3 v = normalize(cameraPosition - vPosW);
      vec3 diffuse = pgIrradiance(uSH, n) / 3.141592653589793;
      vec3 color = uAlbedo * diffuse;
      if (uSpecOn > 0.5) {
        float ndv = clamp(dot(n, v), 0.0, 1.0);
        vec2 ab = texture(uDFG, vec2(ndv, uRoughness)).rg;
        vec3 s = uF0 * ab.x + ab.y;
        vec3 r = 2.0 * dot(n, v) * n - v;
        color = uAlbedo * (1.0 - s) * diffuse + s * texture(uSpec, r).rgb;
      }
      gl_FragColor = vec4(color, 1.0);
      #include <tonemapping_fragment>
      #include <colorspace_fragment>
    }`,
});
const object = new THREE.Mesh(new THREE.SphereGeometry(1, 96, 64), objMaterial);
object.name = 'object';
world.add(object);
const weightLines = new THREE.LineSegments(
  new THREE.BufferGeometry(),
  new THREE.LineBasicMaterial({ vertexColors: true, transparent: true, toneMapped: false }));
world.add(weightLines);

function setMaterial(key) {
  const m = MATERIALS[key];
  objUniforms.uAlbedo.value.fromArray(m.albedo);
  objUniforms.uF0.value.fromArray(m.f0);
  PG.material = key;
  scheduleQuery();
  requestRender();
}

function setMapMethod(m) {
  PG.mapMethod = m === 'blend' ? 'blend' : 'trace';
  scheduleQuery();
}

function specularLevel() {
  const m = MATERIALS[PG.material];
  if (!m.specular || !PG.grid || !PG.grid.kinds.includes('specular')) return null;
  const levels = PG.grid.specular_levels;
  return levels > 1 ? Math.round(m.roughness * (levels - 1)) : 0;
}

function cubeFromNpy({ shape, data }) {
  const n = shape[1];
  const faces = [];
  for (let f = 0; f < 6; f++) {
    const rgba = new Float32Array(n * n * 4);
    for (let t = 0; t < n * n; t++) {
      const s = (f * n * n + t) * 3;
      rgba[4 * t] = data[s]; rgba[4 * t + 1] = data[s + 1]; rgba[4 * t + 2] = data[s + 2]; rgba[4 * t + 3] = 1;
    }
    faces.push(new THREE.DataTexture(rgba, n, n, THREE.RGBAFormat, THREE.FloatType));
  }
  const cube = new THREE.CubeTexture(faces);
  cube.format = THREE.RGBAFormat;
  cube.type = THREE.FloatType;
  cube.minFilter = cube.magFilter = THREE.LinearFilter;
  cube.generateMipmaps = false;
  cube.flipY = false;
  cube.needsUpdate = true;
  return cube;
}

// ---------------------------------------------------------------------------- queries
let inFlight = false;
let pending = false;
const waiters = [];

function queryParams() {
  const p = object.position;
  const n = new THREE.Vector3().subVectors(camera.position, p);
  if (n.lengthSq() === 0) n.set(0, 1, 0);
  n.normalize();
  const f = (v) => Number(v.toFixed(5));
  return { position: [f(p.x), f(p.y), f(p.z)], normal: [f(n.x), f(n.y), f(n.z)] };
}

function scheduleQuery() {
  if (!PG.grid) return;
  if (inFlight) { pending = true; PG.stats.coalesced++; return; }
  pump();
}

async function pump() {
  inFlight = true;
  try {
    do {
      pending = false;
      const q = queryParams();
      const last = PG.lastQuery;
      const same = last && last.grid === PG.grid.name && last.level === specularLevel()
        && last.asked === (specularLevel() === null ? null : PG.mapMethod)
        && String(last.position) === String(q.position) && String(last.normal) === String(q.normal);
      if (!same) await runQuery(q);  // an unchanged query is not asked again
    } while (pending);
  } catch (e) {
    report(e);
  } finally {
    inFlight = false;
  }
  const done = waiters.splice(0);
  done.forEach((w) => w(PG.lastQuery));
}

async function runQuery(q) {
  const grid = PG.grid.name;
  const [x, y, z] = q.position;
  const [nx, ny, nz] = q.normal;
  const where = `x=${x}&y=${y}&z=${z}&nx=${nx}&ny=${ny}&nz=${nz}`;
  const level = specularLevel();
  if (level !== null) await PG.dfgLoading;  // the split sum needs the DFG table
  PG.stats.sh++;
  const shReq = getJSON(`${api.grid(grid)}/sh?${where}`);
  let mapReq = null;
  const asked = level === null ? null : PG.mapMethod;
  let method = null;
  if (level !== null) {
    PG.stats.maps++;
    mapReq = fetchOk(`${api.grid(grid)}/maps/specular?${where}&level=${level}&format=npy&method=${asked}`)
      .then((r) => { method = r.headers.get('X-Probegrid-Method'); return r.arrayBuffer(); });
  }
  const [sh, mapBuf] = await Promise.all([shReq, mapReq]);
  sh.coefficients.forEach((c, i) => objUniforms.uSH.value[i].fromArray(c));
  if (mapBuf) {
    if (objUniforms.uSpec.value) objUniforms.uSpec.value.dispose();
    objUniforms.uSpec.value = cubeFromNpy(parseNpy(mapBuf));
    objUniforms.uRoughness.value = PG.grid.specular_levels > 1 ? level / (PG.grid.specular_levels - 1) : 0;
    objUniforms.uSpecOn.value = PG.dfgTexture ? 1 : 0;
  } else {
    objUniforms.uSpecOn.value = 0;
  }
  PG.lastQuery = { grid, position: q.position, normal: q.normal, sh, level, asked, method };
  showWeights(sh);
  if ($('inspector').open) updateInspector(where);
  requestRender();
}

function waitForQuery() {
  return new Promise((resolve) => {
    if (!inFlight && !pending) resolve(PG.lastQuery); else waiters.push(resolve);
  });
}

function showWeights(sh) {
  const rows = sh.probes.map((p) => `<tr><td>${p.index}</td><td>${p.ijk.join(',')}</td>` +
    `<td>${p.weight.toFixed(3)} <span class="bar" style="width:${Math.round(60 * p.weight)}px"></span></td></tr>`);
  $('used').tBodies[0].innerHTML = rows.join('') || '<tr><td colspan="3">none (unlit)</td></tr>';
  const f = sh.flags;
  $('flags').textContent = [sh.source === 'field' ? 'diffuse: the SH field' : 'diffuse: the probes',
    f.visibility ? 'visibility-aware (DDGI) weights' : 'trilinear weights',
    f.outside ? 'outside the grid: clamped' : '', f.unlit ? 'unlit: no valid probe' : '',
    PG.lastQuery && PG.lastQuery.method ? `reflections: ${PG.lastQuery.method === 'trace' ? 'traced at the object' : 'blended from the probes'}` : '']
    .filter(Boolean).join(' · ');
  const pos = [];
  const col = [];
  const o = object.position;
  for (const p of sh.probes) {  // the probes, or the SH field's lattice points (p.position)
    const i = p.index;
    const q = PG.probes.positions;
    const at = p.position || [q[3 * i], q[3 * i + 1], q[3 * i + 2]];
    pos.push(o.x, o.y, o.z, at[0], at[1], at[2]);
    const w = Math.min(1, p.weight * 2);
    col.push(0.4, 0.7, 1, 0.4 * w + 0.2 * w, 0.7 * w, w);
  }
  weightLines.geometry.setAttribute('position', new THREE.Float32BufferAttribute(pos, 3));
  weightLines.geometry.setAttribute('color', new THREE.Float32BufferAttribute(col, 3));
}

function moveObject(x, y, z) {
  const g = PG.grid;
  const pad = 0.5 * Math.max(...g.spacing, 0.1);
  object.position.set(
    THREE.MathUtils.clamp(x, g.bounds_min[0] - pad, g.bounds_max[0] + pad),
    THREE.MathUtils.clamp(y, g.bounds_min[1] - pad, g.bounds_max[1] + pad),
    THREE.MathUtils.clamp(z, g.bounds_min[2] - pad, g.bounds_max[2] + pad));
  ['x', 'y', 'z'].forEach((c) => { $(`o${c}`).value = object.position[c].toFixed(2); });
  scheduleQuery();
  requestRender();
}

// dragging: on the horizontal plane through the object (shift: on the vertical plane facing the camera)
const raycaster = new THREE.Raycaster();
const pointer = new THREE.Vector2();
let drag = null;
function ndc(ev) {
  const r = canvas.getBoundingClientRect();
  pointer.set(((ev.clientX - r.left) / r.width) * 2 - 1, -((ev.clientY - r.top) / r.height) * 2 + 1);
  raycaster.setFromCamera(pointer, camera);
}
canvas.addEventListener('pointerdown', (ev) => {
  if (!PG.ready) return;
  ndc(ev);
  if (!raycaster.intersectObject(object).length) return;
  const normal = ev.shiftKey
    ? new THREE.Vector3().subVectors(camera.position, object.position).setY(0).normalize()
    : new THREE.Vector3(0, 1, 0);
  drag = { plane: new THREE.Plane().setFromNormalAndCoplanarPoint(normal, object.position), vertical: ev.shiftKey };
  controls.enabled = false;
  canvas.setPointerCapture(ev.pointerId);
});
canvas.addEventListener('pointermove', (ev) => {
  if (!drag) return;
  ndc(ev);
  const hit = new THREE.Vector3();
  if (!raycaster.ray.intersectPlane(drag.plane, hit)) return;
  const p = object.position;
  if (drag.vertical) moveObject(p.x, hit.y, p.z); else moveObject(hit.x, p.y, hit.z);
});
canvas.addEventListener('pointerup', () => { drag = null; controls.enabled = true; });

// ---------------------------------------------------------------------------- inspector, facts
function updateInspector(where) {
  const g = api.grid(PG.grid.name);
  $('insp-diffuse').src = `${g}/maps/diffuse?${where}&format=png&layout=cross&method=${PG.mapMethod}`;
  const box = $('insp-specular');
  const levels = PG.grid.kinds.includes('specular') ? PG.grid.specular_levels : 0;
  if (box.childElementCount !== levels) {
    box.innerHTML = '';
    for (let k = 0; k < levels; k++) {
      const r = levels > 1 ? k / (levels - 1) : 0;
      box.insertAdjacentHTML('beforeend', `<figure><img alt="specular level ${k}">` +
        `<figcaption>specular level ${k} (roughness ${r.toFixed(2)}, ${PG.grid.map_sizes.specular[k]}²)</figcaption></figure>`);
    }
  }
  [...box.querySelectorAll('img')].forEach((img, k) => {
    img.src = `${g}/maps/specular?${where}&level=${k}&format=png&layout=cross&method=${PG.mapMethod}`;
  });
}
$('inspector').addEventListener('toggle', () => {
  if ($('inspector').open && PG.lastQuery) {
    const q = PG.lastQuery;
    updateInspector(`x=${q.position[0]}&y=${q.position[1]}&z=${q.position[2]}&nx=${q.normal[0]}&ny=${q.normal[1]}&nz=${q.normal[2]}`);
  }
});

async function loadDFG() {
  const { shape, data } = parseNpy(await (await fetchOk('/v1/dfg')).arrayBuffer());
  const [h, w] = shape;
  const rgba = new Float32Array(w * h * 4);
  const c = $('insp-dfg');
  c.width = w; c.height = h;
  const ctx = c.getContext('2d');
  const img = ctx.createImageData(w, h);
  for (let t = 0; t < w * h; t++) {
    rgba[4 * t] = data[2 * t]; rgba[4 * t + 1] = data[2 * t + 1]; rgba[4 * t + 3] = 1;
    img.data[4 * t] = Math.round(255 * data[2 * t]);
    img.data[4 * t + 1] = Math.round(255 * data[2 * t + 1]);
    img.data[4 * t + 3] = 255;
  }
  ctx.putImageData(img, 0, 0);
  // rows are roughness (row 0 = roughness 0 = texture v 0), columns N.V: texture(uDFG, (N.V, r))
  const tex = new THREE.DataTexture(rgba, w, h, THREE.RGBAFormat, THREE.FloatType);
  tex.minFilter = tex.magFilter = THREE.LinearFilter;
  tex.needsUpdate = true;
  objUniforms.uDFG.value = tex;
  PG.dfgTexture = tex;
}

function showFacts(g) {
  const m = g.manifest;
  const fmt = (v) => (Array.isArray(v) ? v.map((x) => (typeof x === 'number' ? +x.toFixed(4) : x)).join(', ') : String(v));
  const facts = [
    ['grid', g.name], ['probes', `${g.probes} (${g.counts.join(' × ')}), ${g.valid_probes} valid`],
    ['bounds min', fmt(g.bounds_min)], ['bounds max', fmt(g.bounds_max)], ['spacing', fmt(g.spacing)],
    ['maps', g.kinds.map((k) => `${k} ${g.map_sizes[k].join('/')}`).join('; ')],
    ['specular levels', g.specular_levels], ['visibility (DDGI)', g.visibility],
    ['relocated', m.quality.relocated_probes ?? '–'], ['invalid', m.quality.invalid_probes ?? '–'],
    ['scene', m.scene_file ? `${m.scene_file.source} (${(m.scene_file.bytes / 1024).toFixed(1)} KiB)` : 'not kept'],
    ['scene hash', g.scene_hash.slice(0, 16) + '…'], ['created', g.created],
    ['probegrid', m.probegrid_version],
  ];
  $('facts-list').innerHTML = facts.map(([k, v]) => `<dt>${k}</dt><dd>${v}</dd>`).join('');
  $('conventions').textContent = JSON.stringify(m.conventions, null, 1);
  $('quality').textContent = JSON.stringify(m.quality, null, 1);
}

// ---------------------------------------------------------------------------- loading a grid
async function showGrid(name) {
  PG.ready = false;
  document.body.dataset.ready = '0';
  setStatus(`loading ${name}…`);
  if (!PG.dfgLoading) PG.dfgLoading = loadDFG().catch(report);  // in the background: only reflections need it
  let first = null;
  if (prefetch.first) {  // used once, for the grid shown first
    first = await prefetch.first.catch(() => null);
    prefetch.first = null;
  }
  const [grid, raw, sceneBuffer] = first && first[0].name === name ? first
    : await Promise.all([getJSON(api.grid(name)), getJSON(api.grid(name) + '/probes'), null]);
  PG.grid = grid;
  PG.probes = {
    count: raw.probes,
    positions: base64Array(raw.positions, Float32Array),
    sh: base64Array(raw.sh, Float32Array),
    valid: base64Array(raw.valid, Uint8Array),
    relocated: base64Array(raw.relocated, Uint8Array),
  };
  PG.probeCount = raw.probes;
  mark('data');
  const [nx, ny, nz] = grid.counts;
  if (gridUniforms.pgGridSH.value) gridUniforms.pgGridSH.value.dispose();
  gridUniforms.pgGridSH.value = gridTexture(grid, PG.probes);
  gridUniforms.pgGridMin.value.fromArray(grid.bounds_min);
  gridUniforms.pgGridSpacing.value.fromArray(grid.spacing);
  gridUniforms.pgGridCounts.value.set(nx, ny, nz);
  buildProbes(grid, PG.probes);
  showFacts(grid);
  const hasScene = await loadScene(grid, sceneBuffer);
  mark('scene');
  renderer.compile(world, camera);  // before the first frame (SwiftShader: no parallel compile)
  mark('compiled');
  PG.hasScene = hasScene;
  // camera: outside the grid box, looking at its centre
  const lo = new THREE.Vector3().fromArray(grid.bounds_min);
  const hi = new THREE.Vector3().fromArray(grid.bounds_max);
  const centre = lo.clone().add(hi).multiplyScalar(0.5);
  const size = Math.max(hi.clone().sub(lo).length(), 1e-3);
  const box = new THREE.Box3(lo, hi);
  if (hasScene) box.expandByObject(sceneRoot);
  const radius = Math.max(0.05, 0.25 * Math.min(...grid.spacing.filter((s) => s > 0), size));
  object.scale.setScalar(radius);
  object.position.copy(centre);
  camera.near = size / 1000; camera.far = size * 100; camera.updateProjectionMatrix();
  camera.position.copy(centre).add(new THREE.Vector3(0.35, 0.3, 0.9).multiplyScalar(size * 0.9));
  if (hasScene) {  // inside a closed room, look from inside the grid box
    camera.position.copy(centre).add(new THREE.Vector3(0.3, 0.12, 0.45).multiplyScalar(hi.clone().sub(lo).length()));
  }
  controls.target.copy(centre);
  controls.update();
  moveObject(centre.x, centre.y, centre.z);
  await waitForQuery();
  mark('query');
  if (compare.on) await setCompare(true).catch(report);  // the new grid's export
  await new Promise((r) => requestAnimationFrame(() => { draw(); r(); }));
  mark('frame');
  setStatus(`${grid.name}: ${grid.probes} probes${hasScene ? '' : ' (the store keeps no scene)'}`);
  PG.ready = true;
  document.body.dataset.ready = '1';
}

function report(e) {
  PG.errors.push(String(e));
  setStatus(String(e.message || e), true);
  console.error(e);
}

// ---------------------------------------------------------------------------- test hooks
// Render the object alone into float targets (linear, no tone mapping: three applies those
// only when drawing to the screen) and return `count` pixels inside it: shaded RGB and the
// world normal of the same fragment.
// readObject(count, 'three') shades with three's sphere (LightProbeGridWebGL, the export) instead,
// with the normals and positions of the service's sphere (the same geometry and place).
PG.readObject = function readObject(count = 64, source = 'service') {
  const w = 256, h = 256;
  const target = new THREE.WebGLRenderTarget(w, h, { type: THREE.FloatType, format: THREE.RGBAFormat });
  const solo = new THREE.Scene();
  const parent = object.parent;
  solo.add(object);
  // a square view of the object from the camera's side, filling most of the target
  const cam = camera.clone();
  const dir = new THREE.Vector3().subVectors(camera.position, object.position).normalize();
  cam.position.copy(object.position).addScaledVector(dir, 2.6 * object.scale.x);
  cam.aspect = 1; cam.near = 0.1 * object.scale.x; cam.far = 10 * object.scale.x;
  cam.updateProjectionMatrix();
  cam.lookAt(object.position);
  const read = (mode) => {
    objUniforms.uOutput.value = mode;
    renderer.setRenderTarget(target);
    renderer.setClearColor(0x000000, 0);
    renderer.clear();
    renderer.render(solo, cam);
    const buf = new Float32Array(w * h * 4);
    renderer.readRenderTargetPixels(target, 0, 0, w, h, buf);
    return buf;
  };
  let shaded;
  if (source === 'three') {
    syncThreeObject();
    renderer.setRenderTarget(target);
    renderer.setClearColor(0x000000, 0);
    renderer.clear();
    renderer.render(threeWorld, cam);
    shaded = new Float32Array(w * h * 4);
    renderer.readRenderTargetPixels(target, 0, 0, w, h, shaded);
  } else {
    shaded = read(0);
  }
  const normals = read(1);
  const positions = read(2);
  objUniforms.uOutput.value = 0;
  renderer.setRenderTarget(null);
  renderer.setClearColor(0x000000, 1);
  parent.add(object);
  target.dispose();
  const inside = [];
  for (let t = 0; t < w * h; t++) if (normals[4 * t + 3] > 0 && shaded[4 * t + 3] > 0) inside.push(t);
  const step = Math.max(1, Math.floor(inside.length / count));
  const pixels = [];
  for (let i = 0; i < inside.length && pixels.length < count; i += step) {
    const t = inside[i];
    pixels.push({ pixel: t, rgb: [shaded[4 * t], shaded[4 * t + 1], shaded[4 * t + 2]],
                  normal: [normals[4 * t], normals[4 * t + 1], normals[4 * t + 2]],
                  position: [positions[4 * t], positions[4 * t + 1], positions[4 * t + 2]] });
  }
  requestRender();
  return { covered: inside.length, pixels, size: [w, h], camera: cam.position.toArray(),
           albedo: objUniforms.uAlbedo.value.toArray(), f0: objUniforms.uF0.value.toArray(),
           roughness: objUniforms.uRoughness.value, specular: objUniforms.uSpecOn.value,
           query: PG.lastQuery, source,
           three: source === 'three' ? { albedo: threeObject.material.color.toArray(),
                                         header: compare.header } : null };
};
PG.moveObject = async (x, y, z) => { moveObject(x, y, z); return waitForQuery(); };
PG.setMaterial = (key) => { $('material').value = key; setMaterial(key); return waitForQuery(); };
PG.setMapMethod = (m) => { $('map-method').value = m; setMapMethod(m); return waitForQuery(); };
PG.setToneMapping = (key) => { $('tonemap').value = key; renderer.toneMapping = TONEMAPS[key]; requestRender(); };
PG.render = () => draw();
PG.setCompare = setCompare;
PG.compare = compare;
PG.scene = world;
PG.camera = camera;

// ---------------------------------------------------------------------------- controls
$('tonemap').addEventListener('change', (e) => PG.setToneMapping(e.target.value));
$('exposure').addEventListener('input', (e) => {
  const ev = Number(e.target.value);
  renderer.toneMappingExposure = 2 ** ev;
  $('exposure-out').textContent = `${ev > 0 ? '+' : ''}${ev} EV`;
  requestRender();
});
$('show-probes').addEventListener('change', (e) => { probeRoot.visible = e.target.checked; requestRender(); });
$('show-scene').addEventListener('change', (e) => { sceneRoot.visible = e.target.checked; requestRender(); });
$('probe-size').addEventListener('input', (e) => setProbeSize(Number(e.target.value)));
$('material').addEventListener('change', (e) => setMaterial(e.target.value));
$('map-method').addEventListener('change', (e) => setMapMethod(e.target.value));
$('compare').addEventListener('change', (e) => setCompare(e.target.checked).catch(report));
['x', 'y', 'z'].forEach((c) => $(`o${c}`).addEventListener('change', () => {
  moveObject(Number($('ox').value), Number($('oy').value), Number($('oz').value));
}));
$('grid').addEventListener('change', (e) => showGrid(e.target.value).catch(report));

async function main() {
  resize();
  PG.material = $('material').value;
  setMaterial(PG.material);
  const { grids } = await gridsLoading;
  if (!grids.length) throw new Error('this service serves no grid');
  $('grid').innerHTML = grids.map((g) => `<option>${g.name}</option>`).join('');
  $('grid').disabled = grids.length < 2;
  await showGrid(grids[0].name);
  PG.tti = performance.now();
}
main().catch(report);
