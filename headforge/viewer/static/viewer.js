// headforge's browser viewer: one scene (scene.json, written by headforge.viewer.scene) shown with
// three.js. World = the OpenGL frame of the clip's camera (metres, y up, the camera at the origin
// looking down -z). The first view is the clip's camera (its intrinsics K); the orbit turns about
// the head. window.viewer is the page's state and a small API for tests and benchmarks.
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';

const query = new URLSearchParams(location.search);
const $ = (id) => document.getElementById(id);
const viewer = (window.viewer = { ready: false, error: null });
window.addEventListener('error', (e) => fail(e.message));
window.addEventListener('unhandledrejection', (e) => fail(String(e.reason)));

function fail(message) {
  viewer.error = message;
  $('status').textContent = 'error: ' + message;
}

function slider(parent, id, label, min, max, value, onInput) {
  const row = document.createElement('div');
  row.className = 'row';
  row.innerHTML = `<label for="${id}" title="${label}">${label}</label>` +
    `<input id="${id}" type="range" min="${min}" max="${max}" step="0.01" value="${value}"><output>${(+value).toFixed(2)}</output>`;
  parent.appendChild(row);
  const input = row.querySelector('input');
  const out = row.querySelector('output');
  input.addEventListener('input', () => { out.textContent = (+input.value).toFixed(2); onInput(+input.value); });
  return { input, set(v) { input.value = v; out.textContent = (+v).toFixed(2); } };
}

// ---- scene, renderer, camera ---------------------------------------------------------------
const scene = await (await fetch('scene.json')).json();
$('title').textContent = scene.title;
document.title = 'headforge — ' + scene.title;
const size = query.get('size') ? Number(query.get('size')) : Math.max(256, Math.min(innerHeight, innerWidth - 300));
const canvas = $('view');
const renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
renderer.setPixelRatio(query.get('size') ? 1 : devicePixelRatio);
renderer.setSize(size, size);
renderer.outputColorSpace = THREE.SRGBColorSpace;
renderer.setClearColor(query.get('bg') || '#ffffff', 1);
const world = new THREE.Scene();
const camera = new THREE.PerspectiveCamera(25, 1, 0.01, 100);
world.add(new THREE.AmbientLight(0xffffff, 0.6));
const sun = new THREE.DirectionalLight(0xffffff, 2.2);
world.add(sun, sun.target);
const lightDir = new THREE.Vector3(0, 0, 1);

function useIntrinsics(K, width, height) {
  // OpenCV pinhole (pixel centres at integers) -> an OpenGL projection of the same pixels
  const n = 0.01, f = 100;
  const P = new THREE.Matrix4().set(
    2 * K[0][0] / width, 0, 1 - (2 * K[0][2] + 1) / width, 0,
    0, 2 * K[1][1] / height, (2 * K[1][2] + 1) / height - 1, 0,
    0, 0, -(f + n) / (f - n), -2 * f * n / (f - n),
    0, 0, -1, 0);
  camera.projectionMatrix.copy(P);
  camera.projectionMatrixInverse.copy(P).invert();
  camera.updateProjectionMatrix = () => {};  // keep K whatever the controls do
}

const controls = new OrbitControls(camera, canvas);
controls.enableDamping = false;

let mixer = null, action = null, mesh = null, points = null;
const manual = { morph: new Map(), joints: new Map() };
const bones = {};
let playing = true;
const duration = scene.frames > 0 ? scene.frames / scene.fps : 0;

