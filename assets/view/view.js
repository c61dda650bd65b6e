// One job's model in 3D, with its texture switched between the input, the
// erased texture, regular and seam-aware BC1, and the input sampled with
// the filter taps outside the fragment's chart discarded (Toth, "Avoiding
// Texture Seams by Discarding Filter Taps"). Every file comes through the
// job's file route with the job's token in a header.
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { DDSLoader } from 'three/addons/loaders/DDSLoader.js';
import { takeFragmentToken, authFetch, getJson } from './auth.js';

const started = performance.now();
const params = takeFragmentToken();
const errors = [];
window.addEventListener('error', (e) => errors.push(String(e.message)));
window.addEventListener('unhandledrejection', (e) => errors.push(String(e.reason)));

// Closed, left and spared seams; closed and left in the hues of
// <name>.seams.png, spared in its amber.
const HUES = { closed: 0x00ffbe, left: 0xff46d2, spared: 0xffb000 };
// At this many screen pixels per texel, bilinear filtering shows plainly.
const PIXELS_PER_TEXEL = 16;
const MODES = [
  ['input', 'input'],
  ['erased', 'erased'],
  ['regular', 'regular BC1'],
  ['seam_aware', 'seam-aware BC1'],
  ['discard', 'input, taps discarded'],
];

const jobUrl = location.pathname.replace(/\/view$/, '');
const note = document.getElementById('note');

function say(text) {
  note.textContent = text;
}

/** A job file as an object URL (the loaders cannot send headers). */
async function fileBlob(name) {
  const resp = await authFetch(`${jobUrl}/files/${encodeURIComponent(name)}`);
  if (!resp.ok) throw new Error(`${name}: ${resp.status}`);
  return resp.blob();
}

async function fileUrl(name) {
  return URL.createObjectURL(await fileBlob(name));
}

/** Loads an image through <img>: exact texel values, no colour conversion. */
function loadImage(url) {
  return new Promise((resolve, reject) => {
    const img = new Image();
    img.onload = () => resolve(img);
    img.onerror = () => reject(new Error('cannot decode ' + url));
    img.src = url;
  });
}

function imageTexture(img, nearest) {
  const t = new THREE.Texture(img);
  t.flipY = false;
  t.colorSpace = THREE.NoColorSpace;
  t.wrapS = t.wrapT = THREE.RepeatWrapping;
  if (nearest) {
    t.minFilter = t.magFilter = THREE.NearestFilter;
    t.generateMipmaps = false;
  }
  t.needsUpdate = true;
  return t;
}

// ------------------------------------------------------------------ DDS

const FOURCC_DXT1 = 0x31545844;

/** BC1 (or BC3's colour) decoded with the ideal palette: (2a+b)/3, (a+b)/2. */
function decodeBc(mip, bc3) {
  const { width, height, data } = mip;
  const out = new Uint8Array(width * height * 4);
  const bw = Math.ceil(width / 4);
  const stride = bc3 ? 16 : 8;
  const expand = (c) => [((c >> 11) & 31) * 255 / 31, ((c >> 5) & 63) * 255 / 63, (c & 31) * 255 / 31];
  for (let by = 0; by < Math.ceil(height / 4); by++) {
    for (let bx = 0; bx < bw; bx++) {
      const o = (by * bw + bx) * stride + (bc3 ? 8 : 0);
      const c0 = data[o] | (data[o + 1] << 8);
      const c1 = data[o + 2] | (data[o + 3] << 8);
      const a = expand(c0), b = expand(c1);
      const four = bc3 || c0 > c1;
      const pal = [a, b,
        four ? a.map((x, i) => (2 * x + b[i]) / 3) : a.map((x, i) => (x + b[i]) / 2),
        four ? a.map((x, i) => (x + 2 * b[i]) / 3) : [0, 0, 0]];
      const bits = data[o + 4] | (data[o + 5] << 8) | (data[o + 6] << 16) | (data[o + 7] << 24);
      for (let k = 0; k < 16; k++) {
        const x = bx * 4 + (k & 3), y = by * 4 + (k >> 2);
        if (x >= width || y >= height) continue;
        const idx = (bits >>> (2 * k)) & 3;
        const p = (y * width + x) * 4;
        out[p] = Math.round(pal[idx][0]);
        out[p + 1] = Math.round(pal[idx][1]);
        out[p + 2] = Math.round(pal[idx][2]);
        out[p + 3] = !four && idx === 3 ? 0 : 255;
      }
    }
  }
  return out;
}

