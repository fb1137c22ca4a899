// minimdm's 3D skeleton player: an ES module on three.js (MIT, part of minimdm).
//
// mount(container, payload) draws the motions of a payload built by minimdm.viz.payload:
// bones as capsules (a cylinder between a joint and its parent, a sphere on each joint), a
// ground grid with shadows, each character's root path on the ground, foot-contact discs,
// targets (a sphere above a ring), target paths (dashed) and keyframes (ghost poses). Controls:
// drag to orbit, right-drag (or shift-drag) to pan, wheel or pinch to zoom (once the player has
// been clicked, so that the page still scrolls), double-click to reset the view; play/pause,
// a frame slider, a speed menu and a follow-camera box. Keys: space plays, arrows step.
//
// Payload coordinates are minimdm's z-up world in metres; three.js is y-up, so a point (x, y, z)
// is drawn at (x, z, -y), a proper rotation (no mirror).
import * as THREE from "three";

const VERSION = 1;
const Q = 32767;
const SPEEDS = [0.1, 0.25, 0.5, 1, 2];

// ------------------------------------------------------------------ payload decoding

function bytesOf(b64) {
  const s = atob(b64);
  const out = new Uint8Array(s.length);
  for (let i = 0; i < s.length; i++) out[i] = s.charCodeAt(i);
  return out;
}

async function gunzip(b64) {
  const stream = new Blob([bytesOf(b64)]).stream().pipeThrough(new DecompressionStream("gzip"));
  return new Uint8Array(await new Response(stream).arrayBuffer());
}

// One motion's positions as a Float32Array (T * J * 3), three.js coordinates, lane offset added.
export async function decodeMotion(m, J) {
  const raw = await gunzip(m.data);
  const T = m.n, C = J * 3, N = C * T;
  if (raw.length !== 2 * N) throw new Error(`motion data holds ${raw.length / 2} values, not ${N}`);
  const out = new Float32Array(N);
  for (let c = 0; c < C; c++) {
    const axis = c % 3, j = (c - axis) / 3;
    const step = m.step[axis], lo = m.lo[axis] + m.offset[axis];
    let acc = 0;
    for (let t = 0; t < T; t++) {
      const i = c * T + t;
      acc = (acc + ((raw[i] | (raw[N + i] << 8)) << 16 >> 16)) << 16 >> 16; // int16 wrap
      const v = (acc + Q) * step + lo;
      const o = (t * J + j) * 3;
      if (axis === 0) out[o] = v;
      else if (axis === 1) out[o + 2] = -v;
      else out[o + 1] = v;
    }
  }
  return out;
}

const toThree = (p, off = [0, 0, 0]) =>
  new THREE.Vector3(p[0] + off[0], p[2] + off[2], -(p[1] + off[1]));

// ------------------------------------------------------------------ styles and controls

const CSS = `
.mmp-stage{position:relative;width:100%;overflow:hidden;border-radius:4px;background:#f3f4f6;touch-action:none}
.mmp-stage canvas{display:block;width:100%;height:100%;outline:none}
.mmp-label{position:absolute;transform:translate(-50%,-100%);font:600 12px/1.3 system-ui,sans-serif;
  padding:1px 6px;border-radius:3px;background:rgba(255,255,255,.85);white-space:nowrap;pointer-events:none}
.mmp-bar{display:flex;align-items:center;gap:8px;margin-top:4px;font:12px/1.4 system-ui,sans-serif;color:#333}
.mmp-bar button{font:inherit;min-width:2.4em;padding:2px 6px;cursor:pointer}
.mmp-bar input[type=range]{flex:1;min-width:60px}
.mmp-bar select{font:inherit}
.mmp-time{font-variant-numeric:tabular-nums;white-space:nowrap}
.mmp-hint{position:absolute;right:6px;bottom:4px;font:11px system-ui,sans-serif;color:#555;pointer-events:none;
  opacity:0;transition:opacity .3s}
.mmp-stage:hover .mmp-hint{opacity:.9}
`;