// ---- content ----------------------------------------------------------------------------------
if (scene.kind === 'mesh') {
  const gltf = await new GLTFLoader().loadAsync(scene.files.glb);
  world.add(gltf.scene);
  gltf.scene.traverse((o) => { if (o.isMesh && !mesh) mesh = o; });
  for (const name of ['root', 'neck', 'jaw', 'eye_left', 'eye_right']) bones[name] = gltf.scene.getObjectByName(name);
  viewer.gltf = { meshes: 0, skins: gltf.parser.json.skins ? gltf.parser.json.skins.length : 0,
    morphTargets: mesh.morphTargetInfluences ? mesh.morphTargetInfluences.length : 0,
    animations: gltf.animations.length, targetNames: Object.keys(mesh.morphTargetDictionary || {}) };
  gltf.scene.traverse((o) => { if (o.isMesh) viewer.gltf.meshes += 1; });
  if (gltf.animations.length) {
    mixer = new THREE.AnimationMixer(gltf.scene);
    action = mixer.clipAction(gltf.animations[0]);
    action.play();
  }
} else if (scene.kind === 'points') {
  const buf = await (await fetch(scene.files.points)).arrayBuffer();
  const T = scene.frames, N = scene.points, block = T * N * 3;
  const positions = new Float32Array(buf, 0, block);
  const normals = new Float32Array(buf, block * 4, block);
  const albedo = new Uint8Array(buf, block * 8, N * 3);
  const radius = new Float32Array(buf, Math.ceil((block * 8 + N * 3) / 4) * 4, N);
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute('position', new THREE.BufferAttribute(positions.slice(0, N * 3), 3));
  geometry.setAttribute('normal', new THREE.BufferAttribute(normals.slice(0, N * 3), 3));
  geometry.setAttribute('color', new THREE.BufferAttribute(albedo, 3, true));
  geometry.setAttribute('radius', new THREE.BufferAttribute(radius, 1));
  const material = new THREE.ShaderMaterial({
    uniforms: { lightDir: { value: lightDir }, scale: { value: size / 2 }, lambert: { value: 1.0 } },
    vertexShader: `
      attribute float radius; uniform float scale; varying vec3 vColor; varying vec3 vNormal;
      void main() {
        vec4 mv = modelViewMatrix * vec4(position, 1.0);
        gl_Position = projectionMatrix * mv;
        gl_PointSize = max(1.0, 2.0 * radius * projectionMatrix[1][1] * scale / -mv.z);
        vColor = color; vNormal = normal;
      }`,
    fragmentShader: `
      uniform vec3 lightDir; uniform float lambert; varying vec3 vColor; varying vec3 vNormal;
      void main() {
        vec2 c = gl_PointCoord * 2.0 - 1.0;
        if (dot(c, c) > 1.0) discard;
        float shade = 0.35 + 0.65 * max(dot(normalize(vNormal), normalize(lightDir)), 0.0);
        gl_FragColor = vec4(vColor * mix(1.0, shade, lambert), 1.0);
      }`,
    vertexColors: true,
  });
  points = new THREE.Points(geometry, material);
  points.frustumCulled = false;
  world.add(points);
  points.userData = { positions, normals, N };
}

// ---- camera placement: the clip's camera, orbiting the head -------------------------------------
function headBox() {
  const box = new THREE.Box3();
  if (mesh) box.expandByObject(mesh, true);
  if (points) { points.geometry.computeBoundingBox(); box.union(points.geometry.boundingBox); }
  return box;
}

function showTime(t) {
  if (mixer) { action.time = t; mixer.update(0); }
  if (points && scene.frames > 0) {
    const { positions, normals, N } = points.userData;
    const f = Math.min(scene.frames - 1, Math.max(0, Math.round(t * scene.fps)));
    const posed = points.userData.posed;  // the sliders' pose of this frame, from the server
    const use = posed && posed.frame === f && !playing;
    points.geometry.attributes.position.array.set(use ? posed.positions : positions.subarray(f * N * 3, (f + 1) * N * 3));
    points.geometry.attributes.normal.array.set(use ? posed.normals : normals.subarray(f * N * 3, (f + 1) * N * 3));
    points.geometry.attributes.position.needsUpdate = true;
    points.geometry.attributes.normal.needsUpdate = true;
  }
}

