// minimdm's live character: a joystick policy steering A-MDM, one ONNX graph per frame, run by
// ONNX Runtime Web in the reader's browser and drawn with the 3D player's figure (three.js).
//
// live(container, {ort, data}) loads the bundle that minimdm.viz.live.live_bundle wrote (a JSON
// file beside the .onnx graph), checks its metadata against what this page expects, and starts
// a loop: the task observation (the commanded heading relative to the character's, the
// commanded speed and its gap to the velocity along it, as minimdm.rl.tasks.JoystickTask
// observes them), fresh Gaussian noise, one graph call, then the root integrated and the joints
// placed as the metadata's decode recipe says. Arrow keys or the buttons steer: left/right turn
// the command by 45 degrees, up/down change the speed. A mismatch shows a message, never a
// frozen canvas.
//
// Two clocks. The model steps on its own: frame n is due n / fps seconds after the start
// (30 Hz for the book's model), whatever the display does, so the character moves at the speed
// it has in model time on every machine. The display draws the newest frame whenever the
// browser repaints (requestAnimationFrame). A machine too slow for the model's rate runs it
// slower, and the counter says so: the clock is not allowed to run ahead and burst.
// The container's data-frames, data-fps (model frames per second over the last second),
// data-draws (new frames drawn per second), data-ms (milliseconds one model frame takes, the
// mean over the last second: how fast the page could run), data-speed (m/s in model time over
// the last second),
// data-x, data-y, data-heading and data-goal report the state (the browser test reads them).
import * as THREE from "three";

// The player's figure, shared rather than copied, and player.js left byte for byte as it is (the
// chapters' stored players are keyed by its hash): its source is imported again with an export
// of the two names appended, its "three" pointing at the page's three.js (one THREE for both).
async function playerParts() {
  const src = await (await fetch(new URL("./player.js", import.meta.url))).text();
  const code = src.replace('from "three"', `from "${import.meta.resolve("three")}"`) +
    "\nexport { Figure, headJoint };\n";
  return import(URL.createObjectURL(new Blob([code], { type: "text/javascript" })));
}

const EXPECT = { format: "minimdm-frame-onnx/1", kind: "policy", task: "joystick" };

function fail(container, message) {
  container.dataset.error = message;
  const box = document.createElement("div");
  box.className = "mml-error";
  box.style.cssText = "padding:1em;border:1px solid #c33;color:#900;background:#fee;font:14px sans-serif";
  box.textContent = `The live character cannot start: ${message}`;
  container.replaceChildren(box);
  throw new Error(message);
}

// What this page needs of the model file; the first difference, in words.
export function checkMetadata(meta) {
  if (!meta || meta.format !== EXPECT.format) return `model format ${meta && meta.format}, expected ${EXPECT.format}`;
  if (meta.kind !== EXPECT.kind) return `model kind ${meta.kind}, expected a steering policy`;
  const task = meta.policy && meta.policy.task && meta.policy.task.name;
  if (task !== EXPECT.task) return `the policy's task is ${task}, expected joystick`;
  const cols = meta.feature_columns, sk = meta.skeleton;
  if (!cols || !sk || !meta.normalizer) return "the model file has no feature layout, skeleton or normalizer";
  const J = sk.parents.length, D = meta.inputs[0].shape[1];
  if (cols.joint_pos.columns[1] - cols.joint_pos.columns[0] !== 3 * J)
    return `the feature layout has ${(cols.joint_pos.columns[1] - cols.joint_pos.columns[0]) / 3} joints, the skeleton ${J}`;
  if (meta.normalizer.mean.length !== D) return `the normalizer has ${meta.normalizer.mean.length} features, the model ${D}`;
  return null;
}

function gaussian(n) {
  const out = new Float32Array(n);
  for (let i = 0; i < n; i += 2) { // Box-Muller
    const u = 1 - Math.random(), v = Math.random();
    const r = Math.sqrt(-2 * Math.log(u));
    out[i] = r * Math.cos(2 * Math.PI * v);
    if (i + 1 < n) out[i + 1] = r * Math.sin(2 * Math.PI * v);
  }
  return out;
}

const wrap = (a) => Math.atan2(Math.sin(a), Math.cos(a));

