// The 3D view: the reconstruction's points and the placed models in the table frame (z up, mm).
// Nudges (keys, buttons), drags (TransformControls), a typed pose, snap and assign go to the API;
// each answer carries the new state (and the gates' figures), and the view follows it: the 3D
// view, the outlines over two or three frames' images, the typed-pose box. A pose the gates
// refuse is not journalled: a nudge's or drag's is kept as the object's draft.
import * as THREE from "three";
import { OrbitControls } from "/static/OrbitControls.js";
import { TransformControls } from "/static/TransformControls.js";

const view = document.getElementById("view");
const meshes = new Map();          // object index -> THREE.Mesh
let state = null;
let selected = Number(new URLSearchParams(location.search).get("object") ?? 0);
let renderer = null, scene, camera, orbit, gizmo;
const busy = () => reviewInflight > 0;

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
  let txt = `object ${o.obj_id} (#${o.index}, cluster ${o.cluster}): ${o.draft ? "draft (not saved)" : o.status}` +
            (o.pending ? ", relabel pending" : "");
  txt += ` · at x ${t[3].toFixed(1)}, y ${t[7].toFixed(1)}, z ${t[11].toFixed(1)} mm`;
  const f = o.figures;   // recomputed for the pose shown: every nudge, drag, typed pose
  if (f) txt += ` · here: fitness ${f.fitness.toFixed(2)}, mean distance ${f.score_mm.toFixed(2)} mm (${f.points} points)`;
  if (o.reason && !o.draft) txt += ` · ${o.reason}`;
  if (o.flag) txt += ` · ${o.flag}`;
  document.getElementById("objinfo").textContent = txt;
  const g = document.getElementById("gate");
  g.textContent = o.draft ? o.draft.reason : "";
  g.className = o.draft ? "small err" : "small";
  document.getElementById("discard").hidden = !o.draft;
  const typed = document.getElementById("typed");
  if (document.activeElement !== typed) typed.value = poseText(t);
}

// ---- the typed pose: x y z (mm), rz ry rx (deg; R = Rz Ry Rx), in the table frame
const DEG = Math.PI / 180;
function poseText(T) {
  const rz = Math.atan2(T[4], T[0]), ry = Math.asin(Math.max(-1, Math.min(1, -T[8]))), rx = Math.atan2(T[9], T[10]);
  return [T[3], T[7], T[11]].map(v => v.toFixed(1)).concat([rz, ry, rx].map(v => (v / DEG).toFixed(2))).join(" ");
}
function parsePose(text) {
  const v = text.trim().split(/[\s,]+/).map(Number);
  if (v.length === 16 && v.every(Number.isFinite)) return v;
  if (v.length !== 6 || !v.every(Number.isFinite)) throw new Error("type 6 numbers (x y z mm, rz ry rx deg) or 16 (a 4x4 pose, row by row)");
  const [x, y, z] = v, [a, b, c] = v.slice(3).map(d => d * DEG);
  const ca = Math.cos(a), sa = Math.sin(a), cb = Math.cos(b), sb = Math.sin(b), cc = Math.cos(c), sc = Math.sin(c);
  return [ca * cb, ca * sb * sc - sa * cc, ca * sb * cc + sa * sc, x,
          sa * cb, sa * sb * sc + ca * cc, sa * sb * cc - ca * sc, y,
          -sb, cb * sc, cb * cc, z, 0, 0, 0, 1];
}

// ---- the outlines over the check frames' images
let views = 0;
function refreshViews() {
  views++;
  document.querySelectorAll("#views img").forEach(img => {
    img.src = `/img/frame/${img.dataset.arm}/${img.dataset.step}/opaque.png?object=${selected}&v=${views}`;
  });
}
window.reviewViews = () => views;

