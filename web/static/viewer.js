// The scan viewer: the body textured from the scan's images (body.glb) when it has one, else
// the mesh coloured by sharp / blurred / unseen skin (one click away from the texture); a click
// finds the best image of the spot (the server's navigator, the same as `tbp navigate`); marks; gallery.
import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";
import { getJSON, el, fmt, ending, personName } from "/static/common.js";
import { decodeAtlas, decodeMipmaps, loadBody, swapInAtlas } from "/static/body.js";
import { MarksPane } from "/static/marks.js";

const folder = decodeURIComponent(location.pathname.split("/")[2]);
const api = `/api/scans/${encodeURIComponent(folder)}`;
// unseen, blurred, sharp: the QA report's grey, red and green
const COLOURS = [[0.60, 0.60, 0.60], [0.83, 0.24, 0.18], [0.18, 0.62, 0.29]];
const state = { scan: null, views: [], byPose: new Map(), current: null, point: null, mesh: null, body: null };
const hooks = { ready: false, folder, firstPaintMs: null, lastAnswer: null, clickMs: null, timing: { scriptMs: performance.now() } };
window.tbpViewer = hooks;

// ------------------------------------------------------------------ 3D stage
const stage = document.getElementById("stage");
const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
renderer.setClearColor(0x1c2431);
renderer.setPixelRatio(Math.min(window.devicePixelRatio, 2));
stage.prepend(renderer.domElement);
const scene = new THREE.Scene();
const camera = new THREE.PerspectiveCamera(30, 1, 10, 30000);
camera.up.set(0, 0, 1);
const controls = new OrbitControls(camera, renderer.domElement);
scene.add(new THREE.HemisphereLight(0xffffff, 0x3a4352, 1.5));
const lamp = new THREE.DirectionalLight(0xffffff, 1.6);
lamp.position.set(0.3, 0.4, 1);
camera.add(lamp);
scene.add(camera);
const markers = new THREE.Group();
const markGroup = new THREE.Group();
scene.add(markers, markGroup);
let dirty = true;
controls.addEventListener("change", () => { dirty = true; });

function resize() {
  const { clientWidth: w, clientHeight: h } = stage;
  renderer.setSize(w, h, false);
  camera.aspect = w / Math.max(h, 1);
  camera.updateProjectionMatrix();
  dirty = true;
}
window.addEventListener("resize", resize);
function frame() {
  requestAnimationFrame(frame);
  if (dirty) { dirty = false; renderer.render(scene, camera); }
}

function lookFrom(side) {
  const box = state.mesh.geometry.boundingBox;
  const centre = box.getCenter(new THREE.Vector3());
  const height = box.max.z - box.min.z;
  const dir = { front: [1, 0, 0], back: [-1, 0, 0], left: [0, 1, 0], right: [0, -1, 0] }[side];
  camera.position.set(centre.x + dir[0] * height * 2.1, centre.y + dir[1] * height * 2.1, centre.z + height * 0.05);
  controls.target.copy(centre);
  controls.update();
  dirty = true;
}
document.querySelectorAll(".views button").forEach((b) => b.addEventListener("click", () => lookFrom(b.dataset.view)));

