// c4d view: the 4D viewer (a reconstruction or a generated scene over time), three.js.
// Data: the JSON header (#c4d-header) and the base64 payload (#c4d-payload) written by
// c4d/view/scene_data.py; coordinates are world minus header.centre, OpenCV camera axes.
// When drawn, <html data-c4d-state> becomes "ready" ("error" on failure) and window.c4dView
// exposes stats (what is drawn now), setFrame(t), play(), pause() and frustums() (where the
// camera frustums are drawn; read-only).
import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';

const root = document.documentElement;
const COLORS = { moving: 0xe53935, trackMoving: 0xff9800, trackStatic: 0x29b6f6, camera: 0xd0d0d0,
                 current: 0xffd54f, truth: 0x43d17a, background: 0x15181d };

function fail(error) {
  root.dataset.c4dState = 'error';
  document.title = 'c4d view: error: ' + error.message;
  document.getElementById('status').textContent = 'error: ' + error.message;
  console.error(error);
}

function decodeBase64(text) {
  if (Uint8Array.fromBase64) return Uint8Array.fromBase64(text.trim());
  const raw = atob(text.trim());
  const bytes = new Uint8Array(raw.length);
  for (let i = 0; i < raw.length; i++) bytes[i] = raw.charCodeAt(i);
  return bytes;
}

function ordinal(n) {
  const tail = n % 100 >= 11 && n % 100 <= 13 ? 'th' : ({ 1: 'st', 2: 'nd', 3: 'rd' }[n % 10] || 'th');
  return n + tail;
}

function typedArrays(header, bytes) {
  const types = { float16: Uint16Array, uint8: Uint8Array, float32: Float32Array, uint16: Uint16Array };
  const out = {};
  for (const [name, spec] of Object.entries(header.arrays)) {
    out[name] = new types[spec.type](bytes.buffer, bytes.byteOffset + spec.offset, spec.length);
  }
  return out;
}

// Line segments of camera frustums (apex to the image corners at `depth`, and the image rim).
function frustumPositions(pose, k, size, depth) {
  const [fx, fy, cx, cy] = k, [h, w] = size;
  const corners = [[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]].map(([u, v]) =>
    [(u - cx) / fx * depth, (v - cy) / fy * depth, depth]);
  const world = (p) => [0, 1, 2].map(r => pose[4 * r] * p[0] + pose[4 * r + 1] * p[1] + pose[4 * r + 2] * p[2] + pose[4 * r + 3]);
  const apex = world([0, 0, 0]), rim = corners.map(world), out = [];
  for (let i = 0; i < 4; i++) out.push(...apex, ...rim[i], ...rim[i], ...rim[(i + 1) % 4]);
  return new Float32Array(out);
}

function discTexture() {
  const canvas = document.createElement('canvas');
  canvas.width = canvas.height = 64;
  const context = canvas.getContext('2d');
  context.fillStyle = '#fff';
  context.beginPath();
  context.arc(32, 32, 30, 0, 2 * Math.PI);
  context.fill();
  return new THREE.CanvasTexture(canvas);
}

// All cameras' frustums as one LineSegments (16 vertices each, frustumPositions' order: one draw
// call however long the video) and the trajectory through their centres.
function cameraGroup(cameras, size, depth, color) {
  const group = new THREE.Group();
  const material = new THREE.LineBasicMaterial({ color });
  const positions = new Float32Array(16 * 3 * cameras.cam_to_world.length);
  cameras.cam_to_world.forEach((pose, t) => positions.set(frustumPositions(pose, cameras.intrinsics[t], size, depth), 48 * t));
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute('position', new THREE.BufferAttribute(positions, 3));
  const frustums = new THREE.LineSegments(geometry, material);
  frustums.frustumCulled = false;
  group.add(frustums);
  const path = new THREE.BufferGeometry();
  path.setAttribute('position', new THREE.BufferAttribute(
    new Float32Array(cameras.cam_to_world.flatMap(p => [p[3], p[7], p[11]])), 3));
  const line = new THREE.Line(path, material);
  line.frustumCulled = false;
  group.add(line);
  return group;
}

