// humotion live page: sends a headset's head and hands (WebXR) or a replayed recording to
// `humotion serve` over its WebSocket (binary frames, docs/live.md) and shows the body it returns
// as the skinned body of `humotion body` (body.glb), its rig driven from the streamed rotations.
import * as THREE from "three";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";

const params = new URLSearchParams(location.search);
const state = { poses: 0, errors: [], welcome: null, skeleton: null, last: null, mode: "idle", body: null };
window.humotion = state;               // read by tests and for debugging

// -- scene: a floor grid and the tracked body ----------------------------------------------------
const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: params.has("replay") });
renderer.setPixelRatio(devicePixelRatio);
renderer.setSize(innerWidth, innerHeight);
renderer.xr.enabled = true;
document.body.appendChild(renderer.domElement);
const scene = new THREE.Scene();
scene.background = new THREE.Color(0x202428);
const camera = new THREE.PerspectiveCamera(45, innerWidth / innerHeight, 0.05, 50);
camera.position.set(0, 1.1, -4.2);       // in front of a body facing OpenXR's forward (-Z), as in a mirror
camera.lookAt(0, 0.9, 0);
scene.add(new THREE.GridHelper(6, 12, 0x556070, 0x343a40));
scene.add(new THREE.HemisphereLight(0xffffff, 0x404040, 1.6));
const sun = new THREE.DirectionalLight(0xffffff, 1.8);
sun.position.set(1.5, 3, 2.5);
scene.add(sun);
const avatar = new THREE.Group();      // in VR: 2 m ahead, turned to face the user, like a mirror
scene.add(avatar);
const axes = new THREE.Group();        // humotion's axes -> the connection's (a diagonal of +-1), times the body's scale
avatar.add(axes);
addEventListener("resize", () => {
  camera.aspect = innerWidth / innerHeight;
  camera.updateProjectionMatrix();
  renderer.setSize(innerWidth, innerHeight);
});

// -- the body: body.glb (the rig, rest pose) and body.json (how canonical joints drive its bones)
const CONVENTIONS = { openxr: [-1, 1, -1], unity: [-1, 1, 1], humotion: [1, 1, 1] };
let body = null;                       // { mesh, bones, table, rest: [Quaternion] } once loaded
async function loadBody() {
  let answer = await fetch("./body.json");
  while (answer.status === 503) {      // the server is still making the body (seconds, once)
    await new Promise((resolve) => setTimeout(resolve, 1000));
    answer = await fetch("./body.json");
  }
  if (!answer.ok) throw new Error(await answer.text());
  const table = await answer.json();
  const gltf = await new GLTFLoader().loadAsync("./body.glb");
  let mesh = null;
  gltf.scene.traverse((node) => { if (node.isSkinnedMesh) mesh = node; });
  if (!mesh) throw new Error("body.glb holds no skinned mesh");
  mesh.frustumCulled = false;          // its bounds are the rest pose's; the tracked body walks away from them
  axes.add(gltf.scene);
  const rest = table.rest.map(([w, x, y, z]) => new THREE.Quaternion(x, y, z, w));
  const clavicles = Object.fromEntries(table.clavicles.map((c) => [c.bone, c]));
  body = { mesh, bones: mesh.skeleton.bones, table, rest, clavicles };   // skin joints in rig order (body.json's bones)
  state.body = { bones: table.bones.length, vertices: mesh.geometry.attributes.position.count, height: table.height };
}
loadBody().catch((error) => { state.errors.push(`body: ${error.message}`); });