async function loadMesh() {
  const response = await (window.tbpMesh || fetch(`${api}/mesh`));
  if (!response.ok) {
    const body = await response.json().catch(() => ({}));
    throw new Error(body.error ? body.error.message : response.statusText);
  }
  const buffer = await response.arrayBuffer();
  hooks.timing.meshReceivedMs = performance.now();
  // TBPM, V, F (uint32 LE), the mesh file's SHA-256, positions, faces, skin (analysis/skin_map.py)
  const HEADER = 44;
  const head = new DataView(buffer, 0, HEADER);
  if (String.fromCharCode(...new Uint8Array(buffer, 0, 4)) !== "TBPM") throw new Error("not a mesh payload");
  const nv = head.getUint32(4, true), nf = head.getUint32(8, true);
  const positions = new Float32Array(buffer, HEADER, nv * 3);
  const faces = new Uint32Array(buffer, HEADER + nv * 12, nf * 3);
  const skin = new Uint8Array(buffer, HEADER + nv * 12 + nf * 12, nv);
  const colours = new Float32Array(nv * 3);
  for (let i = 0; i < nv; i++) {
    const c = COLOURS[skin[i]];
    colours[3 * i] = c[0]; colours[3 * i + 1] = c[1]; colours[3 * i + 2] = c[2];
  }
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute("position", new THREE.BufferAttribute(positions, 3));
  geometry.setAttribute("color", new THREE.BufferAttribute(colours, 3));
  geometry.setIndex(new THREE.BufferAttribute(faces, 1));
  geometry.computeVertexNormals();
  geometry.computeBoundingBox();
  geometry.computeBoundingSphere();
  const material = new THREE.MeshStandardMaterial({ vertexColors: true, roughness: 0.8, metalness: 0.0 });
  state.mesh = new THREE.Mesh(geometry, material);
  hooks.timing.meshBuiltMs = performance.now();
  scene.add(state.mesh);
  lookFrom("front");
}

// The textured body, shown instead of the QA map when the scan has one; the toggle swaps them.
// Its preview atlas first, then the full atlas in its place (hooks.textureLevel says which).
async function loadTexturedBody() {
  const body = await loadBody(await (window.tbpBody || fetch(`${api}/body?texture=preview`)));
  hooks.timing.bodyBuiltMs = performance.now();
  hooks.hasBody = Boolean(body);
  if (!body) return;
  state.body = body;
  scene.add(body);
  hooks.textureLevel = "preview";
  const toggle = document.getElementById("body-toggle");
  toggle.hidden = false;
  toggle.addEventListener("click", () => showTexture(!state.body.visible));
  showTexture(true);
  // then the full atlas, fetched once the preview shows (decoding it beside the preview's parsing delays the preview)
  const [bitmap, mipmaps] = await Promise.all([decodeAtlas(fetch(`${api}/body/texture`)),
    decodeMipmaps(fetch(`${api}/body/texture/mipmaps`))]);
  swapInAtlas(body, bitmap, mipmaps);
  dirty = true;
  // the next frame draws (and uploads) it; the one after that is when it is on the screen
  requestAnimationFrame(() => requestAnimationFrame(() => {
    hooks.timing.fullTextureMs = performance.now();
    hooks.textureSize = { width: bitmap.width, height: bitmap.height };
    hooks.textureMipmaps = body.material.map.mipmaps.map((level) => [level.width, level.height]);
    hooks.textureLevel = "full";
  }));
}

function showTexture(on) {
  state.body.visible = on;
  state.mesh.visible = !on;
  hooks.shown = on ? "texture" : "sharpness";
  document.getElementById("body-toggle").textContent = on ? "Sharpness map" : "Skin";
  dirty = true;
}

// The surface a click lands on: the one shown (the same geometry either way).
function shownSurface() {
  return state.body && state.body.visible ? state.body : state.mesh;
}

// The shares of the body surface the server measures on this mesh: the QA report's sharp skin.
async function loadShares() {
  const shares = await getJSON(`${api}/skin`);
  hooks.shares = shares;
  for (const name of ["sharp", "blurred", "unseen"]) document.getElementById(`sh-${name}`).textContent = `${fmt(100 * shares[name])} %`;
}

// A scan that is not complete says so over the body: partial, aborted, faulted, interrupted, running.
const ENDED_TITLE = { partial: "Partial scan: the rotation finished with images missing", aborted: "Aborted scan",
  fault: "Scan stopped by a fault", incomplete: "Incomplete scan: interrupted (the daemon stopped)" };