function apply(newState) {
  state = newState;
  for (const o of state.objects) {
    const b = document.getElementById(`badge-${o.index}`);
    if (b) { b.textContent = (o.draft ? "draft" : o.status) + (o.pending ? " *" : ""); b.className = `badge ${o.draft ? "draft" : o.status}`; }
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
  refreshViews();
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

function gateText(g) {
  const p = g && g.place, v = g && g.visible;
  let t = "";
  if (p && p.fitness !== undefined) t += `fitness ${p.fitness.toFixed(2)}, mean distance ${p.score_mm.toFixed(2)} mm` +
      (p.fit_score_mm !== undefined ? ` (the place stage's fit from here: ${p.fit_score_mm.toFixed(2)} mm)` : "");
  if (v && v.agree !== undefined) t += ` · in the images ${(100 * v.agree).toFixed(0)} % agree with the opaque depth`;
  return t;
}

function showAlternatives(alts, chosenTurn) {
  const box = document.getElementById("alternatives"), tab = document.getElementById("alts");
  box.hidden = !alts || !alts.length;
  tab.innerHTML = "<tr><th>turn</th><th>fitness</th><th>mean distance</th><th>off the images</th><th></th></tr>";
  for (const a of alts || []) {
    const tr = document.createElement("tr");
    const off = a.disagree === null || a.disagree === undefined ? "–" : `${(100 * a.disagree).toFixed(1)} %`;
    tr.innerHTML = `<td>${a.turn_deg}°</td><td>${a.fitness.toFixed(2)}</td><td>${a.score_mm.toFixed(2)} mm</td><td>${off}</td><td></td>`;
    tr.title = a.reason || "";
    const td = tr.lastChild;
    if (chosenTurn === a.turn_deg) td.textContent = "chosen";
    else if (!a.reason) {
      const b = document.createElement("button");
      b.textContent = "Use"; b.dataset.turn = a.turn_deg;
      // the alternative's own pose, through the gates as a typed one
      b.addEventListener("click", () => act(`/api/objects/${selected}/pose`, {T_table_model: a.T_table_model, how: "set"},
                                            `the alternative turned ${a.turn_deg}°`));
      td.appendChild(b);
    } else td.textContent = "refused";
    tab.appendChild(tr);
  }
}

async function act(path, body, what) {
  reviewSay(`${what}...`);
  const res = document.getElementById("result");
  try {
    const j = await reviewApi(path, body);
    apply(j.state);
    const d = j.entry && j.entry.detail;
    showAlternatives(j.alternatives || [], j.entry && d ? d.turn_deg : null);
    if (j.entry && j.entry.how === "snap") {
      res.textContent = `snap: fitness ${d.fitness}, mean distance ${d.score_mm} mm, moved ${d.moved_mm} mm (${d.points} points)` +
          (d.alternatives && d.alternatives.length > 1 ? `; turned ${d.turn_deg}° of ${d.alternatives.length} alternatives` : "");
    } else if (j.entry && j.entry.op === "assign") {
      res.textContent = `assigned to cluster ${j.entry.cluster}: fitness ${d.fitness}, mean distance ${d.score_mm} mm`;
    } else if (j.entry && j.entry.op === "place") {
      res.textContent = `saved: ${gateText(d.gates)}`;
    } else if (!j.entry && j.alternatives) {
      res.textContent = j.reason;
    }
    reviewSay(j.entry ? `${what}: saved as entry #${j.entry.id}` : `${what}: ${j.reason || "nothing saved"}`, !j.entry);
    window.reviewLast = j;
  } catch (e) {
    if (e.stale) return;
    const j = e.body || {};
    if (j.state) apply(j.state);
    if (j.gates && j.gates.alternatives) showAlternatives(j.gates.alternatives, null);
    res.textContent = j.gates ? gateText(j.gates) : "";
    reviewSay(e.message, true);
    window.reviewLast = {entry: null, refused: e.message, draft: !!j.draft, gates: j.gates};
  } finally {
    window.reviewAnswers = (window.reviewAnswers || 0) + 1;
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
  if (ev.repeat && busy()) return;   // a held key does not queue nudges faster than they are judged
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
    describe(); highlight(); refreshViews(); showAlternatives([], null);
  }
});
document.querySelectorAll("[data-nudge]").forEach(b =>
  b.addEventListener("click", () => nudge(b.dataset.nudge, Number(b.dataset.sign))));
document.querySelectorAll("input[name=obj]").forEach(r =>
  r.addEventListener("change", () => { selected = Number(r.value); describe(); highlight(); refreshViews(); showAlternatives([], null); }));
document.getElementById("snap").addEventListener("click", () => act(`/api/objects/${selected}/snap`, {}, "snap"));
document.getElementById("discard").addEventListener("click", () => act(`/api/objects/${selected}/discard`, {}, "discard the draft"));
function setTyped() {
  let T;
  try { T = parsePose(document.getElementById("typed").value); } catch (e) { reviewSay(e.message, true); return; }
  return act(`/api/objects/${selected}/pose`, {T_table_model: T, how: "set"}, "typed pose");
}
document.getElementById("settyped").addEventListener("click", setTyped);
document.getElementById("typed").addEventListener("keydown", (ev) => { if (ev.key === "Enter") { ev.preventDefault(); setTyped(); } });
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
  reviewTake(state);
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