// The pose (the connection's axes) -> humotion's axes -> every rig bone's local rotation; the
// rig's root where the tracked pelvis is, the body scaled to the tracked skeleton's height.
const q = new THREE.Quaternion(), v = new THREE.Vector3();
function driveBody(root, rotations) {
  if (!body || !state.skeleton || !state.welcome) return;
  const c = CONVENTIONS[state.welcome.convention], m = [1, c[0] * c[1] * c[2] * c[0], c[0] * c[1] * c[2] * c[1],
                                                       c[0] * c[1] * c[2] * c[2]];
  const parents = state.welcome.parents, table = body.table;
  const world = rotations.map(() => new THREE.Quaternion());
  rotations.forEach(([w, x, y, z], j) => {
    q.set(x * m[1], y * m[2], z * m[3], w).normalize();
    world[j].copy(parents[j] >= 0 ? world[parents[j]] : new THREE.Quaternion()).multiply(q);
  });
  const rig = table.bones.map(() => new THREE.Quaternion());
  table.bones.forEach((_, b) => {
    const d = table.drivers[b], p = table.parents[b], clavicle = body.clavicles[b];
    if (d >= 0) rig[b].copy(world[d]).multiply(body.rest[b]);
    else if (p >= 0) rig[b].copy(rig[p]);
    if (clavicle) {                    // raised with the upper arm above the chest's horizontal
      v.set(...clavicle.aim).applyQuaternion(world[clavicle.shoulder]).applyQuaternion(q.copy(rig[p]).invert());
      const elevation = Math.asin(Math.min(1, Math.max(-1, v.y / v.length())));
      rig[b].multiply(q.setFromAxisAngle(v.set(...clavicle.axis), clavicle.rise * Math.max(elevation, 0)));
    }
    const local = p >= 0 ? q.copy(rig[p]).invert().multiply(rig[b]) : rig[b];
    body.bones[b].quaternion.copy(local);
  });
  const scale = state.skeleton.height / table.height;
  axes.scale.set(c[0] * scale, c[1] * scale, c[2] * scale);
  const pelvis = state.skeleton.offsets[0].map((value, k) => value * c[k]);          // its rest place, humotion axes
  v.set(...table.root).multiplyScalar(scale).sub(new THREE.Vector3(...pelvis)).applyQuaternion(world[0]);
  v.add(new THREE.Vector3(root[0] * c[0], root[1] * c[1], root[2] * c[2])).divideScalar(scale);
  body.bones[0].position.copy(v);
}

function showPose(pose) {
  state.poses += 1;
  state.last = pose.positions;
  driveBody(pose.root, pose.rotations);
}

// Skinned vertex positions in the scene (metres, the connection's axes), for tests: the lowest
// and highest, and those of a few fixed vertices.
state.probe = (every = 97) => {
  if (!body) return null;
  scene.updateMatrixWorld(true);
  const count = body.mesh.geometry.attributes.position.count, sample = [];
  let low = Infinity, high = -Infinity;
  for (let i = 0; i < count; i += 1) {
    body.mesh.getVertexPosition(i, v);
    v.applyMatrix4(body.mesh.matrixWorld);
    low = Math.min(low, v.y);
    high = Math.max(high, v.y);
    if (i % every === 0) sample.push([v.x, v.y, v.z]);
  }
  return { low, high, sample };
};

// -- the connection: binary frames out (96 bytes), binary poses in (640 bytes) -----------------
const IDENTITY = [0, 0, 0, 1, 0, 0, 0];
function encodeFrame(t, head, left, right) {
  const buffer = new ArrayBuffer(96), view = new DataView(buffer);
  view.setUint8(0, 1);                                       // version
  view.setUint8(1, 1);                                       // kind: headset frame
  view.setUint8(2, (left ? 1 : 0) | (right ? 2 : 0));        // visibility flags
  view.setFloat64(4, t, true);
  [head, left || IDENTITY, right || IDENTITY].forEach((device, k) =>
    device.forEach((value, i) => view.setFloat32(12 + 28 * k + 4 * i, value, true)));
  return buffer;
}
function decodePose(buffer) {
  const view = new DataView(buffer);
  if (buffer.byteLength !== 640 || view.getUint8(1) !== 2) return null;
  const floats = (offset, n) => Array.from({ length: n }, (_, i) => view.getFloat32(offset + 4 * i, true));
  const group = (offset, n, k) => Array.from({ length: n }, (_, j) => floats(offset + 4 * k * j, k));
  return { root: floats(12, 3), rotations: group(24, 22, 4), positions: group(376, 22, 3) };
}