function showEnding(scan) {
  const ended = ending(scan);
  const box = document.getElementById("ended");
  box.hidden = ended.done;
  if (ended.done) return;
  const title = scan.in_progress ? "Scan in progress, or left by a daemon that stopped: images may still be missing" : ENDED_TITLE[scan.state] || scan.state;
  box.className = `ended ${ended.kind}`;
  box.replaceChildren(el("b", {}, title), ...ended.why.map((line) => el("div", {}, line)));
}

function project(point) {
  const v = new THREE.Vector3(...point).project(camera);
  const rect = renderer.domElement.getBoundingClientRect();
  return { x: rect.left + ((v.x + 1) / 2) * rect.width, y: rect.top + ((1 - v.y) / 2) * rect.height, visible: v.z < 1 };
}
hooks.project = project;

function sphere(point, colour, radius = 7) {
  const ball = new THREE.Mesh(new THREE.SphereGeometry(radius, 16, 12), new THREE.MeshBasicMaterial({ color: colour }));
  ball.position.set(...point);
  return ball;
}

function drawMarkers() {
  markers.clear();
  if (state.point) markers.add(sphere(state.point, 0x00dcff, 8));
  dirty = true;
}

// a click (not a drag) on the skin asks for the spot's images
let down = null;
renderer.domElement.addEventListener("pointerdown", (e) => { down = [e.clientX, e.clientY]; });
renderer.domElement.addEventListener("pointerup", (e) => {
  if (!down || Math.hypot(e.clientX - down[0], e.clientY - down[1]) > 4 || !state.mesh) return;
  const rect = renderer.domElement.getBoundingClientRect();
  const ndc = new THREE.Vector2(((e.clientX - rect.left) / rect.width) * 2 - 1, -((e.clientY - rect.top) / rect.height) * 2 + 1);
  const ray = new THREE.Raycaster();
  ray.setFromCamera(ndc, camera);
  const hit = ray.intersectObject(shownSurface(), false)[0];
  if (hit) selectSpot([hit.point.x, hit.point.y, hit.point.z]);
});

// ------------------------------------------------------------------ the spot and its images
async function selectSpot(point) {
  const started = performance.now();
  const q = new URLSearchParams({ x: point[0], y: point[1], z: point[2] });
  const answer = await getJSON(`${api}/navigate?${q}`);
  hooks.clickMs = performance.now() - started;
  hooks.lastAnswer = answer;
  state.point = answer.point_mm;
  state.views = answer.views;
  state.byPose = new Map(answer.views.map((v, rank) => [v.pose, { ...v, rank }]));
  drawMarkers();
  showPane("spot");
  if (answer.views.length) showImage(answer.views[0].angle_index, answer.views[0].camera_index);
  else renderSpot(null, "No verified image shows this spot.");
}

function imageRecord(angle, cameraIndex) {
  return state.scan.images.find((i) => i.angle_index === angle && i.camera_index === cameraIndex);
}

function shot(view, record, size = "preview") {
  const src = `${api}/images/${encodeURIComponent(record.file.split("/").pop())}?size=${size}`;
  const box = el("div", { class: "shot" }, el("img", { src, alt: `${record.camera_id} at ${fmt(record.actual_angle_deg)}°` }));
  if (view) {
    const dot = el("div", { class: "spot" });
    dot.style.left = `${(100 * view.u_px) / state.scan.image_width_px}%`;
    dot.style.top = `${(100 * view.v_px) / state.scan.image_height_px}%`;
    box.append(dot);
    box.dataset.u = view.u_px; box.dataset.v = view.v_px;
  }
  box.dataset.file = record.file;
  return box;
}

function showImage(angle, cameraIndex) {
  const n = state.scan.angles_deg.length;
  angle = ((angle % n) + n) % n;
  state.current = { angle, cameraIndex };
  const record = imageRecord(angle, cameraIndex);
  const pose = angle * state.scan.cameras.length + cameraIndex;
  const view = state.byPose.get(pose) || null;
  if (!record || record.status !== "verified") return renderSpot(null, `No verified image from ${state.scan.cameras[cameraIndex]} at angle ${angle} (${record ? record.status : "not planned"}).`);
  renderSpot({ view, record });
}