showTime(0);
world.updateMatrixWorld(true);
const centre = headBox().getCenter(new THREE.Vector3());
if (scene.K) {
  useIntrinsics(scene.K, scene.resolution, scene.resolution);
  camera.position.set(0, 0, 0);
  controls.target.set(0, 0, centre.z);  // straight ahead: the first view is the clip's camera exactly
} else {
  const extent = headBox().getSize(new THREE.Vector3()).length();
  camera.position.copy(centre).add(new THREE.Vector3(0, 0, 2.2 * extent));
  controls.target.copy(centre);
}
controls.update();

// ---- controls -------------------------------------------------------------------------------------
const frameInput = $('frame');
frameInput.max = Math.max(0, scene.frames - 1);
let time = 0;

function setPlaying(on) {
  playing = on && scene.frames > 1;
  $('play').textContent = playing ? 'pause' : 'play';
  if (playing) { manual.morph.clear(); manual.joints.clear(); if (points) points.userData.posed = null; }
}
$('play').addEventListener('click', () => setPlaying(!playing));
frameInput.addEventListener('input', () => {
  setPlaying(false); time = +frameInput.value / scene.fps;
  if (manual.morph.size || manual.joints.size) requestPose();
});

// point avatars: the server poses the points for the sliders (PointPoser); one request at a time
const posable = !!(points && scene.files.pose);
let poseBusy = false, posePending = false;
async function requestPose() {
  if (!posable) return;
  if (poseBusy) { posePending = true; return; }
  poseBusy = true;
  try {
    const f = Math.round(time * scene.fps);
    const q = new URLSearchParams({ frame: String(f) });
    q.set('expression', [...manual.morph].map(([i, v]) => i + ':' + v).join(','));
    for (const joint of ['jaw', 'neck', 'eyes']) {
      if ([...manual.joints.keys()].some((k) => k.startsWith(joint + '.'))) {
        q.set(joint, ['x', 'y', 'z'].map((a) => manual.joints.get(joint + '.' + a) || 0).join(','));
      }
    }
    const answer = await fetch(scene.files.pose + '?' + q);
    if (!answer.ok) throw new Error('pose: ' + answer.status + ' ' + answer.statusText);
    const buf = await answer.arrayBuffer();
    const N = scene.points;
    points.userData.posed = { frame: f, positions: new Float32Array(buf, 0, N * 3), normals: new Float32Array(buf, N * 12, N * 3) };
    viewer.poses = (viewer.poses || 0) + 1;
  } finally {
    poseBusy = false;
  }
  if (posePending) { posePending = false; requestPose(); }
}

const expressionSliders = new Map();
const expressionNames = mesh && mesh.morphTargetDictionary ? Object.entries(mesh.morphTargetDictionary)
  : posable ? scene.expressions.map((name, i) => [name, i]) : [];
for (const [name, index] of expressionNames) {
  expressionSliders.set(index, slider($('expression-panel'), 'expr-' + name, name, -1, 1, 0, (v) => {
    setPlaying(false); manual.morph.set(index, v); requestPose();
  }));
}
if (!expressionNames.length) $('expression-panel').innerHTML += '<p>This scene has no expressions.</p>';
const jointSliders = new Map();
const JOINT_CONTROLS = [['jaw', 'x', 'jaw open', -0.1, 0.6], ['neck', 'x', 'neck pitch', -0.8, 0.8],
  ['neck', 'y', 'neck yaw', -1.0, 1.0], ['neck', 'z', 'neck roll', -0.6, 0.6],
  ['eyes', 'y', 'eyes yaw', -0.6, 0.6], ['eyes', 'x', 'eyes pitch', -0.5, 0.5]];
