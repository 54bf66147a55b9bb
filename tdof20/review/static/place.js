// The 3D view: the reconstruction's points and the placed models in the table frame (z up, mm).
// Nudges (keys, buttons), drags (TransformControls), snap and assign go to the API; each answer
// carries the new state, and the view follows it.
import * as THREE from "three";
import { OrbitControls } from "/static/OrbitControls.js";
import { TransformControls } from "/static/TransformControls.js";

const view = document.getElementById("view");
const meshes = new Map();          // object index -> THREE.Mesh
let state = null;
let selected = Number(new URLSearchParams(location.search).get("object") ?? 0);
let renderer = null, scene, camera, orbit, gizmo;

function rowMajor(m) {             // three.js keeps column-major elements
  const e = m.elements;
  return [e[0], e[4], e[8], e[12], e[1], e[5], e[9], e[13], e[2], e[6], e[10], e[14], e[3], e[7], e[11], e[15]];
}

function setPose(mesh, T) {
  const m = new THREE.Matrix4().set(...T);
  m.decompose(mesh.position, mesh.quaternion, mesh.scale);
  mesh.updateMatrixWorld(true);
}

let drawing = false;
function redraw() {
  if (!renderer || drawing) return;
  drawing = true;
  requestAnimationFrame(() => { drawing = false; renderer.render(scene, camera); });
}

function objectState(i) { return state.objects.find(o => o.index === i); }

function describe() {
  const o = objectState(selected);
  if (!o) return;
  const t = o.T_table_model;
  let txt = `object ${o.obj_id} (#${o.index}, cluster ${o.cluster}): ${o.status}` + (o.pending ? ", relabel pending" : "");
  txt += ` · at x ${t[3].toFixed(1)}, y ${t[7].toFixed(1)}, z ${t[11].toFixed(1)} mm`;
  if (o.fitness !== null && o.fitness !== undefined) txt += ` · fitness ${o.fitness.toFixed(2)}, mean distance ${o.score_mm.toFixed(2)} mm`;
  if (o.reason) txt += ` · ${o.reason}`;
  document.getElementById("objinfo").textContent = txt;
}

function apply(newState) {
  state = newState;
  for (const o of state.objects) {
    const b = document.getElementById(`badge-${o.index}`);
    if (b) { b.textContent = o.status + (o.pending ? " *" : ""); b.className = `badge ${o.status}`; }
    const mesh = meshes.get(o.index);
    if (mesh) setPose(mesh, o.T_table_model);
  }
  document.querySelectorAll("button[data-api='/api/undo']").forEach(b => {
    b.disabled = !state.undo;
    b.textContent = state.undo ? `Undo #${state.undo.id}` : "Undo";
  });
  document.querySelectorAll(".pending").forEach(p => p.hidden = !state.pending);
  describe();
  highlight();
  redraw();
}
window.reviewAfter = (j) => { if (j.state) apply(j.state); };

function highlight() {
  for (const [i, mesh] of meshes) {
    mesh.material.opacity = i === selected ? 0.75 : 0.4;
    mesh.material.emissive.setHex(i === selected ? 0x333333 : 0x000000);
  }
  if (gizmo) { const m = meshes.get(selected); if (m) gizmo.attach(m); else gizmo.detach(); }
  redraw();
  const r = document.querySelector(`input[name=obj][value="${selected}"]`);
  if (r) r.checked = true;
}

async function act(path, body, what) {
  reviewSay(`${what}...`);
  try {
    const j = await reviewApi(path, body);
    apply(j.state);
    const d = j.entry && j.entry.detail;
    const res = document.getElementById("result");
    if (j.entry && j.entry.how === "snap") {
      res.textContent = `snap: fitness ${d.fitness}, mean distance ${d.score_mm} mm, moved ${d.moved_mm} mm (${d.points} points)`;
    } else if (j.entry && j.entry.op === "assign") {
      res.textContent = `assigned to cluster ${j.entry.cluster}: fitness ${d.fitness}, mean distance ${d.score_mm} mm`;
    }
    reviewSay(`${what}: saved as entry #${j.entry.id}`);
    window.reviewLast = j;
  } catch (e) {
    reviewSay(e.message, true);
  }
}

function nudge(axis, sign) {
  const rot = axis.startsWith("r");
  const step = Number(document.getElementById(rot ? "rstep" : "tstep").value);
  return act(`/api/objects/${selected}/nudge`, {axis, amount: sign * step},
             `nudge ${axis} ${sign > 0 ? "+" : "-"}${step} ${rot ? "deg" : "mm"}`);
}
window.reviewNudge = nudge;

const KEYS = {ArrowLeft: ["x", -1], ArrowRight: ["x", 1], ArrowDown: ["y", -1], ArrowUp: ["y", 1],
              PageDown: ["z", -1], PageUp: ["z", 1], e: ["rz", -1], q: ["rz", 1], x: ["rx", -1], z: ["rx", 1],
              v: ["ry", -1], c: ["ry", 1]};