function renderSpot(shown, message) {
  const root = document.getElementById("spot");
  document.getElementById("spot-empty").hidden = true;
  root.replaceChildren();
  if (state.point) root.append(el("div", { class: "muted", id: "spot-point", dataset: { point: JSON.stringify(state.point) } },
    `Spot (${state.point.map((x) => fmt(x, 1)).join(", ")}) mm · seen sharp or blurred in ${state.views.length} images`));
  if (!shown) { root.append(el("p", { class: "muted" }, message)); return; }
  const { view, record } = shown;
  const main = shot(view, record);
  main.id = view && view.rank === 0 ? "best-image" : "shown-image";
  const row = el("div", { class: "bestrow" }, main);
  if (view) {
    const crop = `${api}/images/${encodeURIComponent(record.file.split("/").pop())}?u=${view.u_px.toFixed(1)}&v=${view.v_px.toFixed(1)}&half=160`;
    row.append(el("div", { class: "crop" }, el("img", { src: crop, alt: "zoomed spot" }), el("div", { class: "hint" }, "zoom on the spot")));
  }
  const title = view ? (view.rank === 0 ? "Best image of the spot" : `Image #${view.rank + 1} of the spot`) : "Image (the spot is not visible here)";
  root.append(el("h2", {}, title), row);
  const dl = el("dl", { class: "facts" });
  const fact = (k, v) => dl.append(el("dt", {}, k), el("dd", {}, v));
  fact("Camera", `${record.camera_id} (phone ${record.camera_index + 1} of ${state.scan.cameras.length})`);
  fact("Exposure angle", `${fmt(record.actual_angle_deg, 2)}° (planned ${fmt(record.planned_angle_deg, 1)}°)`);
  fact("Focus distance", `${fmt(record.focus_mm, 0)} mm`);
  if (view) {
    fact("Spot distance", `${fmt(view.depth_mm, 0)} mm, ${view.in_focus ? "sharp (in depth of field)" : "blurred (outside depth of field)"}`);
    fact("Resolution", `${fmt(view.resolution_mm_px, 3)} mm/px`);
    fact("Pixel", `(${fmt(view.u_px, 0)}, ${fmt(view.v_px, 0)}) of ${state.scan.image_width_px} × ${state.scan.image_height_px}`);
  }
  fact("File", record.file);
  root.append(dl);
  const others = state.views.slice(0, 5).filter((v) => !view || v.pose !== view.pose).slice(0, 4);
  if (others.length) {
    root.append(el("h2", {}, view && view.rank === 0 ? "Runners-up" : "Best images"));
    const grid = el("div", { class: "runners" });
    for (const v of others) {
      const rec = imageRecord(v.angle_index, v.camera_index);
      grid.append(el("div", { class: "r", onclick: () => showImage(v.angle_index, v.camera_index) }, shot(v, rec, "thumb"),
        `#${state.byPose.get(v.pose).rank + 1} ${v.camera_id} ${fmt(v.angle_deg, 1)}° · ${fmt(v.focus_mm, 0)} mm · ${fmt(v.resolution_mm_px, 3)} mm/px${v.in_focus ? "" : " · blurred"}`));
    }
    root.append(grid);
  }
  root.append(el("div", { class: "hint" }, el("kbd", {}, "←"), " ", el("kbd", {}, "→"), " neighbouring angles · ",
    el("kbd", {}, "↑"), " ", el("kbd", {}, "↓"), " neighbouring cameras"));
}

window.addEventListener("keydown", (e) => {
  if (!state.current || e.target.tagName === "INPUT") return;
  const step = { ArrowLeft: [-1, 0], ArrowRight: [1, 0], ArrowUp: [0, -1], ArrowDown: [0, 1] }[e.key];
  if (!step) return;
  e.preventDefault();
  const cam = state.current.cameraIndex + step[1];
  if (cam < 0 || cam >= state.scan.cameras.length) return;
  showImage(state.current.angle + step[0], cam);
});