function addStyle() {
  if (document.getElementById("mmp-style")) return;
  const s = document.createElement("style");
  s.id = "mmp-style";
  s.textContent = CSS;
  document.head.appendChild(s);
}

function el(tag, props = {}, parent = null) {
  const e = Object.assign(document.createElement(tag), props);
  if (parent) parent.appendChild(e);
  return e;
}

// ------------------------------------------------------------------ orbit and zoom

// Spherical camera around a target point: theta about +Y, phi from +Y down.
class Orbit {
  constructor(camera, dom, onChange) {
    Object.assign(this, { camera, dom, onChange, target: new THREE.Vector3() });
    this.radius = 5; this.theta = 0; this.phi = 1.2; this.active = false;
    let last = null, mode = null;
    const pointers = new Map();
    dom.addEventListener("contextmenu", (e) => e.preventDefault());
    dom.addEventListener("pointerdown", (e) => {
      this.active = true;
      dom.focus({ preventScroll: true });
      dom.setPointerCapture(e.pointerId);
      pointers.set(e.pointerId, [e.clientX, e.clientY]);
      mode = e.button === 2 || e.shiftKey || e.ctrlKey || e.metaKey ? "pan" : "orbit";
      last = [e.clientX, e.clientY];
    });
    dom.addEventListener("pointermove", (e) => {
      if (!pointers.has(e.pointerId)) return;
      if (pointers.size === 2) { // pinch: zoom by the change of finger distance
        const [a, b] = [...pointers.values()];
        const d0 = Math.hypot(a[0] - b[0], a[1] - b[1]);
        pointers.set(e.pointerId, [e.clientX, e.clientY]);
        const [c, d] = [...pointers.values()];
        const d1 = Math.hypot(c[0] - d[0], c[1] - d[1]);
        if (d0 > 0 && d1 > 0) this.zoom(d0 / d1);
        return;
      }
      pointers.set(e.pointerId, [e.clientX, e.clientY]);
      const dx = e.clientX - last[0], dy = e.clientY - last[1];
      last = [e.clientX, e.clientY];
      if (mode === "orbit") {
        this.theta -= dx * 0.008;
        this.phi = Math.min(Math.max(this.phi - dy * 0.008, 0.05), Math.PI / 2 - 0.01);
      } else {
        const s = (2 * this.radius * Math.tan((camera.fov * Math.PI) / 360)) / dom.clientHeight;
        const right = new THREE.Vector3().setFromMatrixColumn(camera.matrix, 0);
        const up = new THREE.Vector3().setFromMatrixColumn(camera.matrix, 1);
        this.target.addScaledVector(right, -dx * s).addScaledVector(up, dy * s);
      }
      this.update();
    });
    const end = (e) => pointers.delete(e.pointerId);
    dom.addEventListener("pointerup", end);
    dom.addEventListener("pointercancel", end);
    dom.addEventListener("blur", () => { this.active = false; });
    dom.addEventListener("wheel", (e) => {
      if (!this.active && !e.ctrlKey) return; // let the page scroll until the player is clicked
      e.preventDefault();
      this.zoom(Math.exp(Math.max(-100, Math.min(100, e.deltaY)) * 0.002));
    }, { passive: false });
  }
  zoom(f) { this.radius = Math.min(Math.max(this.radius * f, 0.3), 300); this.update(); }
  update() {
    const { target: t, radius: r, theta, phi } = this;
    this.camera.position.set(
      t.x + r * Math.sin(phi) * Math.sin(theta), t.y + r * Math.cos(phi),
      t.z + r * Math.sin(phi) * Math.cos(theta));
    this.camera.lookAt(t);
    this.onChange();
  }
}

// ------------------------------------------------------------------ scene pieces

const UP = new THREE.Vector3(0, 1, 0);