/** A DDS as the GPU samples it, or decoded here when it cannot. */
function ddsTexture(buffer, gpu) {
  const dds = new DDSLoader().parse(buffer, true);
  let t;
  if (gpu) {
    t = new THREE.CompressedTexture(dds.mipmaps, dds.width, dds.height, dds.format);
    t.minFilter = dds.mipmapCount === 1 ? THREE.LinearFilter : THREE.LinearMipmapLinearFilter;
  } else {
    const fourcc = new Uint32Array(buffer, 84, 1)[0];
    const rgba = decodeBc(dds.mipmaps[0], fourcc !== FOURCC_DXT1);
    t = new THREE.DataTexture(rgba, dds.width, dds.height, THREE.RGBAFormat);
    t.minFilter = THREE.LinearMipmapLinearFilter;
    t.generateMipmaps = true;
  }
  t.magFilter = THREE.LinearFilter;
  t.flipY = false;
  t.colorSpace = THREE.NoColorSpace;
  t.wrapS = t.wrapT = THREE.RepeatWrapping;
  t.needsUpdate = true;
  return t;
}

// ------------------------------------------------------------------ shader

const VERTEX = `
#include <common>
#include <skinning_pars_vertex>
attribute float chartId;
varying vec2 vUv;
flat varying float vChart;
void main() {
  vUv = uv;
  vChart = chartId;
  #include <begin_vertex>
  #include <skinbase_vertex>
  #include <skinning_vertex>
  #include <project_vertex>
}`;

// Mode 0 samples 'map' as the GPU does. Mode 1 does the four bilinear taps
// of the input by hand, drops those whose chart is not the fragment's own
// and renormalises the rest.
const FRAGMENT = `
uniform sampler2D map;
uniform sampler2D inputMap;
uniform sampler2D charts;
uniform int mode;
uniform vec2 size;
varying vec2 vUv;
flat varying float vChart;
int chartAt(ivec2 t) {
  ivec3 b = ivec3(texelFetch(charts, t, 0).rgb * 255.0 + 0.5);
  return b.r + b.g * 256 + b.b * 65536;
}
ivec2 wrapped(ivec2 t, ivec2 n) {
  return t - n * ivec2(floor(vec2(t) / vec2(n)));
}
void main() {
  if (mode == 0) {
    gl_FragColor = vec4(texture2D(map, vUv).rgb, 1.0);
    return;
  }
  ivec2 n = ivec2(size);
  vec2 st = vUv * size - 0.5;
  vec2 f = fract(st);
  ivec2 i0 = ivec2(floor(st));
  int own = int(vChart + 0.5);
  vec3 sum = vec3(0.0);
  float weight = 0.0;
  for (int k = 0; k < 4; k++) {
    ivec2 o = ivec2(k & 1, k >> 1);
    float w = (o.x == 1 ? f.x : 1.0 - f.x) * (o.y == 1 ? f.y : 1.0 - f.y);
    ivec2 t = wrapped(i0 + o, n);
    if (chartAt(t) == own) {
      sum += w * texelFetch(inputMap, t, 0).rgb;
      weight += w;
    }
  }
  gl_FragColor = vec4(weight > 0.0 ? sum / weight : texture2D(inputMap, vUv).rgb, 1.0);
}`;

// ------------------------------------------------------------------ scene