if (bones.jaw || posable) {
  for (const [joint, axis, label, min, max] of JOINT_CONTROLS) {
    const key = joint + '.' + axis;
    jointSliders.set(key, slider($('joint-panel'), 'joint-' + joint + '-' + axis, label, min, max, 0, (v) => {
      setPlaying(false); manual.joints.set(key, v); requestPose();
    }));
  }
} else {
  $('joint-panel').style.display = 'none';
}
const light = { azimuth: 0, elevation: 0.3 };
function aimLight() {
  lightDir.set(Math.sin(light.azimuth) * Math.cos(light.elevation), Math.sin(light.elevation),
    Math.cos(light.azimuth) * Math.cos(light.elevation));
  const c = controls.target;
  sun.position.copy(c).addScaledVector(lightDir, 1.0);
  sun.target.position.copy(c);
}
slider($('light-panel'), 'light-azimuth', 'azimuth', -3.14, 3.14, light.azimuth, (v) => { light.azimuth = v; aimLight(); });
slider($('light-panel'), 'light-elevation', 'elevation', -1.5, 1.5, light.elevation, (v) => { light.elevation = v; aimLight(); });
if (points) {
  const row = document.createElement('div');
  row.className = 'row';
  row.innerHTML = '<label for="lambert">Lambert on albedo</label><input id="lambert" type="checkbox" checked>';
  $('light-panel').appendChild(row);
  row.querySelector('input').addEventListener('change', (e) => { points.material.uniforms.lambert.value = e.target.checked ? 1 : 0; });
}
if (!scene.relightable && !(mesh && !mesh.material.isMeshBasicMaterial)) $('light-panel').style.display = 'none';
aimLight();

function applyManual() {
  if (mesh && mesh.morphTargetInfluences) for (const [i, v] of manual.morph) mesh.morphTargetInfluences[i] = v;
  const euler = {};
  for (const [key, v] of manual.joints) {
    const [joint, axis] = key.split('.');
    (euler[joint] = euler[joint] || { x: 0, y: 0, z: 0 })[axis] = v;
  }
  for (const [joint, e] of Object.entries(euler)) {
    const q = new THREE.Quaternion().setFromEuler(new THREE.Euler(e.x, e.y, e.z, 'YXZ'));
    for (const b of joint === 'eyes' ? [bones.eye_left, bones.eye_right] : [bones[joint]]) if (b) b.quaternion.copy(q);
  }
}

function syncSliders() {
  if (mesh && mesh.morphTargetInfluences) {
    for (const [i, s] of expressionSliders) if (!manual.morph.has(i)) s.set(mesh.morphTargetInfluences[i]);
  }
  for (const [key, s] of jointSliders) {
    if (manual.joints.has(key)) continue;
    const [joint, axis] = key.split('.');
    const b = joint === 'eyes' ? bones.eye_left : bones[joint];
    if (b) s.set(new THREE.Euler().setFromQuaternion(b.quaternion, 'YXZ')[axis]);
  }
  frameInput.value = Math.round(time * scene.fps);
  $('frame-out').textContent = frameInput.value;
}

function draw() {
  showTime(time);
  applyManual();
  renderer.render(world, camera);
}

// ---- loop and API -----------------------------------------------------------------------------------
let last = performance.now();
let frameCount = 0;
renderer.setAnimationLoop(() => {
  const now = performance.now();
  const dt = (now - last) / 1000;
  last = now;
  if (playing && duration > 0) time = (time + dt) % duration;
  draw();
  if (frameCount++ % 6 === 0) syncSliders();
});

Object.assign(viewer, {
  scene,
  // show frame f of the driving sequence, paused, as the clip's camera sees it; drawn at once
  showFrame(f) {
    setPlaying(false);
    manual.morph.clear(); manual.joints.clear();
    camera.position.set(0, 0, 0); controls.target.set(0, 0, centre.z); controls.update();
    time = f / scene.fps;
    draw();
  },
  setPlaying,
  draw,
  // the clear colour (a CSS colour): two backgrounds tell the drawn pixels' coverage apart
  background(colour) { renderer.setClearColor(colour, 1); draw(); },
});
setPlaying(query.get('play') !== '0');
$('status').textContent = `${scene.kind}, ${scene.frames} frames at ${scene.fps} fps — drag to orbit, scroll to zoom`;
draw();
viewer.ready = true;