// A stick figure: one cylinder per bone, one sphere per joint (and a head), updated per frame.
class Figure {
  constructor(parents, head, radius, material, jointMaterial, shadows) {
    this.parents = parents; this.head = head; this.r = radius;
    this.group = new THREE.Group();
    const cyl = new THREE.CylinderGeometry(radius, radius, 1, 14, 1, true);
    const ball = new THREE.SphereGeometry(radius * 1.35, 16, 12);
    this.bones = parents.map((p) => {
      if (p < 0) return null;
      const m = new THREE.Mesh(cyl, material);
      m.castShadow = shadows; this.group.add(m); return m;
    });
    this.joints = parents.map(() => {
      const m = new THREE.Mesh(ball, jointMaterial);
      m.castShadow = shadows; this.group.add(m); return m;
    });
    if (head >= 0) {
      this.headMesh = new THREE.Mesh(new THREE.SphereGeometry(radius * 3.2, 20, 16), material);
      this.headMesh.castShadow = shadows; this.group.add(this.headMesh);
    }
    this._a = new THREE.Vector3(); this._b = new THREE.Vector3(); this._d = new THREE.Vector3();
  }
  // pos: Float32Array, o: index of the frame's first coordinate
  set(pos, o) {
    const { _a: a, _b: b, _d: d } = this;
    this.parents.forEach((p, j) => {
      a.fromArray(pos, o + 3 * j);
      this.joints[j].position.copy(a);
      if (p < 0) return;
      b.fromArray(pos, o + 3 * p);
      d.subVectors(a, b);
      const len = d.length(), bone = this.bones[j];
      bone.position.addVectors(a, b).multiplyScalar(0.5);
      bone.scale.set(1, Math.max(len, 1e-6), 1);
      if (len > 1e-9) bone.quaternion.setFromUnitVectors(UP, d.divideScalar(len));
    });
    if (this.headMesh) {
      a.fromArray(pos, o + 3 * this.head);
      b.fromArray(pos, o + 3 * this.parents[this.head]);
      d.subVectors(a, b).normalize();
      this.headMesh.position.copy(a).addScaledVector(d, this.r * 2.6);
    }
  }
}

function headJoint(names, parents) {
  if (!names) return -1;
  const leaves = parents.map((_, j) => !parents.includes(j));
  for (const key of ["head", "neck"]) {
    const j = names.findIndex((n, i) => leaves[i] && parents[i] >= 0 && n.toLowerCase().includes(key));
    if (j >= 0) return j;
  }
  return -1;
}

function line(points, material) {
  const g = new THREE.BufferGeometry().setFromPoints(points);
  const l = new THREE.Line(g, material);
  if (material.isLineDashedMaterial) l.computeLineDistances();
  return l;
}

function darker(hex, f = 0.7) { return new THREE.Color(hex).multiplyScalar(f); }

// ------------------------------------------------------------------ the player