const stage = document.getElementById('stage');
const width = Number(params.get('width')) || stage.clientWidth || 800;
const height = Number(params.get('height')) || stage.clientHeight || 600;
const renderer = new THREE.WebGLRenderer({ antialias: false, preserveDrawingBuffer: true });
renderer.setPixelRatio(1);
renderer.setSize(width, height);
renderer.setClearColor(0x202028);
stage.prepend(renderer.domElement);
const gpuS3tc = params.get('decode') !== 'page' && renderer.extensions.has('WEBGL_compressed_texture_s3tc');
const scene = new THREE.Scene();
const camera = new THREE.PerspectiveCamera(35, width / height, 0.01, 1000);
const target = new THREE.Vector3();
let dirty = true;

function render() {
  dirty = true;
}

function frame() {
  if (dirty) {
    dirty = false;
    renderer.render(scene, camera);
  }
  requestAnimationFrame(frame);
}

// ------------------------------------------------------------------ orbit

// Drag turns the camera round the target about its own up and right axes
// (so a camera turned to a seam keeps that seam's orientation); the wheel
// moves it nearer or farther.
let drag = null;
renderer.domElement.addEventListener('pointerdown', (e) => {
  drag = { x: e.clientX, y: e.clientY };
  renderer.domElement.setPointerCapture(e.pointerId);
});
renderer.domElement.addEventListener('pointerup', () => { drag = null; });
renderer.domElement.addEventListener('pointermove', (e) => {
  if (!drag) return;
  const dx = (e.clientX - drag.x) * 0.01, dy = (e.clientY - drag.y) * 0.01;
  drag = { x: e.clientX, y: e.clientY };
  const offset = camera.position.clone().sub(target);
  const right = new THREE.Vector3().crossVectors(camera.up, offset).normalize();
  const q = new THREE.Quaternion().setFromAxisAngle(camera.up, -dx)
    .multiply(new THREE.Quaternion().setFromAxisAngle(right, dy));
  offset.applyQuaternion(q);
  camera.up.applyQuaternion(q);
  camera.position.copy(target).add(offset);
  camera.lookAt(target);
  render();
});
renderer.domElement.addEventListener('wheel', (e) => {
  e.preventDefault();
  const offset = camera.position.clone().sub(target).multiplyScalar(Math.exp(e.deltaY * 0.001));
  camera.position.copy(target).add(offset);
  camera.near = offset.length() / 100;
  camera.updateProjectionMatrix();
  camera.lookAt(target);
  render();
}, { passive: false });

function place(position, look, up) {
  camera.position.copy(position);
  target.copy(look);
  camera.up.copy(up);
  camera.near = position.distanceTo(look) / 100;
  camera.far = position.distanceTo(look) * 100 + 1000;
  camera.updateProjectionMatrix();
  camera.lookAt(target);
  render();
}

/** Moves the camera there over half a second (at once when `instant`). */
function fly(position, look, up, instant) {
  if (instant) return place(position, look, up);
  const from = [camera.position.clone(), target.clone(), camera.up.clone()];
  const t0 = performance.now();
  const step = () => {
    const t = Math.min(1, (performance.now() - t0) / 500);
    const s = t * t * (3 - 2 * t);
    place(from[0].clone().lerp(position, s), from[1].clone().lerp(look, s),
      from[2].clone().lerp(up, s).normalize());
    if (t < 1) requestAnimationFrame(step);
  };
  step();
}

// ------------------------------------------------------------------ model

const uvKey = (u, v) => `${Math.round(u * 1e4)},${Math.round(v * 1e4)}`;

/** The skinned world position of vertex `i` of `mesh`. */
function worldVertex(mesh, i) {
  const p = new THREE.Vector3();
  mesh.getVertexPosition(i, p);
  return mesh.localToWorld(p);
}

/** The chart of each triangle: the chart texel under its centroid, or
 * failing one there, under points nearer its corners. */