// ------------------------------------------------------------------ panes: marks, gallery
function showPane(name) {
  document.querySelectorAll(".tabs button").forEach((b) => b.classList.toggle("on", b.dataset.pane === name));
  document.querySelectorAll(".pane").forEach((p) => p.classList.toggle("on", p.id === `pane-${name}`));
  if (name === "gallery") renderGallery(state.galleryCamera || 0);
}
document.querySelectorAll(".tabs button").forEach((b) => b.addEventListener("click", () => showPane(b.dataset.pane)));

function renderGallery(cameraIndex) {
  state.galleryCamera = cameraIndex;
  const root = document.getElementById("gallery");
  const pick = el("div", { class: "cams" }, el("span", { class: "muted" }, "Camera "));
  state.scan.cameras.forEach((id, c) => pick.append(el("button", { class: c === cameraIndex ? "primary" : "", onclick: () => renderGallery(c) }, id)));
  const grid = el("div", { class: "gallery", style: "grid-template-columns: repeat(6, 1fr)" });
  state.scan.angles_deg.forEach((deg, a) => {
    const rec = imageRecord(a, cameraIndex);
    const cell = el("div", {});
    if (rec && rec.status === "verified") {
      cell.append(el("img", { loading: "lazy", src: `${api}/images/${encodeURIComponent(rec.file.split("/").pop())}?size=thumb`,
        title: `${rec.camera_id} at ${fmt(rec.actual_angle_deg, 2)}°, focus ${fmt(rec.focus_mm, 0)} mm`,
        onclick: () => { showPane("spot"); showImage(a, cameraIndex); } }));
    } else cell.append(el("div", { class: "lab error", title: rec && rec.error ? rec.error : "" },
      rec ? (rec.missing_reason ? rec.missing_reason.replace("_", " ") : rec.status) : "–"));
    cell.append(el("div", { class: "lab" }, `${fmt(rec ? rec.planned_angle_deg : deg, 1)}°`));  // the plan may move angles
    grid.append(cell);
  });
  root.replaceChildren(pick, grid);
}

const marks = new MarksPane(api, markGroup, { selectSpot, point: () => state.point, redraw: () => { dirty = true; } }, hooks);

// ------------------------------------------------------------------ start
try {
  resize();
  const scanPromise = getJSON(api);
  scanPromise.then(showEnding, () => {});  // said even when the body cannot be shown
  await loadMesh();
  hooks.shown = "sharpness";
  // First paint with the mesh the QA map colours; the textured body (megabytes more) replaces
  // it once it has arrived. Without one, or if it fails, the QA map stays and the page says why.
  hooks.bodyLoaded = loadTexturedBody().then(() => true, (error) => {
    document.getElementById("stage-msg").textContent = String(error);
    hooks.error = String(error);
    return false;
  });
  state.scan = await scanPromise;
  const who = state.scan.patient ? `${personName(state.scan.patient.name)} (${state.scan.patient.patient_id}) · ` : "";
  document.getElementById("title").textContent = `${who}Scan ${state.scan.scan_id} · ${(state.scan.created_utc || "").replace("T", " ").slice(0, 16)} UTC · ${state.scan.in_progress ? "in progress" : state.scan.state}`;
  loadShares().catch((error) => { document.getElementById("stage-msg").textContent = String(error); });
  renderer.render(scene, camera);
  requestAnimationFrame(() => {
    hooks.firstPaintMs = performance.now();
    hooks.ready = true;
    frame();
  });
  marks.load().catch((error) => marks.error(String(error.message || error)));
  const wanted = new URLSearchParams(location.hash.slice(1));
  if (wanted.has("x")) selectSpot(["x", "y", "z"].map((k) => Number(wanted.get(k))));
} catch (error) {
  document.getElementById("stage-msg").textContent = String(error);
  hooks.error = String(error);
}