// Where a group's camera frustums are drawn, in world coordinates (`centre` added back): per
// camera its apex and its image rim's corners (top-left, top-right, bottom-right, bottom-left).
function drawnFrustums(group, centre) {
  const offset = new THREE.Vector3(...centre);
  const frustums = group.children.find(child => child.isLineSegments);
  const position = frustums.geometry.attributes.position;
  const world = (i) => new THREE.Vector3().fromBufferAttribute(position, i)
    .applyMatrix4(frustums.matrixWorld).add(offset).toArray();
  return Array.from({ length: position.count / 16 }, (_, t) =>
    ({ apex: world(16 * t), corners: [1, 5, 9, 13].map(i => world(16 * t + i)) }));  // frustumPositions' order
}

function main() {
  const timing = { start: performance.now() };
  const header = JSON.parse(document.getElementById('c4d-header').textContent);
  const arrays = typedArrays(header, decodeBase64(document.getElementById('c4d-payload').textContent));
  timing.decoded = performance.now();
  const T = header.frames;
  document.getElementById('title').textContent = header.title;
  const notes = document.getElementById('notes');
  const thinned = header.thinned, count = (n) => n.toLocaleString('en-US');
  const thinning = `drawn: every ${header.stride === 1 ? '' : ordinal(header.stride) + ' '}pixel of ` +
    `every ${header.stride === 1 ? '' : ordinal(header.stride) + ' '}row, at most ` +
    `${count(thinned ? thinned.cap : header.max_points)} per frame`;
  // thinned (a long video): how many of how many points, and why (c4d view --max-page-mb)
  const budget = thinned && `thinned for a page under ${thinned.max_page_mb} MB (--max-page-mb): ` +
    `${count(thinned.points)} of ${count(thinned.of)} points drawn`;
  for (const [text, id] of [...header.notes.map(n => [n]), [thinning], ...(budget ? [[budget, 'thinned']] : [])]) {
    const line = document.createElement('div');
    line.className = 'note';
    line.textContent = text;
    if (id) line.id = id;
    notes.appendChild(line);
  }

  THREE.ColorManagement.enabled = false; // frame colours pass through as they are
  const container = document.getElementById('view');
  const renderer = new THREE.WebGLRenderer({ antialias: true });
  renderer.outputColorSpace = THREE.LinearSRGBColorSpace;
  renderer.setPixelRatio(window.devicePixelRatio);
  renderer.setSize(container.clientWidth, container.clientHeight);
  container.appendChild(renderer.domElement);
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(COLORS.background);

  // Points: each frame's static and dynamic points as two geometries on views of the payload,
  // made (and sent to the GPU) when the frame is first shown, so opening a long video is quick.
  const camera = new THREE.PerspectiveCamera(50, container.clientWidth / container.clientHeight, 1e-3, 1e5);
  // three.js scales a point by (canvas height / 2) / depth; a disc one pixel pitch wide.
  const worldSize = header.point_size / Math.tan(THREE.MathUtils.degToRad(camera.fov / 2));
  const disc = discTexture();
  const staticMaterial = new THREE.PointsMaterial({ size: worldSize, vertexColors: true, map: disc, alphaTest: 0.5 });
  const dynamicMaterial = new THREE.PointsMaterial({ size: worldSize, color: COLORS.moving, map: disc, alphaTest: 0.5 });
  const frameGeometries = new Map();
  function pointGeometries(t) {
    if (!frameGeometries.has(t)) {
      const p = header.points, start = p.start[t], ns = p.static[t], nd = p.dynamic[t];
      frameGeometries.set(t, [[start, ns], [start + ns, nd]].map(([first, count]) => {
        const geometry = new THREE.BufferGeometry();
        geometry.setAttribute('position', new THREE.Float16BufferAttribute(
          arrays.positions.subarray(3 * first, 3 * (first + count)), 3));
        geometry.setAttribute('color', new THREE.Uint8BufferAttribute(
          arrays.colors.subarray(3 * first, 3 * (first + count)), 3, true));
        return geometry;
      }));
    }
    return frameGeometries.get(t);
  }
  const cloud = new THREE.Group();
  const parts = [staticMaterial, dynamicMaterial].map(material => {
    const points = new THREE.Points(new THREE.BufferGeometry(), material);
    points.frustumCulled = false;
    cloud.add(points);
    return points;
  });
  scene.add(cloud);

  const size = header.image_size, depth = header.frustum_depth;
  const cameras = cameraGroup(header.cameras, size, depth, COLORS.camera);
  const truth = header.gt_cameras ? cameraGroup(header.gt_cameras, size, depth, COLORS.truth) : null;
  scene.add(cameras);
  if (truth) {
    truth.renderOrder = 1;  // over the estimated cameras where the two coincide
    scene.add(truth);
  }
  const current = new THREE.LineSegments(new THREE.BufferGeometry(), new THREE.LineBasicMaterial({ color: COLORS.current }));
  current.geometry.setAttribute('position', new THREE.BufferAttribute(new Float32Array(16 * 3), 3));
  current.frustumCulled = false;
  scene.add(current);

  // Tracks: one position per track and frame; a segment from t-1 to t where both are valid (all
  // of them ordered by t, so those up to the current frame are a prefix), and the heads at t.
  let tracks = null, heads = null;
  const segmentsUntil = [0], headStart = [], headCount = [];
  if (header.tracks) {
    const n = header.tracks.count, valid = arrays.track_valid, moving = arrays.track_moving;
    const segments = [], headIndex = [];
    for (let t = 0; t < T; t++) {
      for (let i = 0; i < n; i++) {
        if (t > 0 && valid[(t - 1) * n + i] && valid[t * n + i]) segments.push((t - 1) * n + i, t * n + i);
      }
      segmentsUntil.push(segments.length / 2);
      headStart.push(headIndex.length);
      for (let i = 0; i < n; i++) if (valid[t * n + i]) headIndex.push(t * n + i);
      headCount.push(headIndex.length - headStart[t]);
    }
    segmentsUntil.shift();  // segmentsUntil[t]: the segments ending at frame t or before
    const position = new THREE.Float16BufferAttribute(arrays.track_points, 3);
    const rgb = new Uint8Array(moving.length * 3), hot = new THREE.Color(COLORS.trackMoving), cold = new THREE.Color(COLORS.trackStatic);
    moving.forEach((m, i) => { const c = m ? hot : cold; rgb.set([c.r * 255, c.g * 255, c.b * 255], 3 * i); });
    const color = new THREE.Uint8BufferAttribute(rgb, 3, true);
    const lines = new THREE.BufferGeometry(), dots = new THREE.BufferGeometry();
    for (const [geometry, index] of [[lines, segments], [dots, headIndex]]) {
      geometry.setAttribute('position', position);
      geometry.setAttribute('color', color);
      geometry.setIndex(new THREE.BufferAttribute(new Uint32Array(index), 1));
    }
    // drawn over the points (no depth test), so that a track on a moving object stays visible
    tracks = new THREE.LineSegments(lines, new THREE.LineBasicMaterial({ vertexColors: true, depthTest: false }));
    heads = new THREE.Points(dots, new THREE.PointsMaterial({ vertexColors: true, size: 5, sizeAttenuation: false, depthTest: false }));
    for (const object of [tracks, heads]) {
      object.frustumCulled = false;
      object.renderOrder = 1;
      scene.add(object);
    }
  }

  // The virtual camera: behind, above and to the side of the first camera, looking at the
  // centre, so that depth shows; up is the cameras' mean up direction (OpenCV's y points down).
  const poses = header.cameras.cam_to_world;
  const up = new THREE.Vector3(...[1, 5, 9].map(i => -poses.reduce((s, p) => s + p[i], 0))).normalize();
  const first = new THREE.Vector3(poses[0][3], poses[0][7], poses[0][11]);
  const reach = first.length() + depth;
  const side = new THREE.Vector3().crossVectors(first, up).normalize();
  camera.up.copy(up);
  camera.position.copy(first.clone().multiplyScalar(1.3)).addScaledVector(up, 0.5 * reach).addScaledVector(side, 0.5 * reach);
  const controls = new OrbitControls(camera, renderer.domElement);
  controls.target.set(0, 0, 0);
  controls.update();

  const slider = document.getElementById('frame'), label = document.getElementById('frame-label');
  const status = document.getElementById('status'), playButton = document.getElementById('play');
  slider.max = String(T - 1);
  const show = { points: true, movingRed: header.has_dynamic, cameras: true, truth: !!truth, tracks: !!tracks };
  const stats = {};
  let frame = 0, timer = null;

  function render() { renderer.render(scene, camera); }

  function update() {
    [parts[0].geometry, parts[1].geometry] = pointGeometries(frame);
    const [ns, nd] = parts.map(part => part.geometry.attributes.position.count);
    dynamicMaterial.vertexColors = !show.movingRed;
    dynamicMaterial.color.set(show.movingRed ? COLORS.moving : 0xffffff);
    dynamicMaterial.needsUpdate = true;
    cloud.visible = show.points;
    cameras.visible = show.cameras;
    if (truth) truth.visible = show.truth;
    current.visible = show.cameras;
    current.geometry.attributes.position.array.set(
      frustumPositions(poses[frame], header.cameras.intrinsics[frame], size, 1.3 * depth));
    current.geometry.attributes.position.needsUpdate = true;
    const segments = tracks ? segmentsUntil[frame] : 0;
    if (tracks) {
      tracks.geometry.setDrawRange(0, 2 * segments);
      heads.geometry.setDrawRange(headStart[frame], headCount[frame]);
      tracks.visible = heads.visible = show.tracks;
    }
    Object.assign(stats, {
      frame, frames: T,
      points: show.points ? ns + nd : 0,
      staticPoints: show.points ? ns : 0,
      dynamicPoints: show.points ? nd : 0,
      cameras: show.cameras ? header.cameras.cam_to_world.length : 0,
      gtCameras: truth && show.truth ? header.gt_cameras.cam_to_world.length : 0,
      trackSegments: tracks && show.tracks ? segments : 0,
      trackHeads: tracks && show.tracks ? headCount[frame] : 0,
      tracks: header.tracks ? header.tracks.count : 0,
    });
    const time = header.timestamps ? `, t = ${header.timestamps[frame].toFixed(2)}` : '';
    label.textContent = `frame ${frame} of 0-${T - 1}${time}`;  // counted from 0, as --frame
    status.textContent = `${ns + nd} points (${nd} dynamic), ${stats.cameras} cameras` +
      (truth ? `, ${header.gt_cameras.cam_to_world.length} ground truth` : '') +
      (tracks ? `, ${segments} track segments of ${header.tracks.count} tracks` : '');
    render();
  }

  function setFrame(t) {
    frame = Math.max(0, Math.min(T - 1, Math.round(t)));
    slider.value = String(frame);
    update();
    return frame;
  }
  function pause() {
    clearInterval(timer);
    timer = null;
    playButton.textContent = 'Play';
  }
  function play() {
    if (timer) return;
    playButton.textContent = 'Pause';
    timer = setInterval(() => setFrame((frame + 1) % T), 1000 / header.fps);
  }

  const toggles = document.getElementById('toggles');
  const keyed = { movingRed: [COLORS.moving], truth: [COLORS.truth], tracks: [COLORS.trackStatic, COLORS.trackMoving] };
  for (const [key, text, available] of [['points', 'points', true], ['movingRed', 'dynamic in red', header.has_dynamic],
                                        ['cameras', 'cameras', true], ['truth', 'ground truth', !!truth],
                                        ['tracks', '3D tracks (static, moving)', !!tracks]]) {
    if (!available) continue;
    const box = document.createElement('input');
    box.type = 'checkbox';
    box.checked = show[key];
    box.id = 'show-' + key;
    box.addEventListener('change', () => { show[key] = box.checked; update(); });
    const tag = document.createElement('label');  // holds its box: the two wrap together
    tag.appendChild(box);
    for (const value of keyed[key] || []) {
      const swatch = document.createElement('span');
      swatch.className = 'key';
      swatch.style.background = '#' + value.toString(16).padStart(6, '0');
      tag.appendChild(swatch);
    }
    tag.appendChild(document.createTextNode(text));
    toggles.appendChild(tag);
  }
  slider.addEventListener('input', () => { pause(); setFrame(Number(slider.value)); });
  playButton.addEventListener('click', () => (timer ? pause() : play()));
  window.addEventListener('keydown', (event) => {
    if (event.target instanceof HTMLInputElement && event.target.type === 'range') return;
    if (event.key === ' ') { event.preventDefault(); timer ? pause() : play(); }
    if (event.key === 'ArrowRight') { pause(); setFrame((frame + 1) % T); }
    if (event.key === 'ArrowLeft') { pause(); setFrame((frame + T - 1) % T); }
  });
  controls.addEventListener('change', render);
  window.addEventListener('resize', () => {
    camera.aspect = container.clientWidth / container.clientHeight;
    camera.updateProjectionMatrix();
    renderer.setSize(container.clientWidth, container.clientHeight);
    render();
  });

  const frustums = () => ({ cameras: drawnFrustums(cameras, header.centre),
                            truth: truth ? drawnFrustums(truth, header.centre) : [] });
  window.c4dView = { stats, setFrame, play, pause, frustums, header, timing };
  setFrame(0);
  timing.drawn = performance.now();
  root.dataset.c4dState = 'ready';
  document.title = header.title;
}

try {
  main();
} catch (error) {
  fail(error);
}