function triangleCharts(geometry, chartPixels, w, h) {
  const uv = geometry.attributes.uv;
  const n = uv.count / 3;
  const ids = new Float32Array(uv.count);
  const at = (u, v) => {
    const x = ((Math.floor(u * w) % w) + w) % w;
    const y = ((Math.floor(v * h) % h) + h) % h;
    const p = (y * w + x) * 4;
    return chartPixels[p] + chartPixels[p + 1] * 256 + chartPixels[p + 2] * 65536;
  };
  for (let t = 0; t < n; t++) {
    const c = [0, 1, 2].map((k) => [uv.getX(3 * t + k), uv.getY(3 * t + k)]);
    const m = [(c[0][0] + c[1][0] + c[2][0]) / 3, (c[0][1] + c[1][1] + c[2][1]) / 3];
    let id = at(m[0], m[1]);
    for (const s of [0.5, 0.8]) {
      for (let k = 0; k < 3 && id === 0; k++) {
        id = at(m[0] + s * (c[k][0] - m[0]), m[1] + s * (c[k][1] - m[1]));
      }
    }
    ids.fill(id, 3 * t, 3 * t + 3);
  }
  return ids;
}

/** Every half-edge of the meshes by its UV endpoints. */
function indexEdges(meshes) {
  const byUv = new Map();
  for (const mesh of meshes) {
    const uv = mesh.geometry.attributes.uv;
    for (let t = 0; t < uv.count / 3; t++) {
      for (let k = 0; k < 3; k++) {
        const i = 3 * t + k, j = 3 * t + ((k + 1) % 3);
        const key = uvKey(uv.getX(i), uv.getY(i)) + '|' + uvKey(uv.getX(j), uv.getY(j));
        if (!byUv.has(key)) byUv.set(key, []);
        byUv.get(key).push({ mesh, i, j, t });
      }
    }
  }
  return byUv;
}

/** Every half-edge with these UV endpoints: mirrored halves of a model
 * share UVs, so there may be several. */
function findHalves(byUv, h) {
  const ka = uvKey(h[0][0], h[0][1]), kb = uvKey(h[1][0], h[1][1]);
  return [...(byUv.get(ka + '|' + kb) || []), ...(byUv.get(kb + '|' + ka) || [])];
}

function faceNormal(mesh, t) {
  const [a, b, c] = [0, 1, 2].map((k) => worldVertex(mesh, 3 * t + k));
  return new THREE.Vector3().crossVectors(b.sub(a), c.sub(a)).normalize();
}

/** A seam edge placed on the model: its 3D endpoints and the surface
 * normal, from the two triangles that meet along it (of the copies of each
 * half-edge, the two that share their 3D endpoints). */
function placeSeam(byUv, edge, texSize) {
  const as = findHalves(byUv, edge.a), bs = findHalves(byUv, edge.b);
  let best = null;
  for (const ha of as) {
    const p0 = worldVertex(ha.mesh, ha.i), p1 = worldVertex(ha.mesh, ha.j);
    for (const hb of bs) {
      const q0 = worldVertex(hb.mesh, hb.i), q1 = worldVertex(hb.mesh, hb.j);
      const gap = Math.min(p0.distanceTo(q0) + p1.distanceTo(q1), p0.distanceTo(q1) + p1.distanceTo(q0));
      if (!best || gap < best.gap) best = { gap, ha, hb, p0, p1 };
    }
  }
  if (!best) return null;
  const { ha, hb, p0, p1 } = best;
  const normal = faceNormal(ha.mesh, ha.t).add(faceNormal(hb.mesh, hb.t)).normalize();
  const texels = Math.hypot((edge.a[1][0] - edge.a[0][0]) * texSize[0], (edge.a[1][1] - edge.a[0][1]) * texSize[1]);
  return { p0, p1, normal, worldPerTexel: p0.distanceTo(p1) / Math.max(texels, 1e-6) };
}

/** The camera that looks at the seam's middle along its normal, the seam
 * upright on the screen, at PIXELS_PER_TEXEL. */
function seamView(s) {
  const mid = s.p0.clone().add(s.p1).multiplyScalar(0.5);
  const tan = Math.tan(THREE.MathUtils.degToRad(camera.fov / 2));
  const distance = (s.worldPerTexel * height) / (2 * tan * PIXELS_PER_TEXEL);
  const up = s.p1.clone().sub(s.p0).normalize();
  return [mid.clone().addScaledVector(s.normal, distance), mid, up];
}

