// uavloc live view: draws the frames of mission/view/state.py (ENU metres from home) in an SVG map.
// Live mode: frames arrive over a WebSocket (/ws), incrementally. Log mode: /api/frame?t=... for the
// time slider. No external script, no CDN; map tiles only from the URL the operator gave.
"use strict";
(() => {
  const SVGNS = "http://www.w3.org/2000/svg";
  const COLORS = ["#d35400", "#16a085", "#8e44ad", "#c0392b", "#2980b9", "#7a8a00", "#d63384", "#34495e"];
  // a fleet's vehicles (track, estimated track, leg, marker, home); one vehicle keeps the colours of view.css
  const VEHICLE_COLORS = ["#2f6fdb", "#1e8e3e", "#b5179e", "#8d5524", "#0097a7", "#c99700", "#d62728", "#5a5a5a"];
  window.uavlocPalette = { users: COLORS, vehicles: VEHICLE_COLORS };
  // one grouping of a track's items by vehicle, for the map and the 3-D view (view3d.js)
  window.uavlocByVehicle = (items, at) => byVehicle(items, at);
  const WARN_KINDS = new Set(["return", "rtl_failed", "gnb_lost", "link_lost", "abort", "interrupted",
    "refused", "dropped", "estimator_error", "leg_timeout", "landing_timeout", "goto_failed", "breach"]);
  const NOTE_KINDS = new Set(["rtl", "stop", "landed", "end", "gnb_restored", "link_restored"]);
  const $ = (id) => document.getElementById(id);
  const S = { info: null, static: null, frame: null, series: { track: null, est_track: null, events: null } };
  const view = { cx: 0, cy: 0, scale: 2, auto: true, whole: false, w: 800, h: 600 };
  let selected = 0; // the vehicle the strip and the "next waypoint" row show (a fleet: click its legend entry)
  let frames = 0;
  window.uavlocState = S; // the 3-D view (view3d.js) draws the same state

  // ---- frames -------------------------------------------------------------------------------
  function mergeSeries(name, part) {
    const cur = S.series[name];
    if (part.from === 0 || !cur || cur.gen !== part.gen || cur.items.length !== part.from) {
      if (part.from !== 0) return false; // a gap: ask for a whole frame
      S.series[name] = { gen: part.gen, items: part.items.slice() };
    } else {
      for (const it of part.items) cur.items.push(it);
    }
    return true;
  }

  function applyFrame(f) {
    if (f.static && f.static.origin) S.static = f.static;
    let ok = true;
    for (const name of ["track", "est_track", "events"]) if (f[name]) ok = mergeSeries(name, f[name]) && ok;
    if (!S.frame || S.frame.version !== f.version) S.changedWall = performance.now();
    S.frame = f;
    frames += 1;
    document.body.dataset.frames = String(frames);
    document.body.dataset.version = String(f.version);
    render();
    window.dispatchEvent(new CustomEvent("uavloc:frame"));
    return ok;
  }

  function resetSeries() { S.series = { track: null, est_track: null, events: null }; }

  // ---- geometry -----------------------------------------------------------------------------
  function toScreen(e, n) { return [view.w / 2 + (e - view.cx) * view.scale, view.h / 2 - (n - view.cy) * view.scale]; }
  function toWorld(x, y) { return [view.cx + (x - view.w / 2) / view.scale, view.cy - (y - view.h / 2) / view.scale]; }
  function el(tag, attrs, parent) {
    const node = document.createElementNS(SVGNS, tag);
    for (const [k, v] of Object.entries(attrs || {})) node.setAttribute(k, v);
    if (parent) parent.appendChild(node);
    return node;
  }
  function clear(node) { while (node.firstChild) node.removeChild(node.firstChild); }
  function pts(list) { return list.map((p) => `${p[0]},${p[1]}`).join(" "); }
  function userColor(id) {
    const users = (S.static && S.static.users) || [];
    const i = Math.max(0, users.findIndex((u) => u.id === id));
    return COLORS[i % COLORS.length];
  }
  function vehicleColor(k) { return VEHICLE_COLORS[k % VEHICLE_COLORS.length]; }
  function fleetOf(f) { return (f && f.vehicles) || []; }
  function isFleet(f) { return fleetOf(f).length > 1; }
  function shown(f) { const vs = fleetOf(f); return vs[selected] || vs[0] || null; }
  // a track's items by vehicle: the vehicle is element `at` of an item (absent: vehicle 0)
  function byVehicle(items, at) {
    const out = new Map();
    for (const p of items) {
      const k = p.length > at ? p[at] : 0;
      if (!out.has(k)) out.set(k, []);
      out.get(k).push(p);
    }
    return out;
  }
  // a vehicle's condition in words, and whether it needs the operator's eye
  function vehicleCondition(v) {
    const h = v.health || {};
    const words = [];
    if (v.landed) words.push("landed");
    else if (v.returning) words.push("returning");
    if (v.link_lost || (v.health && h.vehicle_stale && !v.landed)) words.push("link lost");
    return { text: words.join(" · ") || (v.vehicle ? "flying" : "no telemetry"),
      warn: words.includes("link lost") || (h.battery_pct != null && h.battery_pct < 30) };
  }
  function fmt(x, nd = 1) { return x === null || x === undefined || !isFinite(x) ? "-" : Number(x).toFixed(nd); }
  function fmtT(t) {
    if (!isFinite(t)) return "-";
    const m = Math.floor(t / 60), s = t - 60 * m;
    return `${m}:${s.toFixed(1).padStart(4, "0")} (${t.toFixed(1)} s)`;
  }

  function contentBox() {
    const xs = [], ys = [];
    const add = (e, n) => { if (isFinite(e) && isFinite(n)) { xs.push(e); ys.push(n); } };
    add(0, 0);
    const st = S.static || {};
    // "fit" follows the action (track, users, waypoint, buildings); "area" shows the whole fence
    if (view.whole) {
      (st.geofence || []).forEach((p) => add(p[0], p[1]));
      (st.no_fly_zones || []).forEach((z) => z.forEach((p) => add(p[0], p[1])));
    }
    (st.buildings || []).forEach((b) => b.footprint.forEach((p) => add(p[0], p[1])));
    Object.values(st.truth || {}).forEach((p) => add(p[0], p[1]));
    const tr = S.series.track ? S.series.track.items : [];
    tr.forEach((p) => add(p[1], p[2]));
    const f = S.frame || {};
    (f.users || []).forEach((u) => { if (u.located) { const r = Math.min(u.r95_m, 200); add(u.enu_m[0] - r, u.enu_m[1] - r); add(u.enu_m[0] + r, u.enu_m[1] + r); } });
    if (f.waypoint) add(f.waypoint.enu_m[0], f.waypoint.enu_m[1]);
    fleetOf(f).forEach((v) => {
      if (v.waypoint) add(v.waypoint.enu_m[0], v.waypoint.enu_m[1]);
      if (v.home_enu_m) add(v.home_enu_m[0], v.home_enu_m[1]);
    });
    return [Math.min(...xs), Math.min(...ys), Math.max(...xs), Math.max(...ys)];
  }

  function fit() {
    const [x0, y0, x1, y1] = contentBox();
    const wm = Math.max(x1 - x0, 60), hm = Math.max(y1 - y0, 60);
    // margins: 30 px at the sides and the bottom, 45 px at the top (the buttons; the legend is under the map)
    view.scale = Math.min((view.w - 60) / wm, (view.h - 75) / hm);
    view.cx = (x0 + x1) / 2;
    view.cy = (y0 + y1) / 2 + 7.5 / view.scale;
  }

  // ---- drawing ------------------------------------------------------------------------------
  function drawGrid() {
    const g = $("grid"), labels = $("grid-labels");
    clear(g); clear(labels);
    const [e0, n1] = toWorld(0, 0), [e1, n0] = toWorld(view.w, view.h);
    const raw = 70 / view.scale;
    const p10 = Math.pow(10, Math.floor(Math.log10(raw)));
    const step = [1, 2, 5, 10].map((m) => m * p10).find((s) => s >= raw);
    const major = step * 5;
    let minor = "", maj = "";
    for (let e = Math.ceil(e0 / step) * step; e <= e1; e += step) {
      const isMajor = Math.abs(e / major - Math.round(e / major)) < 1e-6;
      const seg = `M${e},${n0}L${e},${n1}`;
      if (isMajor) maj += seg; else minor += seg;
      if (isMajor || step * view.scale > 90) {
        const [x] = toScreen(e, 0);
        if (x > 60) el("text", { x: x + 2, y: view.h - 4, class: "gridlabel" }, labels).textContent = `${+e.toFixed(6)} m E`;
      }
    }
    for (let n = Math.ceil(n0 / step) * step; n <= n1; n += step) {
      const isMajor = Math.abs(n / major - Math.round(n / major)) < 1e-6;
      const seg = `M${e0},${n}L${e1},${n}`;
      if (isMajor) maj += seg; else minor += seg;
      if (isMajor || step * view.scale > 90) {
        const [, y] = toScreen(0, n);
        if (y > 44 && y < view.h - 16) el("text", { x: 4, y: y - 2, class: "gridlabel" }, labels).textContent = `${+n.toFixed(6)} m N`;
      }
    }
    el("path", { d: minor, class: "gridline" }, g);
    el("path", { d: maj, class: "gridline major" }, g);
    el("path", { d: `M${e0},0L${e1},0M0,${n0}L0,${n1}`, class: "axis" }, g);
    $("scale").textContent = `grid ${step} m`;
  }

  // slippy-map tiles (Web Mercator) placed by a local flat-earth mapping around the origin
  const tileCache = new Map();
  function drawTiles() {
    const g = $("tiles");
    const url = S.info && S.info.tiles_url;
    if (!url || !S.static) { clear(g); tileCache.clear(); return; }
    const o = S.static.origin, R = 6378137.0, lat0 = o.lat_deg * Math.PI / 180;
    const mpp = 1 / view.scale;
    const z = Math.max(0, Math.min(20, Math.round(Math.log2(156543.034 * Math.cos(lat0) / mpp))));
    const nz = Math.pow(2, z);
    const toLL = (e, n) => [o.lat_deg + (n / R) * 180 / Math.PI, o.lon_deg + (e / (R * Math.cos(lat0))) * 180 / Math.PI];
    const toEN = (lat, lon) => [(lon - o.lon_deg) * Math.PI / 180 * R * Math.cos(lat0), (lat - o.lat_deg) * Math.PI / 180 * R];
    const tx = (lon) => (lon + 180) / 360 * nz;
    const ty = (lat) => { const r = lat * Math.PI / 180; return (1 - Math.log(Math.tan(r) + 1 / Math.cos(r)) / Math.PI) / 2 * nz; };
    const tileLat = (y) => Math.atan(Math.sinh(Math.PI * (1 - 2 * y / nz))) * 180 / Math.PI;
    const tileLon = (x) => x / nz * 360 - 180;
    const [e0, n1] = toWorld(0, 0), [e1, n0] = toWorld(view.w, view.h);
    const [latN, lonW] = toLL(e0, n1), [latS, lonE] = toLL(e1, n0);
    const x0 = Math.floor(tx(lonW)), x1 = Math.floor(tx(lonE)), y0 = Math.floor(ty(latN)), y1 = Math.floor(ty(latS));
    const want = new Set();
    if ((x1 - x0 + 1) * (y1 - y0 + 1) <= 80) {
      for (let x = x0; x <= x1; x++) for (let y = y0; y <= y1; y++) {
        if (y < 0 || y >= nz) continue;
        const xw = ((x % nz) + nz) % nz;
        const key = `${z}/${xw}/${y}`;
        want.add(key);
        const [ea, na] = toEN(tileLat(y), tileLon(x)), [eb, nb] = toEN(tileLat(y + 1), tileLon(x + 1));
        const [sx0, sy0] = toScreen(ea, na), [sx1, sy1] = toScreen(eb, nb);
        let img = tileCache.get(key);
        if (!img) {
          img = el("image", { href: url.replace("{z}", z).replace("{x}", xw).replace("{y}", y).replace("{s}", "a"), preserveAspectRatio: "none" }, g);
          tileCache.set(key, img);
        }
        img.setAttribute("x", sx0); img.setAttribute("y", sy0);
        img.setAttribute("width", sx1 - sx0 + 0.5); img.setAttribute("height", sy1 - sy0 + 0.5);
      }
    }
    for (const [key, img] of tileCache) if (!want.has(key)) { img.remove(); tileCache.delete(key); }
  }

  function drawArea() {
    const a = $("area"), b = $("buildings");
    clear(a); clear(b);
    const st = S.static;
    if (!st || !st.origin) return;
    if (st.max_distance_m) el("circle", { cx: 0, cy: 0, r: st.max_distance_m, class: "maxdist" }, a);
    if (st.geofence) el("polygon", { points: pts(st.geofence), class: "fence", id: "geofence" }, a);
    (st.no_fly_zones || []).forEach((z, i) => el("polygon", { points: pts(z), class: "nofly", "data-zone": i }, a));
    (st.buildings || []).forEach((bd) => {
      const poly = el("polygon", { points: pts(bd.footprint), class: "building" }, b);
      el("title", {}, poly).textContent = `building ${bd.height_m} m`;
    });
  }

  function marker(shape, x, y, attrs, parent) {
    if (shape === "cross") {
      return el("path", { d: `M${x - 6},${y - 6}L${x + 6},${y + 6}M${x - 6},${y + 6}L${x + 6},${y - 6}`, ...attrs }, parent);
    }
    if (shape === "square") return el("rect", { x: x - 5, y: y - 5, width: 10, height: 10, ...attrs }, parent);
    return el("circle", { cx: x, cy: y, r: 4, ...attrs }, parent);
  }

  // vehicle k's lines: vehicle 0's are the page's #track, #est-track and #leg; the others' are made
  // in #fleet-lines; in a fleet each in its vehicle's colour, one vehicle in view.css's colours
  function vehicleLines(k) {
    if (k === 0) return { track: $("track"), est: $("est-track"), leg: $("leg") };
    const g = $("fleet-lines");
    let set = g.querySelector(`g[data-vehicle="${k}"]`);
    if (!set) {
      set = el("g", { "data-vehicle": k }, g);
      el("polyline", { class: "track" }, set);
      el("polyline", { class: "est-track" }, set);
      el("line", { class: "leg", visibility: "hidden" }, set);
    }
    const [track, est, leg] = set.children;
    return { track, est, leg };
  }

  function drawLeg(leg, v) {
    const wp = v && v.waypoint;
    const start = wp && (wp.from_enu_m || (v.vehicle && v.vehicle.enu_m));
    if (wp && start) {
      leg.setAttribute("x1", start[0]); leg.setAttribute("y1", start[1]);
      leg.setAttribute("x2", wp.enu_m[0]); leg.setAttribute("y2", wp.enu_m[1]);
      leg.setAttribute("visibility", "visible");
    } else leg.setAttribute("visibility", "hidden");
  }

  function drawDynamic() {
    const f = S.frame;
    const vehicles = fleetOf(f), fleet = isFleet(f);
    const tracks = byVehicle(S.series.track ? S.series.track.items : [], 4);
    const ests = byVehicle(S.series.est_track ? S.series.est_track.items : [], 3);
    const n = Math.max(1, vehicles.length, ...[...tracks.keys(), ...ests.keys()].map((k) => k + 1));
    for (const set of [...$("fleet-lines").children]) if (Number(set.dataset.vehicle) >= n) set.remove();
    for (let k = 0; k < n; k++) {
      const lines = vehicleLines(k);
      lines.track.setAttribute("points", (tracks.get(k) || []).map((p) => `${p[1]},${p[2]}`).join(" "));
      lines.est.setAttribute("points", (ests.get(k) || []).map((p) => `${p[0]},${p[1]}`).join(" "));
      drawLeg(lines.leg, k === 0 && !vehicles.length ? f : vehicles[k]);
      // the colour as a style (view.css's class rules win over presentation attributes)
      for (const node of [lines.track, lines.est, lines.leg]) node.style.stroke = fleet ? vehicleColor(k) : "";
    }

    const eg = $("ellipses"), mk = $("markers");
    clear(eg); clear(mk);
    if (!fleet) marker("square", ...toScreen(0, 0), { class: "home" }, mk);
    else {
      vehicles.forEach((v) => {
        if (!v.home_enu_m) return;
        const sq = marker("square", ...toScreen(v.home_enu_m[0], v.home_enu_m[1]), { class: "home", "data-home": v.index }, mk);
        sq.style.stroke = vehicleColor(v.index);
        el("title", {}, sq).textContent = `home of ${v.id}`;
      });
    }
    const st = S.static || { truth: {} };
    for (const [id, p] of Object.entries(st.truth || {})) {
      marker("cross", ...toScreen(p[0], p[1]), { class: "truth", stroke: userColor(id), "data-truth": id }, mk);
    }
    for (const u of (f && f.users) || []) {
      if (!u.located) continue;
      const c = userColor(u.id);
      const [e, n] = u.enu_m;
      el("ellipse", {
        cx: e, cy: n, rx: u.ellipse.a_m, ry: u.ellipse.b_m,
        transform: `rotate(${u.ellipse.angle_deg} ${e} ${n})`,
        class: "ellipse" + (u.ambiguous ? " ambiguous" : ""), fill: c, stroke: c,
        "data-user": u.id, "data-r95-m": u.r95_m, "data-e": e, "data-n": n, "data-ambiguous": u.ambiguous,
      }, eg);
      const [x, y] = toScreen(e, n);
      marker("dot", x, y, { fill: c, stroke: "#fff", "data-marker": u.id }, mk);
      el("text", { x: x + 7, y: y - 7, class: "ulabel", fill: c }, mk).textContent = u.id + (u.ambiguous ? " ?" : "");
    }
    const each = vehicles.length ? vehicles : [{ index: 0, vehicle: f && f.vehicle, waypoint: f && f.waypoint }];
    for (const veh of each) {
      const k = veh.index, wp = veh.waypoint;
      if (wp) {
        const [x, y] = toScreen(wp.enu_m[0], wp.enu_m[1]);
        const ring = el("circle", { cx: x, cy: y, r: 7, class: "wp", ...(k === 0 ? { id: "waypoint" } : {}), "data-waypoint": k }, mk);
        const cross = el("path", { d: `M${x - 10},${y}L${x + 10},${y}M${x},${y - 10}L${x},${y + 10}`, class: "wp" }, mk);
        if (fleet) ring.style.stroke = cross.style.stroke = vehicleColor(k);
      }
    }
    for (const veh of each) {
      if (!veh.vehicle) continue;
      const k = veh.index;
      const [x, y] = toScreen(veh.vehicle.enu_m[0], veh.vehicle.enu_m[1]);
      const v = veh.vehicle.vel_en_mps;
      const heading = v && Math.hypot(v[0], v[1]) > 0.3 ? Math.atan2(v[0], v[1]) * 180 / Math.PI : 0;
      const attrs = { d: "M0,-11L7,8L0,4L-7,8Z", class: "vehicle", transform: `translate(${x} ${y}) rotate(${heading})` };
      if (k === 0) attrs.id = "vehicle";
      if (fleet) attrs["data-vehicle"] = k;
      const body = el("path", attrs, mk);
      if (fleet) body.style.fill = vehicleColor(k);
      if (fleet) el("text", { x: x + 9, y: y + 14, class: "vlabel", fill: vehicleColor(k), "data-vehicle-label": k }, mk).textContent = veh.id;
    }
  }

  // a fleet: one legend entry per vehicle (its colour, id and health); click one to show it in the strip
  function drawFleetLegend() {
    const f = S.frame, box = $("fleet-legend");
    const fleet = isFleet(f);
    $("legend").classList.toggle("fleet", fleet);
    box.hidden = !fleet;
    if (!fleet) { clear(box); return; }
    const vehicles = fleetOf(f);
    while (box.children.length > vehicles.length) box.lastChild.remove();
    vehicles.forEach((v, i) => {
      let item = box.children[i];
      if (!item) {
        item = document.createElement("button");
        item.type = "button";
        item.className = "vitem";
        item.addEventListener("click", () => { selected = Number(item.dataset.vehicle); render(); });
        box.appendChild(item);
      }
      const h = v.health || {};
      const cond = vehicleCondition(v);
      const parts = [v.id];
      if (h.battery_pct != null) parts.push(`${fmt(h.battery_pct, 0)} %`);
      if (h.flight_mode) parts.push(h.flight_mode);
      parts.push(cond.text);
      item.dataset.vehicle = String(v.index);
      item.dataset.condition = cond.text;
      item.classList.toggle("warn", cond.warn);
      item.classList.toggle("on", v.index === (shown(f) || {}).index);
      clear(item);
      const sw = document.createElement("i");
      sw.className = "sw vsw";
      sw.style.borderColor = vehicleColor(v.index);
      item.append(sw, parts.join(" · "));
      item.title = `${v.id}: click to show it in the vehicle strip`;
    });
  }

  function drawPanel() {
    const f = S.frame, st = S.static || {};
    if (!f) return;
    $("title").textContent = (S.info && S.info.title) || "uavloc";
    $("m-state").textContent = f.state + (f.status ? ` — ${f.status}` : "");
    $("m-t").textContent = fmtT(f.t);
    $("m-flown").textContent = `${fmt(f.flown_m, 0)} m`;
    $("m-meas").textContent = String(f.measurements);
    $("m-kf").textContent = String(f.keyframes);
    const veh = shown(f), fleet = isFleet(f);
    const wp = veh ? veh.waypoint : f.waypoint;
    $("h-vehicle").textContent = fleet && veh ? ` · ${veh.id}` : "";
    $("h-vehicle").style.color = fleet && veh ? vehicleColor(veh.index) : "";
    $("m-wp").textContent = wp ? (fleet ? `${veh.id} ` : "") + `leg ${wp.leg}: (${fmt(wp.enu_m[0])}, ${fmt(wp.enu_m[1])}, ${fmt(wp.enu_m[2])}) m` +
      (wp.planner ? ` · ${wp.planner}` : "") : "-";
    drawTarget(f.target);
    drawHealth();
    const tb = $("users").tBodies[0];
    clear(tb);
    for (const u of f.users) {
      const tr = tb.insertRow();
      tr.dataset.user = u.id;
      const id = tr.insertCell();
      id.className = "uid";
      id.style.color = userColor(u.id);
      id.textContent = u.id;
      if (u.ambiguous) {
        const b = document.createElement("span");
        b.className = "badge"; b.textContent = "ambig."; b.title = "ambiguous: a mirror solution fits about as well";
        id.append(" ", b);
      }
      const cells = u.located
        ? [fmt(u.enu_m[0]), fmt(u.enu_m[1]), fmt(u.sigma_m, 2), fmt(u.r95_m, 2), String(u.measurements),
          u.error_m !== undefined ? fmt(u.error_m, 2) : "-"]
        : ["-", "-", "-", "-", String(u.measurements), "-"];
      const names = ["east", "north", "sigma", "r95", "meas", "error"];
      cells.forEach((txt, i) => { const c = tr.insertCell(); c.className = names[i]; c.textContent = txt; });
      if (u.located) tr.cells[4].dataset.r95M = String(u.r95_m);
    }
    const ol = $("events");
    const evs = S.series.events ? S.series.events.items : [];
    const fleetKey = fleetOf(f).map((v) => v.id).join("\n");
    if (ol.dataset.count !== String(evs.length) || ol.dataset.gen !== String(S.series.events && S.series.events.gen)
        || ol.dataset.fleet !== fleetKey) {
      clear(ol);
      for (let i = evs.length - 1; i >= 0; i--) {
        const ev = evs[i];
        const li = document.createElement("li");
        if (WARN_KINDS.has(ev.kind)) li.className = "warn";
        else if (NOTE_KINDS.has(ev.kind)) li.className = "note";
        const t = document.createElement("span");
        t.className = "t"; t.textContent = `${fmt(ev.t, 1)} s`;
        li.append(t);
        const who = isFleet(f) && ev.vehicle != null ? fleetOf(f)[ev.vehicle] : null;
        if (who) {
          const b = document.createElement("span");
          b.className = "vtag"; b.style.color = vehicleColor(who.index); b.textContent = who.id;
          li.dataset.vehicle = String(who.index);
          li.append(b, " ");
        }
        li.append(ev.message);
        ol.appendChild(li);
      }
      ol.dataset.count = String(evs.length);
      ol.dataset.fleet = fleetKey;
      ol.dataset.gen = String(S.series.events && S.series.events.gen);
    }
  }

  // the stop rule's line: the radius, the users whose printed r95 is within it, what the stop judged
  function drawTarget(tg) {
    const td = $("m-target");
    if (!tg) { td.textContent = "-"; td.className = ""; return; }
    let text = `${tg.radius_m} m: ${tg.within.length}/${tg.users} users within`;
    if (tg.stop) {
      const worst = Math.max(...Object.values(tg.stop.r95_m));
      text += ` · stop at ${fmt(tg.stop.t, 1)} s judged r95 ${fmt(worst, 2)} m`;
    }
    td.textContent = text;
    td.dataset.within = String(tg.within.length);
    td.className = tg.within.length === tg.users ? "met" : "unmet";
  }

  const HEALTH = [
    ["h-rel-alt", (h) => h.rel_alt_m, (v) => `${fmt(v, 1)} m`],
    ["h-amsl", (h) => h.alt_amsl_m, (v) => `${fmt(v, 1)} m`],
    ["h-gs", (h) => h.groundspeed_mps, (v) => `${fmt(v, 1)} m/s`],
    ["h-climb", (h) => h.climb_mps, (v) => `${fmt(v, 1)} m/s`],
    ["h-hdg", (h) => h.heading_deg, (v) => `${fmt(v, 0)}°`],
    ["h-bat", (h) => h.battery_pct, (v, h) => `${fmt(v, 0)} %` + (h.battery_voltage_v != null ? ` · ${fmt(h.battery_voltage_v, 2)} V` : ""),
      (h) => h.battery_pct != null && h.battery_pct < 30],
    ["h-mode", (h) => h.flight_mode, (v) => String(v)],
    ["h-armed", (h) => h.armed, (v) => (v ? "armed" : "disarmed")],
    ["h-gps", (h) => h.gps_fix, (v, h) => `${v}` + (h.gps_satellites != null ? ` · ${h.gps_satellites} sats` : ""),
      (h) => h.gps_fix_type != null && h.gps_fix_type < 3],
    ["h-veh-age", (h) => h.vehicle_age_s, (v) => `${fmt(v, 1)} s`, (h) => h.vehicle_stale],
    ["h-gnb-age", (h) => h.gnb_age_s, (v) => `${fmt(v, 1)} s`, (h) => h.gnb_stale],
    ["h-rate", (h) => h.measurements_per_min, (v) => `${v} /min`],
  ];

  // live: seconds (wall) since the state last changed, when nothing came for longer than 3 s
  function idleWall() {
    const f = S.frame;
    if (!f || !S.info || S.info.mode !== "live" || f.ended || !S.changedWall) return 0;
    const s = (performance.now() - S.changedWall) / 1000;
    return s > 3 ? s : 0;
  }

  function drawHealth() {
    const veh = shown(S.frame);
    const health = veh ? veh.health : S.frame && S.frame.health;
    const h = health || {};
    const idle = idleWall();
    for (const [id, get, show, warn] of HEALTH) {
      const v = get(h);
      const node = $(id);
      const known = v !== null && v !== undefined;
      let text = known ? show(v, h) : "-";
      let bad = known && warn ? Boolean(warn(h)) : false;
      if (idle && (id === "h-veh-age" || id === "h-gnb-age")) { text += ` +${idle.toFixed(0)} s idle`; bad = true; }
      node.textContent = text;
      node.dataset.value = known ? String(v) : "";
      node.parentElement.classList.toggle("warn", bad || ((id === "h-veh-age" || id === "h-gnb-age") && !known && !!S.frame && !!health));
    }
  }
  setInterval(() => { if (idleWall()) drawHealth(); }, 1000);

  function render() {
    const svg = $("map");
    const r = svg.getBoundingClientRect();
    view.w = r.width || 800; view.h = r.height || 600;
    if (view.auto && S.static && S.static.origin) fit();
    $("world").setAttribute("transform",
      `translate(${view.w / 2} ${view.h / 2}) scale(${view.scale} ${-view.scale}) translate(${-view.cx} ${-view.cy})`);
    drawTiles();
    drawGrid();
    drawArea();
    drawDynamic();
    drawFleetLegend();
    drawPanel();
  }

  // ---- interaction --------------------------------------------------------------------------
  function setupInteraction() {
    const svg = $("map");
    svg.addEventListener("wheel", (ev) => {
      ev.preventDefault();
      const r = svg.getBoundingClientRect();
      const [e, n] = toWorld(ev.clientX - r.left, ev.clientY - r.top);
      const k = Math.exp(-ev.deltaY * 0.0015);
      view.scale = Math.min(Math.max(view.scale * k, 0.005), 500);
      const [e2, n2] = toWorld(ev.clientX - r.left, ev.clientY - r.top);
      view.cx += e - e2; view.cy += n - n2;
      view.auto = false;
      render();
    }, { passive: false });
    let drag = null;
    svg.addEventListener("pointerdown", (ev) => { drag = [ev.clientX, ev.clientY]; svg.classList.add("dragging"); svg.setPointerCapture(ev.pointerId); });
    svg.addEventListener("pointermove", (ev) => {
      if (!drag) return;
      view.cx -= (ev.clientX - drag[0]) / view.scale; view.cy += (ev.clientY - drag[1]) / view.scale;
      drag = [ev.clientX, ev.clientY];
      view.auto = false;
      render();
    });
    const end = () => { drag = null; svg.classList.remove("dragging"); };
    svg.addEventListener("pointerup", end);
    svg.addEventListener("pointercancel", end);
    $("fit").addEventListener("click", () => { view.auto = true; view.whole = false; render(); });
    $("whole").addEventListener("click", () => { view.auto = true; view.whole = true; render(); });
    window.addEventListener("resize", render);
  }

  function setConn(cls, text) { const c = $("conn"); c.className = "conn " + cls; c.textContent = text; }

  // ---- live mode ----------------------------------------------------------------------------
  function connectLive() {
    const proto = location.protocol === "https:" ? "wss:" : "ws:";
    const ws = new WebSocket(`${proto}//${location.host}/ws`);
    let ended = false;
    ws.onopen = () => { resetSeries(); setConn("live", "live"); };
    ws.onmessage = (msg) => {
      const f = JSON.parse(msg.data);
      if (!applyFrame(f)) { ws.close(); return; }
      ws.send("ack"); // the server sends the next frame after this: a slow page skips frames
      if (f.ended) {
        ended = true;
        setConn("ended", `mission ended${f.status ? ": " + f.status : ""}${f.reason ? " (" + f.reason + ")" : ""}`);
      }
    };
    ws.onclose = () => {
      if (ended) return;
      setConn("lost", "connection lost: retrying");
      setTimeout(connectLive, 2000);
    };
  }

  // ---- log mode (time slider) ---------------------------------------------------------------
  function setupLog(info) {
    $("timebar").hidden = false;
    setConn("ended", "recorded mission");
    const slider = $("slider");
    slider.max = String(info.t_end_s);
    slider.value = String(info.t_end_s);
    let inFlight = false, pending = null;
    async function load(t) {
      if (inFlight) { pending = t; return; }
      inFlight = true;
      try {
        const resp = await fetch(`api/frame?t=${encodeURIComponent(t)}`, { credentials: "same-origin" });
        if (resp.status === 429) {
          // over the server's request budget: ask again (the newest time asked) after Retry-After
          const wait_s = Number(resp.headers.get("Retry-After")) || 1;
          await new Promise((done) => setTimeout(done, 1000 * wait_s));
          if (pending === null) pending = t;
          return;
        }
        if (!resp.ok) throw new Error(`frame: HTTP ${resp.status}`);
        resetSeries();
        applyFrame(await resp.json());
        $("slider-t").textContent = `t = ${fmtT(Number(t))} of ${fmt(info.t_end_s, 1)} s`;
        document.body.dataset.sliderT = String(t);
      } catch (err) {
        setConn("lost", String(err));
      } finally {
        inFlight = false;
        if (pending !== null) { const p = pending; pending = null; load(p); }
      }
    }
    slider.addEventListener("input", () => load(slider.value));
    let timer = null;
    $("play").addEventListener("click", () => {
      if (timer) { clearInterval(timer); timer = null; $("play").textContent = "play"; return; }
      if (Number(slider.value) >= info.t_end_s) slider.value = "0";
      $("play").textContent = "pause";
      const step = Math.max(info.t_end_s / 300, 0.2);
      timer = setInterval(() => {
        const t = Math.min(Number(slider.value) + step, info.t_end_s);
        slider.value = String(t);
        load(slider.value);
        if (t >= info.t_end_s) { clearInterval(timer); timer = null; $("play").textContent = "play"; }
      }, 100);
    });
    load(slider.value);
  }

  async function start() {
    setupInteraction();
    const resp = await fetch("api/info", { credentials: "same-origin" });
    if (!resp.ok) { setConn("lost", `HTTP ${resp.status}`); return; }
    S.info = await resp.json();
    document.title = S.info.title;
    if (S.info.mode === "log") setupLog(S.info); else connectLive();
  }

  document.addEventListener("DOMContentLoaded", start);
})();