export async function mount(container, payload) {
  if (payload.version !== VERSION)
    throw new Error(`minimdm player: payload version ${payload.version}, this player reads ${VERSION}`);
  addStyle();
  const J = payload.parents.length, parents = payload.parents, fps = payload.fps;
  const motions = await Promise.all(payload.motions.map((m) => decodeMotion(m, J)));
  const contacts = await Promise.all(payload.motions.map((m) =>
    m.contacts ? gunzip(m.contacts) : Promise.resolve(null)));
  const n = motions.length, T = Math.max(...payload.motions.map((m) => m.n));
  const lengths = payload.motions.map((m) => m.n);
  const frameOffset = (i, f) => Math.min(f, lengths[i] - 1) * J * 3;
  const root = parents.indexOf(-1);

  // sizes: bone radius from the median bone length; the scene box over all frames
  const box = new THREE.Box3();
  const v = new THREE.Vector3();
  motions.forEach((pos) => { for (let i = 0; i < pos.length; i += 3) box.expandByPoint(v.fromArray(pos, i)); });
  // targets, paths and keyframes: index -1 belongs to every character (each lane, side by side)
  const lanes = (s) => (s.motion >= 0 ? [s.motion] : n > 1 && payload.layout === "side" ? [...Array(n).keys()] : [-1]);
  const offsetOf = (i) => (i >= 0 ? payload.motions[i].offset : [0, 0, 0]);
  (payload.shapes || []).forEach((s) => lanes(s).forEach((i) => {
    const flat = s.kind === "keyframes" ? s.poses.flat() : s.points.flat();
    for (let k = 0; k < flat.length; k += 3) box.expandByPoint(toThree(flat.slice(k, k + 3), offsetOf(i)));
  }));
  const bl = [];
  parents.forEach((p, j) => {
    if (p >= 0) bl.push(v.fromArray(motions[0], 3 * j).distanceTo(new THREE.Vector3().fromArray(motions[0], 3 * p)));
  });
  bl.sort((a, b) => a - b);
  const scale = bl.length ? bl[bl.length >> 1] : 0.25;
  const radius = Math.min(Math.max(0.13 * scale, 0.006), 0.05);

  // DOM: stage (canvas, labels, hint), control bar
  const width = container.clientWidth || payload.width || 640;
  const aspect = (payload.height || 360) / (payload.width || 640);
  const stage = el("div", { className: "mmp-stage" }, container);
  stage.style.height = `${Math.round(width * aspect)}px`;
  let renderer;
  try {
    renderer = new THREE.WebGLRenderer({ antialias: true });
  } catch (e) {
    stage.remove();
    throw new Error("WebGL is not available in this browser");
  }
  renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
  renderer.shadowMap.enabled = true;
  renderer.shadowMap.type = THREE.PCFSoftShadowMap;
  stage.appendChild(renderer.domElement);
  renderer.domElement.tabIndex = 0;
  renderer.domElement.setAttribute("aria-label", "3D skeleton player: drag to turn, click then scroll to zoom");
  const hint = el("div", { className: "mmp-hint", textContent: "drag: turn · right-drag: pan · click, then scroll: zoom" }, stage);

  const scene = new THREE.Scene();
  scene.background = new THREE.Color(0xf3f4f6);
  const camera = new THREE.PerspectiveCamera(35, 1, 0.02, 1000);

  // lights: sky/ground fill and one sun that casts the shadows, sized to the scene
  scene.add(new THREE.HemisphereLight(0xffffff, 0x9a9a9a, 1.5));
  const sun = new THREE.DirectionalLight(0xffffff, 2.6);
  const centre = box.getCenter(new THREE.Vector3());
  const size = box.getSize(new THREE.Vector3());
  const reach = Math.max(size.x, size.z) / 2 + 2;
  sun.position.set(centre.x + 0.8 * reach + 1, 1.6 * reach + 3, centre.z + 1.0 * reach + 1);
  sun.target.position.set(centre.x, 0, centre.z);
  sun.castShadow = true;
  sun.shadow.mapSize.set(2048, 2048);
  Object.assign(sun.shadow.camera, { left: -reach, right: reach, top: reach, bottom: -reach, near: 0.1, far: 8 * reach + 10 });
  sun.shadow.bias = -0.0005;
  sun.shadow.radius = 3;
  scene.add(sun, sun.target);

  // ground: a plane that takes shadows, and a 1 m grid (major lines every 5 m)
  const half = Math.ceil(reach + 1);
  scene.fog = new THREE.Fog(0xf3f4f6, 6 * half, 14 * half); // the far ground fades out
  const ground = new THREE.Mesh(new THREE.PlaneGeometry(40 * half, 40 * half),
    new THREE.MeshStandardMaterial({ color: 0xe6e7ea, roughness: 1 }));
  ground.rotation.x = -Math.PI / 2;
  ground.position.set(Math.round(centre.x), 0, Math.round(centre.z));
  ground.receiveShadow = true;
  scene.add(ground);
  const grid = new THREE.GridHelper(2 * half, 2 * half, 0xb4b7bd, 0xcfd2d6);
  grid.position.set(Math.round(centre.x), 0.001, Math.round(centre.z));
  scene.add(grid);

  // characters
  const head = headJoint(payload.names, parents);
  const feet = payload.feet || [];
  const figures = [], labels = [], discs = [], trails = [];
  const disc = new THREE.CircleGeometry(Math.max(3 * radius, 0.05), 24).rotateX(-Math.PI / 2);
  payload.motions.forEach((m, i) => {
    const mat = new THREE.MeshStandardMaterial({ color: m.color, roughness: 0.5, metalness: 0.05 });
    const jmat = new THREE.MeshStandardMaterial({ color: darker(m.color, 0.75), roughness: 0.5 });
    const fig = new Figure(parents, head, radius, mat, jmat, true);
    scene.add(fig.group);
    figures.push(fig);
    // the root's path on the ground
    const pts = [];
    for (let f = 0; f < m.n; f++) {
      const o = f * J * 3 + 3 * root;
      pts.push(new THREE.Vector3(motions[i][o], 0.003, motions[i][o + 2]));
    }
    trails.push(line(pts, new THREE.LineBasicMaterial({ color: darker(m.color, 0.85), transparent: true, opacity: 0.8 })));
    scene.add(trails[i]);
    // foot-contact discs, shown while the foot is on the ground
    discs.push(feet.map(() => {
      const d = new THREE.Mesh(disc, new THREE.MeshBasicMaterial({ color: darker(m.color, 0.6), transparent: true, opacity: 0.75 }));
      d.visible = false; scene.add(d); return d;
    }));
    const lab = el("div", { className: "mmp-label", textContent: m.label || "" }, stage);
    lab.style.color = `#${darker(m.color, 0.7).getHexString()}`;
    lab.style.display = m.label ? "" : "none";
    labels.push(lab);
  });

  // targets (a sphere over a ring), target paths (dashed) and keyframes (ghost poses)
  const TARGET = 0xd62728;
  const ghosts = [];
  const targetMat = new THREE.MeshStandardMaterial({ color: TARGET, roughness: 0.4, emissive: 0x400000 });
  const ringGeo = new THREE.RingGeometry(0.12, 0.17, 32).rotateX(-Math.PI / 2);
  const ringMat = new THREE.MeshBasicMaterial({ color: TARGET, side: THREE.DoubleSide });
  (payload.shapes || []).forEach((s) => {
    lanes(s).forEach((i) => {
      const off = offsetOf(i);
      if (s.kind === "target") {
        s.points.forEach((p) => {
          const q = toThree(p, off);
          const ring = new THREE.Mesh(ringGeo, ringMat);
          ring.position.set(q.x, 0.004, q.z); scene.add(ring);
          const ball = new THREE.Mesh(new THREE.SphereGeometry(0.07, 20, 14), targetMat);
          ball.position.set(q.x, Math.max(q.y, 0.07), q.z); ball.castShadow = true; scene.add(ball);
        });
      } else if (s.kind === "path") {
        const pts = s.points.map((p) => { const q = toThree(p, off); q.y = Math.max(q.y, 0.005); return q; });
        scene.add(line(pts, new THREE.LineDashedMaterial({ color: TARGET, dashSize: 0.15, gapSize: 0.08 })));
      } else if (s.kind === "keyframes") {
        const col = i >= 0 ? payload.motions[i].color : TARGET;
        s.poses.forEach((flat, k) => {
          const mat = new THREE.MeshStandardMaterial({ color: col, transparent: true, opacity: 0.28, depthWrite: false });
          const g = new Figure(parents, head, radius, mat, mat, false);
          const pos = new Float32Array(J * 3);
          for (let j = 0; j < J; j++) pos.set(toThree(flat.slice(3 * j, 3 * j + 3), off).toArray(), 3 * j);
          g.set(pos, 0);
          scene.add(g.group);
          ghosts.push({ mat, frame: s.frames ? s.frames[k] : -1 });
        });
      }
    });
  });

  // camera: centres per frame (smoothed over +-1 s) for follow, a fit of the whole box otherwise
  const centres = [];
  for (let f = 0; f < T; f++) {
    const c = new THREE.Vector3();
    motions.forEach((pos, i) => c.add(new THREE.Vector3().fromArray(pos, frameOffset(i, f) + 3 * root)));
    centres.push(c.divideScalar(n));
  }
  const k = Math.max(1, Math.round(fps));
  const smooth = centres.map((_, f) => {
    const c = new THREE.Vector3(); let w = 0;
    for (let g = Math.max(0, f - k); g <= Math.min(T - 1, f + k); g++) { c.add(centres[g]); w++; }
    c.divideScalar(w); c.y = 0.45 * size.y + box.min.y; return c;
  });
  // what the follow camera shows at frame f: the characters as they are at f (the camera's
  // distance is then smoothed over +-1 s), so that it frames their bodies, and draws back only
  // as far as characters that part (a fast and a slow walker) need
  const nearBox = (f) => {
    const b = new THREE.Box3();
    motions.forEach((pos, i) => {
      const o = frameOffset(i, f);
      for (let j = 0; j < J; j++) b.expandByPoint(v.fromArray(pos, o + 3 * j));
    });
    return b.set(b.min.setY(box.min.y), b.max.setY(box.max.y));
  };
  const orbit = new Orbit(camera, renderer.domElement, () => requestRender());
  let follow = !!payload.follow;
  const [az, el_] = payload.view.map((d) => (d * Math.PI) / 180);
  const fitted = []; // follow: the camera distance that frames each frame's box
  // the nearest camera that shows all of a box: bisect between a sphere's fit, which always
  // shows it, and 0
  const fit = (shown) => {
    const half = Math.atan(Math.tan((camera.fov * Math.PI) / 360) * Math.min(1, camera.aspect));
    const corners = [0, 1, 2, 3, 4, 5, 6, 7].map((c) => new THREE.Vector3(
      c & 1 ? shown.max.x : shown.min.x, c & 2 ? shown.max.y : shown.min.y, c & 4 ? shown.max.z : shown.min.z));
    // room above for labels: one row, or a stack of them when the characters overlay each other
    const rows = payload.layout === "overlay" ? payload.motions.filter((m) => m.label).length : 1;
    const roof = Math.max(0.3, 0.8 - (Math.max(rows, 1) - 1) * 40 / (stage.clientHeight || payload.height));
    const fits = (d) => {
      orbit.radius = d;
      orbit.update();
      camera.updateMatrixWorld();
      return corners.every((c) => {
        const q = c.clone().project(camera);
        return q.z < 1 && Math.abs(q.x) < 0.94 && q.y > -0.94 && q.y < roof;
      });
    };
    let lo = 0.3, hi = (shown.getBoundingSphere(new THREE.Sphere()).radius + 0.3) / Math.sin(half);
    if (!fits(hi)) hi *= 1.5;
    for (let q = 0; q < 20; q++) { const mid = (lo + hi) / 2; if (fits(mid)) hi = mid; else lo = mid; }
    return hi;
  };
  const home = () => {
    // the payload's azimuth/elevation are in the z-up world; turn them into theta/phi here
    const dir = toThree([Math.cos(el_) * Math.cos(az), Math.cos(el_) * Math.sin(az), Math.sin(el_)]);
    orbit.theta = Math.atan2(dir.x, dir.z);
    orbit.phi = Math.acos(Math.min(Math.max(dir.y, -1), 1));
    fitted.length = 0;
    if (follow) {
      // fit 6 frames a second, the last one too, and interpolate between them (then smoothed)
      const step = Math.max(1, Math.round(fps / 6)), d = new Array(T);
      for (let f = 0; f < T; f = f === T - 1 ? T : Math.min(f + step, T - 1)) {
        orbit.target.copy(smooth[f]);
        d[f] = fit(nearBox(f));
      }
      for (let f = 0, a = 0; f < T; f++) {
        if (d[f] !== undefined) { a = f; continue; }
        const b = Math.min(a + step, T - 1);
        d[f] = d[a] + ((d[b] - d[a]) * (f - a)) / (b - a);
      }
      for (let f = 0; f < T; f++) {
        const near = d.slice(Math.max(0, f - k), f + k + 1);
        fitted.push(near.reduce((a, b) => a + b, 0) / near.length);
      }
      orbit.target.copy(smooth[frame]);
      orbit.radius = fitted[frame];
    } else {
      orbit.target.set(centre.x, 0.45 * size.y + box.min.y, centre.z);
      orbit.radius = fit(box);
    }
    orbit.update();
  };

  // control bar
  const bar = el("div", { className: "mmp-bar" }, container);
  const playBtn = el("button", { type: "button", title: "play / pause (space)" }, bar);
  const slider = el("input", { type: "range", min: 0, max: T - 1, step: 1, value: 0, title: "frame" }, bar);
  const time = el("span", { className: "mmp-time" }, bar);
  const speed = el("select", { title: "playback speed" }, bar);
  SPEEDS.forEach((s) => el("option", { value: s, textContent: `${s}×`, selected: s === 1 }, speed));
  const followLabel = el("label", { title: "the camera follows the characters; untick for the whole path" }, bar);
  const followBox = el("input", { type: "checkbox", checked: follow }, followLabel);
  followLabel.append(" follow");
  const resetBtn = el("button", { type: "button", textContent: "⟲", title: "reset the view (double-click)" }, bar);

  let frame = 0, shown = 0, playing = false, clock = 0, lastTime = null, dirty = false, visible = true;
  const aspectFix = () => {
    const w = stage.clientWidth || width, h = Math.round(w * aspect);
    stage.style.height = `${h}px`;
    renderer.setSize(w, h, false);
    camera.aspect = w / h;
    camera.updateProjectionMatrix();
  };
  aspectFix();
  home();

  function show(f) {
    frame = Math.min(Math.max(Math.round(f), 0), T - 1);
    const tmp = new THREE.Vector3();
    figures.forEach((fig, i) => {
      const o = frameOffset(i, frame);
      fig.set(motions[i], o);
      const bits = contacts[i] ? contacts[i][Math.min(frame, lengths[i] - 1)] : 0;
      feet.forEach((j, q) => {
        const d = discs[i][q];
        d.visible = ((bits >> q) & 1) === 1;
        d.position.set(motions[i][o + 3 * j], 0.002, motions[i][o + 3 * j + 2]);
      });
    });
    ghosts.forEach((g) => { g.mat.opacity = g.frame >= 0 && Math.abs(g.frame - frame) <= 2 ? 0.6 : 0.28; });
    if (follow) {
      orbit.radius *= fitted[frame] / fitted[shown]; // keeps a zoom the reader chose
      orbit.target.add(tmp.subVectors(smooth[frame], orbit.target));
      orbit.update();
    }
    shown = frame;
    slider.value = String(frame);
    time.textContent = `${frame + 1} / ${T} · ${(frame / fps).toFixed(2)} s`;
    container.dataset.frame = String(frame);
    requestRender();
  }

  function placeLabels() {
    const w = stage.clientWidth, h = stage.clientHeight, p = new THREE.Vector3();
    camera.updateMatrixWorld(); // a turn of the view moved the camera since the last render
    figures.forEach((fig, i) => {
      if (!payload.motions[i].label) return;
      let top = -Infinity;
      fig.joints.forEach((m) => { if (m.position.y > top) { top = m.position.y; p.copy(m.position); } });
      if (fig.headMesh && fig.headMesh.position.y > top) p.copy(fig.headMesh.position);
      p.y += 5 * radius + 0.05;
      p.project(camera);
      labels[i].style.left = `${((p.x + 1) / 2) * w}px`;
      labels[i].style.top = `${((1 - p.y) / 2) * h}px`;
      labels[i].style.visibility = p.z < 1 ? "visible" : "hidden";
    });
    // labels that would overlap stack upwards, so each stays readable; a stack that reaches the
    // top of the picture goes on below the head instead, so that no label is cut off
    const placed = [];
    const free = (x, y, w, h) => placed.every((q) => Math.abs(q.x - x) >= (q.w + w) / 2 + 2 || Math.abs(q.y - y) >= h + 1);
    labels.forEach((lab) => {
      if (lab.style.display === "none") return;
      const x = parseFloat(lab.style.left), w = lab.offsetWidth, h = lab.offsetHeight;
      const y0 = Math.max(parseFloat(lab.style.top), h + 2); // the label's bottom edge
      let y = y0;
      for (let k = 1; !free(x, y, w, h) && y0 - k * (h + 2) >= h + 2; k++) y = y0 - k * (h + 2);
      for (let k = 1; !free(x, y, w, h) && k <= labels.length; k++) y = y0 + k * (h + 2);
      lab.style.top = `${y}px`;
      placed.push({ x, y, w });
    });
  }

  function requestRender() {
    if (!dirty) { dirty = true; requestAnimationFrame(tick); }
  }
  function tick(now) {
    if (playing && visible) {
      if (lastTime !== null) clock += ((now - lastTime) / 1000) * Number(speed.value);
      lastTime = now;
      const f = Math.floor(clock * fps) % T;
      if (f !== frame) show(f);
      dirty = false;
      requestAnimationFrame(tick);
    } else {
      lastTime = null;
      dirty = false;
    }
    placeLabels();
    renderer.render(scene, camera);
  }
  const setPlaying = (p) => {
    playing = p;
    playBtn.textContent = p ? "❚❚" : "▶";
    playBtn.setAttribute("aria-label", p ? "pause" : "play");
    clock = frame / fps;
    if (p) { dirty = true; requestAnimationFrame(tick); }
  };

  playBtn.addEventListener("click", () => setPlaying(!playing));
  slider.addEventListener("input", () => { setPlaying(false); show(Number(slider.value)); });
  followBox.addEventListener("change", () => { follow = followBox.checked; home(); show(frame); });
  resetBtn.addEventListener("click", () => { home(); show(frame); });
  renderer.domElement.addEventListener("dblclick", () => { home(); show(frame); });
  renderer.domElement.addEventListener("keydown", (e) => {
    if (e.key === " ") { e.preventDefault(); setPlaying(!playing); }
    else if (e.key === "ArrowRight" || e.key === "ArrowLeft") {
      e.preventDefault(); setPlaying(false); show(frame + (e.key === "ArrowRight" ? 1 : -1));
    }
  });
  new ResizeObserver(() => { aspectFix(); placeLabels(); requestRender(); }).observe(stage);
  new IntersectionObserver((entries) => {
    visible = entries[0].isIntersecting;
    if (visible && playing) { dirty = true; requestAnimationFrame(tick); }
  }).observe(stage);
  hint.style.display = "";

  show(0);
  setPlaying(!!payload.autoplay);
  const api = {
    get frame() { return frame; },
    nFrames: T,
    setFrame: (f) => { setPlaying(false); show(f); },
    play: () => setPlaying(true),
    pause: () => setPlaying(false),
    get playing() { return playing; },
    // each character's on-screen height, as a share of the picture's height
    bodyHeights: () => {
      camera.updateMatrixWorld();
      return figures.map((fig) => {
        const ys = fig.joints.map((m) => m.position.clone().project(camera).y);
        return (Math.max(...ys) - Math.min(...ys)) / 2;
      });
    },
    camera, orbit, renderer,
  };
  container.minimdmPlayer = api;
  container.dataset.ready = "1";
  return api;
}