const status = document.getElementById("status");
const query = new URLSearchParams({ convention: "openxr", hand_frame: params.get("hand_frame") || "forward" });
if (params.get("token")) query.set("token", params.get("token"));
const socket = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/?${query}`);
socket.binaryType = "arraybuffer";
socket.onopen = () => {
  socket.send(JSON.stringify({ type: "hello", version: 1 }));
  status.textContent = "connected";
};
socket.onclose = (event) => { status.textContent = `closed (${event.code} ${event.reason})`; };
socket.onmessage = (event) => {
  if (typeof event.data !== "string") {
    const pose = decodePose(event.data);
    if (pose) showPose(pose);
    return;
  }
  const message = JSON.parse(event.data);
  if (message.type === "welcome") {
    state.welcome = message;
    if (params.has("replay")) startReplay();
  } else if (message.type === "skeleton") state.skeleton = message;
  else if (message.type === "error") {
    state.errors.push(message.message);
    status.textContent = message.message;
  }
};
const send = (data) => { if (socket.readyState === WebSocket.OPEN && socket.bufferedAmount < 65536) socket.send(data); };

// -- WebXR: head and hands (wrist joints, or controllers' grips) every XR frame ------------------
const values = (pose) => {
  const p = pose.transform.position, q = pose.transform.orientation;
  return [p.x, p.y, p.z, q.w, q.x, q.y, q.z];
};
let latestXR = null;
function sendXRFrame(frame) {
  const space = renderer.xr.getReferenceSpace();
  const viewer = frame.getViewerPose(space);
  if (!viewer) return;
  const hands = { left: null, right: null };
  for (const source of frame.session.inputSources) {
    if (source.handedness !== "left" && source.handedness !== "right") continue;
    const wrist = source.hand && source.hand.get("wrist");
    const pose = wrist ? frame.getJointPose(wrist, space) : source.gripSpace && frame.getPose(source.gripSpace, space);
    if (pose) hands[source.handedness] = values(pose);
  }
  latestXR = [values(viewer), hands.left, hands.right];
  send(encodeFrame(frame.predictedDisplayTime / 1000, ...latestXR));
}
const vrButton = document.getElementById("vr");
if (navigator.xr) navigator.xr.isSessionSupported("immersive-vr").then((ok) => { vrButton.disabled = !ok; });
vrButton.onclick = async () => {
  const session = await navigator.xr.requestSession("immersive-vr", { optionalFeatures: ["local-floor", "hand-tracking"] });
  renderer.xr.setReferenceSpaceType("local-floor");
  await renderer.xr.setSession(session);
  state.mode = "xr";
  avatar.position.set(0, 0, -2);
  avatar.rotation.y = Math.PI;
  document.getElementById("calibrate").disabled = false;
  session.addEventListener("end", () => { state.mode = "idle"; avatar.position.set(0, 0, 0); avatar.rotation.y = 0; });
};
document.getElementById("calibrate").onclick = () => {
  if (latestXR && latestXR[1] && latestXR[2]) {
    send(JSON.stringify({ type: "calibrate", head: latestXR[0], left: latestXR[1], right: latestXR[2] }));
  }
};

// -- replay: a recording's frames (the server's demo clip) sent at their own times --------------
let replay = null;
async function startReplay() {
  const answer = await fetch("./demo.json");
  const { frames } = await answer.json();
  socket.send(JSON.stringify({ type: "reset" }));
  replay = { frames, next: 0, start: performance.now() / 1000, offset: 0, span: frames[frames.length - 1][0] + 1 / 90 };
  state.mode = "replay";
}
document.getElementById("replay").onclick = () => { if (state.welcome) startReplay(); };
function stepReplay() {
  const now = performance.now() / 1000 - replay.start;
  while (replay.next < replay.frames.length && replay.frames[replay.next][0] + replay.offset <= now) {
    const [t, head, left, right] = replay.frames[replay.next];
    send(encodeFrame(t + replay.offset, head, left, right));
    replay.next += 1;
  }
  if (replay.next === replay.frames.length) {          // loop, time running on
    replay.next = 0;
    replay.offset += replay.span;
  }
}

renderer.setAnimationLoop((time, frame) => {
  if (frame) sendXRFrame(frame);
  else if (replay) stepReplay();
  renderer.render(scene, camera);
});