document.addEventListener("keydown", (ev) => {
  if (ev.target.closest("input[type=text], select, textarea") || ev.ctrlKey || ev.metaKey || ev.altKey) return;
  const k = ev.key.length === 1 ? ev.key.toLowerCase() : ev.key;
  if (KEYS[k]) { ev.preventDefault(); nudge(...KEYS[k]); }
  else if (k === "n") { ev.preventDefault(); document.getElementById("snap").click(); }
  else if (k === "u") { ev.preventDefault(); act("/api/undo", {}, "undo"); }
  else if (k === "t" && gizmo) gizmo.setMode("translate");
  else if (k === "r" && gizmo) gizmo.setMode("rotate");
  else if (k === "Tab") {
    ev.preventDefault();
    const ids = state.objects.map(o => o.index);
    selected = ids[(ids.indexOf(selected) + 1) % ids.length];
    describe(); highlight();
  }
});
document.querySelectorAll("[data-nudge]").forEach(b =>
  b.addEventListener("click", () => nudge(b.dataset.nudge, Number(b.dataset.sign))));
document.querySelectorAll("input[name=obj]").forEach(r =>
  r.addEventListener("change", () => { selected = Number(r.value); describe(); highlight(); }));
document.getElementById("snap").addEventListener("click", () => act(`/api/objects/${selected}/snap`, {}, "snap"));
document.getElementById("assign").addEventListener("click", () =>
  act(`/api/objects/${selected}/assign`, {cluster: Number(document.getElementById("cluster").value)}, "assign"));

const PALETTE = [0x8e99a6, 0x26c6da, 0xffca28, 0xab47bc, 0x66bb6a, 0xef5350, 0x42a5f5, 0xff7043, 0xd4e157, 0xec407a];

function startGL() {
  try {
    renderer = new THREE.WebGLRenderer({antialias: true, preserveDrawingBuffer: true});
  } catch (e) {
    renderer = null;
    document.getElementById("nogl").hidden = false;
    return false;
  }
  renderer.setPixelRatio(window.devicePixelRatio);
  renderer.setSize(view.clientWidth, view.clientHeight);
  view.appendChild(renderer.domElement);
  scene = new THREE.Scene();
  scene.background = new THREE.Color(0x1b1f24);
  camera = new THREE.PerspectiveCamera(40, view.clientWidth / view.clientHeight, 5, 5000);
  camera.up.set(0, 0, 1);
  camera.position.set(0, -520, 420);
  scene.add(new THREE.HemisphereLight(0xffffff, 0x445566, 2.2));
  const sun = new THREE.DirectionalLight(0xffffff, 1.5);
  sun.position.set(200, -300, 600);
  scene.add(sun);
  const grid = new THREE.PolarGridHelper(240, 12, 6, 64, 0x3a4a5a, 0x2c3844);
  grid.rotation.x = Math.PI / 2;
  scene.add(grid);
  scene.add(new THREE.AxesHelper(60));
  orbit = new OrbitControls(camera, renderer.domElement);
  orbit.target.set(0, 0, 50);
  orbit.update();
  gizmo = new TransformControls(camera, renderer.domElement);
  gizmo.setSpace("world");
  gizmo.addEventListener("dragging-changed", (ev) => {
    orbit.enabled = !ev.value;
    if (!ev.value && gizmo.object) {       // a drag ended: the new pose is one journal entry
      gizmo.object.updateMatrix();
      act(`/api/objects/${selected}/pose`, {T_table_model: rowMajor(gizmo.object.matrix)}, "drag");
    }
  });
  scene.add(gizmo.getHelper());
  window.addEventListener("resize", () => {
    camera.aspect = view.clientWidth / view.clientHeight;
    camera.updateProjectionMatrix();
    renderer.setSize(view.clientWidth, view.clientHeight);
    redraw();
  });
  // drawn on demand (a move, a drag, an answer), not on every animation frame: a software
  // WebGL (no GPU) would otherwise keep a core busy while the page is only open
  orbit.addEventListener("change", redraw);
  gizmo.addEventListener("change", redraw);
  redraw();
  return true;
}

async function load() {
  state = await (await fetch("/api/state")).json();
  if (startGL()) {
    const pts = await (await fetch("/api/scene3d")).json();
    const geo = new THREE.BufferGeometry();
    geo.setAttribute("position", new THREE.Float32BufferAttribute(pts.points, 3));
    const col = new Float32Array(pts.cluster.length * 3);
    const c = new THREE.Color();
    pts.cluster.forEach((j, n) => {
      if (j < 0) c.setRGB(0.33, 0.36, 0.4); else c.setHex(PALETTE[j % PALETTE.length]);
      col.set([c.r, c.g, c.b], 3 * n);
    });
    geo.setAttribute("color", new THREE.Float32BufferAttribute(col, 3));
    scene.add(new THREE.Points(geo, new THREE.PointsMaterial({size: 2.2, vertexColors: true})));
    const models = new Map();
    for (const o of state.objects) {
      if (!models.has(o.obj_id)) {
        const m = await (await fetch(`/api/model/${o.obj_id}`)).json();
        const g = new THREE.BufferGeometry();
        g.setAttribute("position", new THREE.Float32BufferAttribute(m.vertices, 3));
        g.setIndex(m.faces);
        g.computeVertexNormals();
        models.set(o.obj_id, g);
      }
      const mat = new THREE.MeshStandardMaterial({color: new THREE.Color(`rgb(${o.colour.join(",")})`),
                                                  transparent: true, opacity: 0.5, roughness: 0.5,
                                                  side: THREE.DoubleSide, depthWrite: false});
      const mesh = new THREE.Mesh(models.get(o.obj_id), mat);
      mesh.userData.index = o.index;
      scene.add(mesh);
      meshes.set(o.index, mesh);
    }
  }
  apply(state);
  window.reviewReady = true;
}
load().catch(e => reviewSay(`the 3D view could not load: ${e.message}`, true));