export async function live(container, { ort, data: dataUrl }) {
  let data, session;
  try {
    data = await (await fetch(dataUrl)).json();
  } catch (e) { fail(container, `cannot read ${dataUrl}: ${e.message}`); }
  const meta = data.metadata;
  const problem = checkMetadata(meta);
  if (problem) fail(container, problem);
  try {
    const bytes = await (await fetch(new URL(data.model, new URL(dataUrl, location.href)))).arrayBuffer();
    session = await ort.InferenceSession.create(new Uint8Array(bytes), { executionProviders: ["wasm"] });
  } catch (e) { fail(container, `cannot load the model: ${e.message}`); }

  let Figure, headJoint;
  try {
    ({ Figure, headJoint } = await playerParts());
  } catch (e) { fail(container, `cannot load the 3D player: ${e.message}`); }
  const D = meta.inputs[0].shape[1], A = meta.inputs[1].shape[1], N = meta.inputs[2].shape[1];
  const cols = meta.feature_columns, fps = meta.fps || 30;
  const mean = Float32Array.from(meta.normalizer.mean), std = Float32Array.from(meta.normalizer.std);
  const parents = meta.skeleton.parents, J = parents.length;
  const [pos0] = cols.joint_pos.columns, [vel0] = cols.root_vel.columns, [yaw0] = cols.yaw_rate.columns;

  // scene: the player's figure on a grid, a camera that follows
  const width = container.clientWidth || 640, height = Math.round(width * 0.56);
  const renderer = new THREE.WebGLRenderer({ antialias: true });
  renderer.setSize(width, height);
  renderer.shadowMap.enabled = true;
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(0xf3f4f6);
  scene.add(new THREE.HemisphereLight(0xffffff, 0x9a9a9a, 1.5));
  const sun = new THREE.DirectionalLight(0xffffff, 2.2);
  sun.position.set(3, 8, 4);
  scene.add(sun);
  // the ground: a checkerboard of 1 m squares (a texture: lines vanish near the camera in
  // software WebGL), moved along with the character by whole squares
  const check = new THREE.DataTexture(Uint8Array.of(
    214, 216, 220, 255, 190, 193, 198, 255, 190, 193, 198, 255, 214, 216, 220, 255), 2, 2);
  check.wrapS = check.wrapT = THREE.RepeatWrapping;
  check.repeat.set(30, 30); // 2 squares per texel pair: 60 m, 1 m squares
  check.magFilter = THREE.NearestFilter;
  check.colorSpace = THREE.SRGBColorSpace;
  check.needsUpdate = true;
  const grid = new THREE.Mesh(new THREE.PlaneGeometry(60, 60),
    new THREE.MeshBasicMaterial({ map: check }));
  grid.rotation.x = -Math.PI / 2;
  scene.add(grid);
  const camera = new THREE.PerspectiveCamera(40, width / height, 0.05, 500);
  // the book's colours (minimdm.viz.scene): orange for generated motion, red for goals
  const GENERATED = 0xf28e2b, TARGET = 0xd62728;
  const mat = new THREE.MeshStandardMaterial({ color: GENERATED, roughness: 0.5 });
  const jmat = new THREE.MeshStandardMaterial({
    color: new THREE.Color(GENERATED).multiplyScalar(0.75), roughness: 0.5 });
  const fig = new Figure(parents, headJoint(meta.skeleton.names, parents), 0.03, mat, jmat, false);
  scene.add(fig.group);
  const arrow = new THREE.ArrowHelper(new THREE.Vector3(1, 0, 0), new THREE.Vector3(), 0.8, TARGET);
  scene.add(arrow);

  // controls: arrow keys on the canvas (or anywhere on the page) and buttons
  const bar = document.createElement("div");
  bar.style.cssText = "display:flex;gap:.4em;align-items:center;margin:.4em 0;font:14px sans-serif";
  const info = document.createElement("span");
  const goal = { heading: 0, speed: 1.2 };
  const act = {
    left: () => { goal.heading = wrap(goal.heading + Math.PI / 4); },
    right: () => { goal.heading = wrap(goal.heading - Math.PI / 4); },
    up: () => { goal.speed = Math.min(goal.speed + 0.4, 2.5); },
    down: () => { goal.speed = Math.max(goal.speed - 0.4, 0); },
  };
  for (const [name, label] of [["left", "⟲ left"], ["up", "faster"], ["down", "slower"], ["right", "right ⟳"]]) {
    const b = document.createElement("button");
    b.textContent = label; b.dataset.act = name;
    b.addEventListener("click", act[name]);
    bar.appendChild(b);
  }
  bar.appendChild(info);
  container.replaceChildren(renderer.domElement, bar);
  window.addEventListener("keydown", (e) => {
    const name = { ArrowLeft: "left", ArrowRight: "right", ArrowUp: "up", ArrowDown: "down" }[e.key];
    if (!name) return;
    e.preventDefault();
    act[name]();
  });

  // the character: normalized frame, root on the ground, heading, world velocity
  let x = Float32Array.from(data.starts[0]);
  let xy = [0, 0], heading = 0, velocity = [0, 0];
  const world = new Float32Array(3 * J);
  let frames = 0;

  function place() { // features -> three.js joint positions (x, z, -y), root integration done
    const c = Math.cos(heading), s = Math.sin(heading);
    for (let j = 0; j < J; j++) {
      const o = pos0 + 3 * j;
      const lx = x[o] * std[o] + mean[o], ly = x[o + 1] * std[o + 1] + mean[o + 1];
      const lz = x[o + 2] * std[o + 2] + mean[o + 2];
      const wx = c * lx - s * ly + xy[0], wy = s * lx + c * ly + xy[1];
      world[3 * j] = wx; world[3 * j + 1] = lz; world[3 * j + 2] = -wy;
    }
    fig.set(world, 0);
    const target = new THREE.Vector3(xy[0], 0.9, -xy[1]);
    camera.position.set(xy[0] + 3.2, 2.2, -xy[1] + 3.2);
    camera.lookAt(target);
    grid.position.set(2 * Math.round(xy[0] / 2), 0, -2 * Math.round(xy[1] / 2)); // whole squares
    arrow.position.set(xy[0], 0.02, -xy[1]);
    arrow.setDirection(new THREE.Vector3(Math.cos(goal.heading), 0, -Math.sin(goal.heading)));
    renderer.render(scene, camera);
  }

  async function step() {
    const d = goal.heading - heading;
    const along = velocity[0] * Math.cos(goal.heading) + velocity[1] * Math.sin(goal.heading);
    const task = Float32Array.of(Math.cos(d), Math.sin(d), goal.speed / 3, (goal.speed - along) / 3);
    const out = await session.run({
      state: new ort.Tensor("float32", x, [1, D]),
      task: new ort.Tensor("float32", task, [1, A]),
      noise: new ort.Tensor("float32", gaussian(N), [1, N]),
    });
    x = out.next_state.data;
    if (!x.every(Number.isFinite)) fail(container, `the model produced a non-finite frame ${frames + 1}`);
    // the root, as SteeringVecEnv integrates it
    const yaw = x[yaw0] * std[yaw0] + mean[yaw0];
    const vx = x[vel0] * std[vel0] + mean[vel0], vy = x[vel0 + 1] * std[vel0 + 1] + mean[vel0 + 1];
    const h = heading + yaw, c = Math.cos(h), s = Math.sin(h);
    velocity = [(c * vx - s * vy) * fps, (s * vx + c * vy) * fps];
    heading = wrap(h);
    xy = [xy[0] + velocity[0] / fps, xy[1] + velocity[1] / fps];
    frames += 1;
  }

  // rates over the last second, from the times of the events in it
  function rate(times, now) {
    while (times.length && times[0] < now - 1000) times.shift();
    return times.length > 1 ? (1000 * (times.length - 1)) / (times[times.length - 1] - times[0]) : 0;
  }
  const stepTimes = [], drawTimes = [], speeds = [], costs = [];
  const period = 1000 / fps;
  let due = performance.now(), drawn = -1;

  function report(now) {
    const modelRate = rate(stepTimes, now), drawRate = rate(drawTimes, now);
    const mean = (a) => (a.length ? a.reduce((u, v) => u + v, 0) / a.length : 0);
    const speed = mean(speeds);
    Object.assign(container.dataset, {
      frames: String(frames), fps: modelRate.toFixed(1), draws: drawRate.toFixed(1),
      ms: mean(costs).toFixed(2), speed: speed.toFixed(2), x: xy[0].toFixed(3), y: xy[1].toFixed(3),
      heading: heading.toFixed(3), goal: goal.heading.toFixed(3),
    });
    info.textContent = `${speed.toFixed(2)} m/s (command ${goal.speed.toFixed(1)} m/s, ` +
      `${Math.round((goal.heading * 180) / Math.PI)}°) · model ${modelRate.toFixed(0)} frames/s ` +
      `of ${fps} · drawn ${drawRate.toFixed(0)}/s`;
  }

  async function tick() { // the model's clock
    const start = performance.now();
    try { await step(); } catch (e) { if (!container.dataset.error) fail(container, e.message); return; }
    const now = performance.now();
    stepTimes.push(now);
    speeds.push(Math.hypot(velocity[0], velocity[1]));
    costs.push(now - start);
    if (speeds.length > fps) { speeds.shift(); costs.shift(); }
    due += period;
    if (now - due > 5 * period) due = now; // fell behind (a slow machine, a hidden tab): no burst
    report(now);
    setTimeout(tick, Math.max(0, due - now));
  }

  function draw(now) { // the display's clock: the newest frame, once
    if (container.dataset.error) return;
    if (drawn !== frames) {
      place();
      drawn = frames;
      drawTimes.push(now);
    }
    requestAnimationFrame(draw);
  }

  place();
  container.dataset.frames = "0";
  due = performance.now();
  setTimeout(tick, 0);
  requestAnimationFrame(draw);
}
