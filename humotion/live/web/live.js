// humotion live page: sends a headset's head and hands (WebXR) or a replayed recording to
// `humotion serve` over its WebSocket (binary frames, docs/live.md) and draws the body it returns.
import * as THREE from "three";

const params = new URLSearchParams(location.search);
const state = { poses: 0, errors: [], welcome: null, skeleton: null, last: null, mode: "idle" };
window.humotion = state;               // read by tests and for debugging

// -- scene: a floor grid and the tracked skeleton (joints and bones) ----------------------------
const renderer = new THREE.WebGLRenderer({ antialias: true });
renderer.setPixelRatio(devicePixelRatio);
renderer.setSize(innerWidth, innerHeight);
renderer.xr.enabled = true;
document.body.appendChild(renderer.domElement);
const scene = new THREE.Scene();
scene.background = new THREE.Color(0x202428);
const camera = new THREE.PerspectiveCamera(55, innerWidth / innerHeight, 0.05, 50);
camera.position.set(0, 1.3, 3.2);
camera.lookAt(0, 1.0, 0);
scene.add(new THREE.GridHelper(6, 12, 0x556070, 0x343a40));
scene.add(new THREE.HemisphereLight(0xffffff, 0x404040, 2.5));
const avatar = new THREE.Group();      // in VR: 2 m ahead, turned to face the user, like a mirror
scene.add(avatar);
const jointMaterial = new THREE.MeshStandardMaterial({ color: 0xff8800 });
const jointGeometry = new THREE.SphereGeometry(0.035, 16, 10);
const joints = Array.from({ length: 22 }, () => {
  const mesh = new THREE.Mesh(jointGeometry, jointMaterial);
  mesh.visible = false;
  avatar.add(mesh);
  return mesh;
});
const bonePositions = new Float32Array(22 * 2 * 3);
const boneGeometry = new THREE.BufferGeometry();
boneGeometry.setAttribute("position", new THREE.BufferAttribute(bonePositions, 3));
avatar.add(new THREE.LineSegments(boneGeometry, new THREE.LineBasicMaterial({ color: 0xffcc66 })));
addEventListener("resize", () => {
  camera.aspect = innerWidth / innerHeight;
  camera.updateProjectionMatrix();
  renderer.setSize(innerWidth, innerHeight);
});

function showPose(positions) {
  state.poses += 1;
  state.last = positions;
  const parents = state.welcome ? state.welcome.parents : null;
  positions.forEach((p, j) => {
    joints[j].position.set(p[0], p[1], p[2]);
    joints[j].visible = true;
    if (parents && parents[j] >= 0) {
      bonePositions.set(p, 6 * j);
      bonePositions.set(positions[parents[j]], 6 * j + 3);
    }
  });
  boneGeometry.attributes.position.needsUpdate = true;
  boneGeometry.computeBoundingSphere();
}

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
  return Array.from({ length: 22 }, (_, j) => [0, 1, 2].map((a) => view.getFloat32(376 + 12 * j + 4 * a, true)));
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
    const positions = decodePose(event.data);
    if (positions) showPose(positions);
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