function project(p) {
  const v = p.clone().project(camera);
  return [(v.x + 1) / 2 * width, (1 - v.y) / 2 * height];
}

// ------------------------------------------------------------------ page

function table(rows, head) {
  const t = document.createElement('table');
  const tr = document.createElement('tr');
  for (const h of head) {
    const th = document.createElement('th');
    th.textContent = h;
    tr.append(th);
  }
  t.append(tr);
  for (const r of rows) {
    const row = document.createElement('tr');
    r.forEach((v, i) => {
      const td = document.createElement('td');
      td.textContent = typeof v === 'number' ? v.toFixed(2) : v == null ? '–' : v;
      if (i > 0) td.className = 'num';
      row.append(td);
    });
    t.append(row);
  }
  return t;
}

/** The report's figures, per version and per decoder. */
function showFigures(report) {
  const box = document.getElementById('figures');
  for (const tex of report.textures) {
    const h = document.createElement('h3');
    h.textContent = `${tex.name} ${tex.width}×${tex.height}: ${tex.seams.closed.edges} seams closed, ${tex.seams.left.edges} left, ${tex.seams.spared} spared`;
    box.append(h);
    const versions = [['input', tex.input], ['erased', tex.erased], ['regular BC1', tex.bc1],
      ['seam-aware BC1', tex.bc1_seam_aware], ['regular BC7', tex.bc7], ['seam-aware BC7', tex.bc7_seam_aware]]
      .filter(([, m]) => m);
    box.append(table(versions.map(([n, m]) => [n, m.seam_rms, m.seam_rms_closed, m.psnr]),
      ['version', 'seam RMS', 'closed seams', 'PSNR dB']));
    for (const [n, m] of versions) {
      if (!m.decoders) continue;
      const p = document.createElement('p');
      p.textContent = `${n}, per decoder`;
      box.append(p, table(Object.entries(m.decoders).map(([d, f]) => [d, f.seam_rms, f.seam_rms_closed, f.psnr, f.encoding_psnr]),
        ['decoder', 'seam RMS', 'closed seams', 'PSNR dB', 'vs erased dB']));
    }
  }
}

function showLegend() {
  const box = document.getElementById('legend');
  for (const [name, hue] of Object.entries(HUES)) {
    const s = document.createElement('span');
    s.className = 'swatch';
    s.style.background = '#' + hue.toString(16).padStart(6, '0');
    box.append(s, name + ' ');
  }
}

const POLL_MS = 1000;

/** The job once it has finished, its progress shown while it runs; and
 * the states it was seen in on the way. */
async function finishedJob() {
  const seen = [];
  for (;;) {
    const asked = performance.now();
    const job = await getJson(jobUrl);
    if (seen[seen.length - 1] !== job.state) seen.push(job.state);
    document.getElementById('title').textContent = `${job.input ? job.input.name : 'job'} (${job.state})`;
    if (job.state !== 'queued' && job.state !== 'running') return { job, seen, asked };
    const p = job.progress || { stage: job.state, fraction: 0 };
    say(`The job is ${job.state}: ${p.stage}, ${(p.fraction * 100).toFixed(0)}%. The model loads when it has finished.`);
    await new Promise((r) => setTimeout(r, POLL_MS));
  }
}

