// uavloc live view, the 3-D pane: the state view.js keeps (window.uavlocState), drawn with three.js
// (vendored, static/vendor/README.md). World axes: x = east, y = up, z = −north (metres from home).
// Drawn on demand (a frame, an orbit, a resize), not in a loop: an idle page costs nothing.
import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";

const COLORS = ["#d35400", "#16a085", "#8e44ad", "#c0392b", "#2980b9", "#7a8a00", "#d63384", "#34495e"];
const BG = 0xeef1f4;
const $ = (id) => document.getElementById(id);
const W = (e, n, u) => new THREE.Vector3(e, u, -n);

const box = $("view3d");
const api = { ready: false, renders: 0 };
window.uavloc3d = api;

let renderer;
try {
  renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
} catch (err) {
  $("status3d").textContent = "3-D view needs WebGL, which this browser does not offer";
  api.error = String(err);
}

if (renderer) {
  renderer.setPixelRatio(window.devicePixelRatio || 1);
  renderer.setClearColor(BG, 1);
  box.appendChild(renderer.domElement);
  const scene = new THREE.Scene();
  const camera = new THREE.PerspectiveCamera(45, 1, 0.5, 50000);
  camera.position.set(-150, 120, 150);
  const controls = new OrbitControls(camera, renderer.domElement);
  controls.enableDamping = false;
  scene.add(new THREE.AmbientLight(0xffffff, 1.6));
  const sun = new THREE.DirectionalLight(0xffffff, 1.8);
  sun.position.set(-0.5, 1.0, 0.3);
  scene.add(sun);

  const staticGroup = new THREE.Group();
  const dynamicGroup = new THREE.Group();
  scene.add(staticGroup, dynamicGroup);
  let staticKey = null;
  let extent = 100; // m: the size of the area (the grid)
  let markerM = 1.5; // m: marker size (scales with the area of the action)
  let centre = new THREE.Vector3();
  let auto = true; // follow the action until the operator orbits, pans or zooms
  let mode = "orbit";

  const disposeGroup = (g) => {
    for (const child of [...g.children]) {
      g.remove(child);
      child.traverse((o) => { if (o.geometry) o.geometry.dispose(); if (o.material) o.material.dispose(); });
    }
  };
  const line = (points, color, opts = {}) => {
    const geom = new THREE.BufferGeometry().setFromPoints(points);
    const mat = opts.dashed ? new THREE.LineDashedMaterial({ color, dashSize: opts.dash || 4, gapSize: (opts.dash || 4) * 0.6 })
      : new THREE.LineBasicMaterial({ color, transparent: opts.opacity !== undefined, opacity: opts.opacity ?? 1 });
    const obj = opts.loop ? new THREE.LineLoop(geom, mat) : new THREE.Line(geom, mat);
    if (opts.dashed) obj.computeLineDistances();
    return obj;
  };
  const userColor = (S, id) => {
    const users = (S.static && S.static.users) || [];
    return COLORS[Math.max(0, users.findIndex((u) => u.id === id)) % COLORS.length];
  };

  // walls along a ring from the ground to `top` (fences, no-fly zones)
  function walls(ring, top, color, opacity) {
    const pos = [];
    for (let i = 0; i < ring.length; i++) {
      const [e0, n0] = ring[i], [e1, n1] = ring[(i + 1) % ring.length];
      pos.push(e0, 0, -n0, e1, 0, -n1, e1, top, -n1, e0, 0, -n0, e1, top, -n1, e0, top, -n0);
    }
    const geom = new THREE.BufferGeometry();
    geom.setAttribute("position", new THREE.Float32BufferAttribute(pos, 3));
    const g = new THREE.Group();
    g.add(new THREE.Mesh(geom, new THREE.MeshBasicMaterial({ color, transparent: true, opacity, side: THREE.DoubleSide, depthWrite: false })));
    g.add(line(ring.map(([e, n]) => W(e, n, top)), color, { loop: true }));
    g.add(line(ring.map(([e, n]) => W(e, n, 0)), color, { loop: true }));
    return g;
  }

  function buildStatic(st) {
    disposeGroup(staticGroup);
    const pts = [[0, 0]];
    (st.geofence || []).forEach((p) => pts.push(p));
    (st.buildings || []).forEach((b) => b.footprint.forEach((p) => pts.push(p)));
    Object.values(st.truth || {}).forEach((p) => pts.push(p));
    const es = pts.map((p) => p[0]), ns = pts.map((p) => p[1]);
    const e0 = Math.min(...es), e1 = Math.max(...es), n0 = Math.min(...ns), n1 = Math.max(...ns);
    extent = Math.max(e1 - e0, n1 - n0, 60);
    const [a0, a1, b0, b1] = actionBox(window.uavlocState || { series: {} });
    const action = Math.max(a1 - a0, b1 - b0, 60);
    const band = st.altitude_band_m || {};
    const top = Number(band.max_m) > 0 ? Number(band.max_m) : Math.max(40, extent / 5);
    // the ground: a grid at 1, 2, 5 x 10^k m around home
    const raw = extent / 12, p10 = Math.pow(10, Math.floor(Math.log10(raw)));
    const step = [1, 2, 5, 10].map((m) => m * p10).find((s) => s >= raw);
    const half = Math.ceil(Math.max(Math.abs(e0), Math.abs(e1), Math.abs(n0), Math.abs(n1), 30) / step) * step;
    const grid = new THREE.GridHelper(2 * half, Math.round(2 * half / step), 0x9aa2a9, 0xcfd4d8);
    staticGroup.add(grid);
    if (st.geofence) staticGroup.add(walls(st.geofence, top, 0x27ae60, 0.08));
    (st.no_fly_zones || []).forEach((z) => staticGroup.add(walls(z, top, 0xc0392b, 0.18)));
    if (st.max_distance_m) {
      const c = [];
      for (let i = 0; i < 128; i++) { const a = 2 * Math.PI * i / 128; c.push(W(st.max_distance_m * Math.cos(a), st.max_distance_m * Math.sin(a), 0.05)); }
      staticGroup.add(line(c, 0x27ae60, { loop: true, dashed: true, dash: extent / 60 }));
    }
    for (const b of st.buildings || []) {
      const shape = new THREE.Shape(b.footprint.map(([e, n]) => new THREE.Vector2(e, n)));
      const geom = new THREE.ExtrudeGeometry(shape, { depth: b.height_m, bevelEnabled: false });
      geom.rotateX(-Math.PI / 2); // (e, n, h) -> (e, h, −n)
      const mesh = new THREE.Mesh(geom, new THREE.MeshLambertMaterial({ color: 0x8a939b }));
      mesh.userData.building = b.height_m;
      staticGroup.add(mesh);
      staticGroup.add(new THREE.LineSegments(new THREE.EdgesGeometry(geom), new THREE.LineBasicMaterial({ color: 0x4d565f })));
    }
    markerM = Math.max(1.5, action / 120);
  }

  // one vehicle in the colours of before fleets; a fleet's vehicles each in its colour (view.js's palette)
  const ONE = { track: 0x2f6fdb, est: 0xe67e22, leg: 0x8e44ad, body: 0x1d232a, home: 0x1d232a };
  function vehicleColors(k, fleet) {
    if (!fleet) return ONE;
    const pal = (window.uavlocPalette && window.uavlocPalette.vehicles) || ["#2f6fdb"];
    const c = new THREE.Color(pal[k % pal.length]).getHex();
    return { track: c, est: c, leg: c, body: c, home: c };
  }
  // a track's items by vehicle (view.js: the vehicle is element `at` of an item, absent: vehicle 0)
  const byVehicle = (items, at) => window.uavlocByVehicle(items, at);

  function buildDynamic(S) {
    disposeGroup(dynamicGroup);
    const f = S.frame || {}, st = S.static || {};
    const s = markerM; // marker size [m]
    const vehicles = f.vehicles && f.vehicles.length ? f.vehicles
      : [{ index: 0, vehicle: f.vehicle, waypoint: f.waypoint, health: f.health, home_enu_m: [0, 0, 0] }];
    const fleet = vehicles.length > 1;
    for (const [k, track] of byVehicle(S.series.track ? S.series.track.items : [], 4)) {
      if (track.length > 1) dynamicGroup.add(line(track.map((p) => W(p[1], p[2], p[3])), vehicleColors(k, fleet).track));
    }
    for (const [k, est] of byVehicle(S.series.est_track ? S.series.est_track.items : [], 3)) {
      if (est.length > 1) dynamicGroup.add(line(est.map((p) => W(p[0], p[1], p[2])), vehicleColors(k, fleet).est, { dashed: true, dash: s * 2 }));
    }
    for (const v of vehicles) {
      const col = vehicleColors(v.index, fleet);
      const wp = v.waypoint;
      const start = wp && (wp.from_enu_m || (v.vehicle && v.vehicle.enu_m));
      if (wp && start) {
        dynamicGroup.add(line([W(...start), W(...wp.enu_m)], col.leg, { dashed: true, dash: s }));
        const m = new THREE.Mesh(new THREE.TorusGeometry(1.2 * s, 0.25 * s, 8, 24), new THREE.MeshBasicMaterial({ color: col.leg }));
        m.position.copy(W(...wp.enu_m));
        m.rotation.x = Math.PI / 2;
        dynamicGroup.add(m);
      }
      if (v.home_enu_m && (fleet || v.index === 0)) {
        const home = new THREE.Mesh(new THREE.BoxGeometry(2 * s, 0.2, 2 * s), new THREE.MeshBasicMaterial({ color: col.home }));
        home.position.copy(fleet ? W(v.home_enu_m[0], v.home_enu_m[1], v.home_enu_m[2] + 0.1) : W(0, 0, 0.1));
        home.userData.home = v.index;
        dynamicGroup.add(home);
      }
    }
    for (const [id, p] of Object.entries(st.truth || {})) {
      const c = userColor(S, id), u = p[2];
      dynamicGroup.add(line([W(p[0] - s, p[1] - s, u + 0.1), W(p[0] + s, p[1] + s, u + 0.1)], c));
      dynamicGroup.add(line([W(p[0] - s, p[1] + s, u + 0.1), W(p[0] + s, p[1] - s, u + 0.1)], c));
    }
    for (const u of f.users || []) {
      if (!u.located) continue;
      const c = new THREE.Color(userColor(S, u.id));
      const [e, n, up] = u.enu_m;
      const ang = u.ellipse.angle_deg * Math.PI / 180;
      const ring = [];
      for (let i = 0; i < 96; i++) {
        const t = 2 * Math.PI * i / 96, x = u.ellipse.a_m * Math.cos(t), y = u.ellipse.b_m * Math.sin(t);
        ring.push([e + x * Math.cos(ang) - y * Math.sin(ang), n + x * Math.sin(ang) + y * Math.cos(ang)]);
      }
      const shape = new THREE.Shape(ring.map(([a, b]) => new THREE.Vector2(a, b)));
      const disc = new THREE.Mesh(new THREE.ShapeGeometry(shape).rotateX(-Math.PI / 2),
        new THREE.MeshBasicMaterial({ color: c, transparent: true, opacity: 0.18, side: THREE.DoubleSide, depthWrite: false }));
      disc.position.y = up + 0.15;
      dynamicGroup.add(disc);
      dynamicGroup.add(u.ambiguous ? line(ring.map(([a, b]) => W(a, b, up + 0.2)), c, { loop: true, dashed: true, dash: s })
        : line(ring.map(([a, b]) => W(a, b, up + 0.2)), c, { loop: true }));
      const pin = new THREE.Mesh(new THREE.SphereGeometry(0.9 * s, 16, 12), new THREE.MeshLambertMaterial({ color: c }));
      pin.position.copy(W(e, n, up + 0.9 * s));
      pin.userData.user = u.id;
      dynamicGroup.add(pin);
    }
    for (const veh of vehicles) {
      if (!veh.vehicle) continue;
      const col = vehicleColors(veh.index, fleet);
      const [e, n, up] = veh.vehicle.enu_m;
      const v = veh.vehicle.vel_en_mps;
      const h = veh.health && veh.health.heading_deg;
      const hdg = h != null ? h * Math.PI / 180 : (v && Math.hypot(v[0], v[1]) > 0.3 ? Math.atan2(v[0], v[1]) : 0);
      const body = new THREE.Mesh(new THREE.ConeGeometry(1.3 * s, 3.5 * s, 4), new THREE.MeshLambertMaterial({ color: col.body }));
      body.rotation.x = -Math.PI / 2; // the cone's tip points north (−z)
      const g = new THREE.Group();
      g.add(body);
      g.rotation.y = -hdg; // heading clockwise from north
      g.position.copy(W(e, n, up));
      g.userData.vehicle = veh.index;
      dynamicGroup.add(g);
      dynamicGroup.add(line([W(e, n, up), W(e, n, 0)], col.body, { opacity: 0.35 })); // drop line to the ground
      const shadow = new THREE.Mesh(new THREE.CircleGeometry(0.8 * s, 16).rotateX(-Math.PI / 2),
        new THREE.MeshBasicMaterial({ color: col.body, transparent: true, opacity: 0.25, depthWrite: false }));
      shadow.position.copy(W(e, n, 0.1));
      dynamicGroup.add(shadow);
    }
  }

  // what "fit" follows in the 2-D map too: home, the tracks, the users, the buildings, the waypoint
  function actionBox(S) {
    const es = [0], ns = [0], us = [0];
    const add = (e, n, u) => { if (isFinite(e) && isFinite(n)) { es.push(e); ns.push(n); us.push(isFinite(u) ? u : 0); } };
    const st = S.static || {}, f = S.frame || {};
    (st.buildings || []).forEach((b) => b.footprint.forEach((p) => add(p[0], p[1], b.height_m)));
    Object.values(st.truth || {}).forEach((p) => add(p[0], p[1], p[2]));
    (S.series.track ? S.series.track.items : []).forEach((p) => add(p[1], p[2], p[3]));
    (f.users || []).forEach((u) => { if (u.located) { const r = Math.min(u.r95_m, 200); add(u.enu_m[0] - r, u.enu_m[1] - r, 0); add(u.enu_m[0] + r, u.enu_m[1] + r, 0); } });
    if (f.waypoint) add(...f.waypoint.enu_m);
    (f.vehicles || []).forEach((v) => {
      if (v.waypoint) add(...v.waypoint.enu_m);
      if (v.home_enu_m) add(...v.home_enu_m);
    });
    return [Math.min(...es), Math.max(...es), Math.min(...ns), Math.max(...ns), Math.max(...us)];
  }

  function frameView(which, byHand) {
    mode = which;
    if (byHand) auto = true;
    const S = window.uavlocState || { series: {} };
    const [e0, e1, n0, n1, top] = actionBox(S);
    centre = W((e0 + e1) / 2, (n0 + n1) / 2, 0);
    // the camera's distance: the action's bounding sphere inside the narrower field of view
    resize();
    const radius = 0.5 * Math.hypot(Math.max(e1 - e0, 30), Math.max(n1 - n0, 30), Math.max(top, 10));
    const vfov = camera.fov * Math.PI / 180, hfov = 2 * Math.atan(Math.tan(vfov / 2) * camera.aspect);
    const dist = 1.05 * radius / Math.sin(Math.min(vfov, hfov) / 2);
    const h = Math.max(top, 20) / 2;
    controls.target.copy(centre).setY(which === "side" ? h : 0);
    const dir = which === "side" ? new THREE.Vector3(0, 0, 1) : which === "top" ? new THREE.Vector3(0, 1, 0.001)
      : new THREE.Vector3(-0.45, 0.6, 0.75);
    camera.position.copy(controls.target).addScaledVector(dir.normalize(), dist);
    camera.lookAt(controls.target);
    controls.update();
    for (const [id, m] of [["orbit3d", "orbit"], ["side3d", "side"], ["top3d", "top"]]) $(id).classList.toggle("on", m === which);
    draw();
  }

  function resize() {
    const r = box.getBoundingClientRect();
    const w = Math.max(1, Math.floor(r.width)), hgt = Math.max(1, Math.floor(r.height));
    renderer.setSize(w, hgt, true);
    camera.aspect = w / hgt;
    camera.updateProjectionMatrix();
  }

  function draw() {
    resize();
    renderer.render(scene, camera);
    api.renders += 1;
    document.body.dataset.renders3d = String(api.renders);
  }

  function onFrame() {
    const S = window.uavlocState;
    if (!S || !S.static || !S.static.origin) return;
    const key = JSON.stringify([S.static.geofence, S.static.buildings, S.static.no_fly_zones, S.static.max_distance_m,
      S.static.truth, S.static.altitude_band_m]);
    if (key !== staticKey) { staticKey = key; buildStatic(S.static); }
    buildDynamic(S);
    if (auto) frameView(mode); else draw();
  }

  controls.addEventListener("change", draw);
  controls.addEventListener("start", () => { auto = false; }); // the operator took the camera
  new ResizeObserver(() => draw()).observe(box);
  window.addEventListener("uavloc:frame", onFrame);
  $("orbit3d").addEventListener("click", () => frameView("orbit", true));
  $("side3d").addEventListener("click", () => frameView("side", true));
  $("top3d").addEventListener("click", () => frameView("top", true));

  // for tests and screenshots: where a point (ENU metres) lands on the canvas (CSS pixels), and
  // the canvas's pixels there
  api.project = (e, n, u) => {
    const p = W(e, n, u).project(camera);
    const r = renderer.domElement.getBoundingClientRect();
    return [(p.x + 1) / 2 * r.width, (1 - p.y) / 2 * r.height, p.z];
  };
  api.pixels = (points) => {
    const c = renderer.domElement;
    const tmp = document.createElement("canvas");
    tmp.width = c.width; tmp.height = c.height;
    const ctx = tmp.getContext("2d");
    ctx.drawImage(c, 0, 0);
    const k = c.width / c.getBoundingClientRect().width;
    return points.map(([x, y]) => Array.from(ctx.getImageData(Math.round(x * k), Math.round(y * k), 1, 1).data));
  };
  api.background = [(BG >> 16) & 255, (BG >> 8) & 255, BG & 255, 255];
  api.setView = frameView;
  api.ready = true;
  onFrame(); // a frame that came before this module loaded
  draw();
}