async function main() {
  const { job, seen, asked } = await finishedJob();
  // The load is timed from the page's start, or for a job that was still
  // running, from the request that found it finished.
  const ready = seen.length > 1 ? asked : started;
  if (job.state !== 'succeeded' || !job.report) {
    const why = job.error && job.error.message ? `: ${job.error.message}` : '';
    say(`The job is ${job.state}${why}. Nothing to show.`);
    return { failed: job.state, seen };
  }
  const report = job.report;
  showFigures(report);
  showLegend();
  const names = new Set(job.files.map((f) => f.name));
  const model = job.files.map((f) => f.name).find((n) => /\.(gltf|glb)$/i.test(n));
  if (!model) throw new Error('the job has no model file');

  // Every file the model names comes from the job's file route.
  const urls = new Map();
  await Promise.all([...names].filter((n) => /\.(bin|png|jpe?g|dds|ktx2)$/i.test(n) && !/\.(charts|seams|input|regular)\./.test(n))
    .map(async (n) => urls.set(n, await fileUrl(n))));
  const manager = new THREE.LoadingManager();
  manager.setURLModifier((url) => {
    const name = decodeURIComponent(url.replace(/^job\//, ''));
    return urls.get(name) || url;
  });
  const gltfBytes = await (await fileBlob(model)).arrayBuffer();
  const gltf = await new GLTFLoader(manager).parseAsync(gltfBytes, 'job/');
  scene.add(gltf.scene);
  gltf.scene.updateMatrixWorld(true);
  const json = gltf.parser.json;

  // The report's texture of each mesh: the image its base colour samples
  // (the rewrite keeps the input's image indices).
  const meshes = [];
  gltf.scene.traverse((o) => {
    if (!o.isMesh) return;
    const assoc = gltf.parser.associations.get(o.material);
    const mat = assoc && assoc.materials != null ? json.materials[assoc.materials] : null;
    const ref = mat && mat.pbrMetallicRoughness && mat.pbrMetallicRoughness.baseColorTexture;
    const image = ref ? json.textures[ref.index].source : null;
    const tex = report.textures.find((t) => t.image === image);
    if (tex) meshes.push({ mesh: o, tex });
  });
  if (updateSkeletons(gltf.scene)) gltf.scene.updateMatrixWorld(true);

  const sets = new Map();
  const missing = new Set();
  for (const tex of report.textures) {
    const f = tex.files;
    const set = { size: [tex.width, tex.height], textures: {} };
    const get = async (name) => (name && names.has(name) ? fileBlob(name) : null);
    const [input, erased, regular, shipped, charts, edges] = await Promise.all(
      [f.input, f.erased, f.regular, f.dds, f.charts, f.edges].map(get));
    if (input) set.textures.input = imageTexture(await loadImage(URL.createObjectURL(input)));
    set.textures.erased = imageTexture(await loadImage(URL.createObjectURL(erased)));
    if (regular) set.textures.regular = ddsTexture(await regular.arrayBuffer(), gpuS3tc);
    if (shipped) set.textures.seam_aware = ddsTexture(await shipped.arrayBuffer(), gpuS3tc);
    if (charts && input) {
      const img = await loadImage(URL.createObjectURL(charts));
      const c = document.createElement('canvas');
      c.width = img.width;
      c.height = img.height;
      const ctx = c.getContext('2d', { willReadFrequently: true });
      ctx.drawImage(img, 0, 0);
      set.chartPixels = ctx.getImageData(0, 0, img.width, img.height).data;
      set.charts = imageTexture(img, true);
      set.textures.discard = set.textures.input;
    }
    set.edges = edges ? JSON.parse(await edges.text()).edges : [];
    for (const [m] of MODES) if (!set.textures[m]) missing.add(m);
    sets.set(tex.image, set);
  }

  // Each mesh gets its own triangles (for the flat chart attribute) and
  // the shader that samples the chosen version.
  const materials = [];
  for (const { mesh, tex } of meshes) {
    const set = sets.get(tex.image);
    const g = mesh.geometry.index ? mesh.geometry.toNonIndexed() : mesh.geometry;
    const ids = set.chartPixels ? triangleCharts(g, set.chartPixels, tex.width, tex.height)
      : new Float32Array(g.attributes.position.count);
    g.setAttribute('chartId', new THREE.BufferAttribute(ids, 1));
    mesh.geometry = g;
    const material = new THREE.ShaderMaterial({
      vertexShader: VERTEX,
      fragmentShader: FRAGMENT,
      uniforms: {
        map: { value: set.textures.erased },
        inputMap: { value: set.textures.input || set.textures.erased },
        charts: { value: set.charts || set.textures.erased },
        mode: { value: 0 },
        size: { value: new THREE.Vector2(tex.width, tex.height) },
      },
      side: THREE.DoubleSide,
      polygonOffset: true,
      polygonOffsetFactor: 1,
      polygonOffsetUnits: 1,
    });
    mesh.material = material;
    mesh.frustumCulled = false;
    materials.push({ material, set });
  }

  // Seam lines, and the seams to visit: the worst closed first (by their
  // input residual), then those left apart. Each is also found by its
  // texture and its place in that texture's edges.json, for an address
  // that names one seam (#seam=N, #texture=I).
  const linePos = [], lineCol = [];
  const stops = [];
  const bySeam = new Map();
  report.textures.forEach((tex, ti) => {
    const set = sets.get(tex.image);
    const own = meshes.filter((m) => m.tex === tex).map((m) => m.mesh);
    if (!own.length) return;
    const byUv = indexEdges(own);
    const placed = new Map();
    set.edges.forEach((e, index) => {
      const key = JSON.stringify([e.a, e.b]);
      if (placed.has(key)) {
        bySeam.set(`${ti}:${index}`, placed.get(key));
        return;
      }
      const s = placeSeam(byUv, e, set.size);
      if (!s) return;
      const hue = new THREE.Color(HUES[e.closed ? 'closed' : e.spared ? 'spared' : 'left']);
      const lift = s.normal.clone().multiplyScalar(s.worldPerTexel * 0.05);
      linePos.push(...s.p0.clone().add(lift).toArray(), ...s.p1.clone().add(lift).toArray());
      lineCol.push(...hue.toArray(), ...hue.toArray());
      const stop = { edge: e, seam: s, texture: ti, index };
      placed.set(key, stop);
      bySeam.set(`${ti}:${index}`, stop);
      stops.push(stop);
    });
  });
  stops.sort((x, y) => (y.edge.closed - x.edge.closed) || (y.edge.residual[0] - x.edge.residual[0]));
  const lineGeo = new THREE.BufferGeometry();
  lineGeo.setAttribute('position', new THREE.Float32BufferAttribute(linePos, 3));
  lineGeo.setAttribute('color', new THREE.Float32BufferAttribute(lineCol, 3));
  const lines = new THREE.LineSegments(lineGeo, new THREE.LineBasicMaterial({ vertexColors: true }));
  lines.frustumCulled = false;
  scene.add(lines);

  // The whole model in view.
  const box = new THREE.Box3();
  for (const { mesh } of meshes) {
    for (let i = 0; i < mesh.geometry.attributes.position.count; i += 3) box.expandByPoint(worldVertex(mesh, i));
  }
  if (box.isEmpty()) box.setFromObject(gltf.scene);
  const centre = box.getCenter(new THREE.Vector3());
  const radius = box.getSize(new THREE.Vector3()).length() / 2 || 1;
  const dist = radius / Math.tan(THREE.MathUtils.degToRad(camera.fov / 2));
  place(centre.clone().add(new THREE.Vector3(0, 0, dist)), centre, new THREE.Vector3(0, 1, 0));

  // The switch.
  let mode = 'seam_aware';
  const setMode = (m) => {
    mode = m;
    for (const { material, set } of materials) {
      const t = set.textures[m] || set.textures.erased;
      material.uniforms.map.value = t;
      material.uniforms.mode.value = m === 'discard' ? 1 : 0;
    }
    const box = document.querySelector(`#modes input[value="${m}"]`);
    if (box) box.checked = true;
    render();
  };
  const modes = document.getElementById('modes');
  for (const [m, label] of MODES) {
    const l = document.createElement('label');
    const r = document.createElement('input');
    r.type = 'radio';
    r.name = 'mode';
    r.value = m;
    r.disabled = missing.has(m);
    r.onchange = () => setMode(m);
    l.append(r, ' ' + label);
    if (missing.has(m)) {
      l.className = 'missing';
      l.title = m === 'regular' || m === 'input' || m === 'discard'
        ? 'not written: run the job with keep_regular (and pictures for the chart IDs)'
        : 'not written by this job';
    }
    modes.append(l);
  }
  if (missing.has(mode)) mode = 'erased';
  setMode(mode);
  document.getElementById('lines').onchange = (e) => { lines.visible = e.target.checked; render(); };

  let next = 0;
  const info = document.getElementById('seam-info');
  const visit = (stop, instant) => {
    const [pos, look, up] = seamView(stop.seam);
    fly(pos, look, up, instant);
    const e = stop.edge;
    const k = stops.indexOf(stop);
    info.textContent = `${k + 1}/${stops.length}: ${e.closed ? 'closed' : e.spared ? 'spared' : 'left'}, ` +
      `jump ${e.jump.toFixed(1)}; residual input ${e.residual[0].toFixed(1)}, regular ${e.residual[2].toFixed(1)}, seam-aware ${e.residual[3].toFixed(1)} levels`;
    next = k + 1;
    return stop;
  };
  const goTo = (k, instant) => (stops.length ? visit(stops[k % stops.length], instant) : null);
  /** Edge `index` of texture `ti`'s edges.json, if it lies on the model. */
  const goToSeam = (ti, index, instant) => {
    const stop = bySeam.get(`${ti}:${index}`);
    return stop ? visit(stop, instant) : null;
  };
  document.getElementById('next').onclick = () => goTo(next, false);

  const decoding = gpuS3tc ? 'DDS decoded by the GPU (WEBGL_compressed_texture_s3tc)'
    : 'DDS decoded in the page with the ideal palette: this browser offers no S3TC';
  say(`${decoding}. Drag to turn, wheel to zoom.`);
  if (params.has('seam')) {
    const ti = Number(params.get('texture')) || 0;
    if (!goToSeam(ti, Number(params.get('seam')), true)) say(`No seam ${params.get('seam')} of texture ${ti} on the model.`);
  }
  renderer.render(scene, camera);
  const loadMs = performance.now() - ready;
  const waitedMs = ready - started;
  return { setMode, goTo, goToSeam, lines, stops, missing, loadMs, waitedMs, seen };
}

/** Skinned meshes need their bones' matrices before a vertex is placed. */
function updateSkeletons(root) {
  let any = false;
  root.traverse((o) => {
    if (o.isSkinnedMesh) {
      o.skeleton.update();
      any = true;
    }
  });
  return any;
}

/** With #probe: for each version, a screenshot and where the seam lies on
 * it, written into <pre id="result"> for a test. The camera is on the seam
 * #seam names, or on stop K of "next seam" (#probe=K), or, with
 * #probe=overview, where the page opened it, on the whole model. */
function probe(view, which) {
  let stop = null;
  if (which !== 'overview') {
    stop = params.has('seam')
      ? view.goToSeam(Number(params.get('texture')) || 0, Number(params.get('seam')), true)
      : view.goTo(Number(which) || 0, true);
    if (!stop) throw new Error('no such seam on the model');
  }
  view.lines.visible = false;
  const shots = {};
  const samples = 64;
  for (const [m] of MODES) {
    if (view.missing.has(m)) continue;
    view.setMode(m);
    renderer.render(scene, camera);
    dirty = false;
    const line = [];
    for (let i = 0; stop && i <= samples; i++) {
      line.push(project(stop.seam.p0.clone().lerp(stop.seam.p1, i / samples)));
    }
    shots[m] = { png: renderer.domElement.toDataURL('image/png'), line };
  }
  return stop ? { stop: view.stops.indexOf(stop), texture: stop.texture, index: stop.index, edge: stop.edge, shots } : { shots };
}

// What a driving browser reads once the page has rendered (or failed): a
// JSON string, also written into <pre id="result">.
window.seamstressResult = main().then((view) => {
  const ok = !!(view && view.setMode);
  const out = {
    ok, s3tc: gpuS3tc, errors, seen: view ? view.seen : [],
    load_ms: ok ? view.loadMs : null, waited_ms: ok ? view.waitedMs : null,
  };
  if (ok && params.has('probe')) Object.assign(out, probe(view, params.get('probe')));
  requestAnimationFrame(frame);
  return out;
}).catch((e) => {
  say(String(e));
  errors.push(String(e && e.stack || e));
  return { ok: false, errors };
}).then((out) => {
  const text = JSON.stringify(out);
  document.getElementById('result').textContent = text;
  return text;
});
