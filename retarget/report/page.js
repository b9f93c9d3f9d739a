// mocaptk report page: draws the embedded report data with plotly (offline bundle above).
// Rig frame: X = subject's left, Y up, Z forward, mm. Exposes window.mocaptkReport for tests.
(function () {
  "use strict";
  const started = performance.now();
  const data = JSON.parse(document.getElementById("report-data").textContent);
  const M = data.markers;
  const N = M.labels.length;
  const NC = M.captured;
  const clusters = data.clusters || [];
  const errors = data.errors || [];
  const mesh = data.mesh;
  const character = data.character ? decodeCharacter(data.character) : null;  // retarget: beside the actor
  const plane = data.mirror_plane;
  const gd = document.getElementById("scene");
  const GAP = -32768;

  const clips = (data.clips || []).map(function (c) {
    const raw = atob(c.positions);
    const bytes = new Uint8Array(raw.length);
    for (let i = 0; i < raw.length; i++) bytes[i] = raw.charCodeAt(i);
    return Object.assign({}, c, {track: new Int16Array(bytes.buffer)});  // little-endian (x86, ARM)
  });

  // The character's shapes (S x V x 3 int16 offsets) and replayed weights (frames x S).
  function decodeCharacter(c) {
    const raw = atob(c.shapes);
    const bytes = new Uint8Array(raw.length);
    for (let i = 0; i < raw.length; i++) bytes[i] = raw.charCodeAt(i);
    return Object.assign({}, c, {deltas: new Int16Array(bytes.buffer)});
  }

  // Character vertices at the replay frame: neutral + sum_k w_k delta_k.
  function characterVertices(frame) {
    const V = character.vertices.length, w = character.weights[frame] || [], r = character.resolution_mm;
    const x = new Float64Array(V), y = new Float64Array(V), z = new Float64Array(V);
    for (let v = 0; v < V; v++) { const p = character.vertices[v]; x[v] = p[0]; y[v] = p[1]; z[v] = p[2]; }
    for (let k = 0; k < w.length; k++) {
      if (!w[k]) continue;
      const base = k * V * 3, s = w[k] * r;
      for (let v = 0; v < V; v++) {
        x[v] += s * character.deltas[base + 3 * v]; y[v] += s * character.deltas[base + 3 * v + 1];
        z[v] += s * character.deltas[base + 3 * v + 2];
      }
    }
    return {x: Array.from(x), y: Array.from(y), z: Array.from(z)};
  }

  const state = {clip: 0, frame: 0, colour: errors.length ? 0 : -1,
                 show: {face: true, dense: true, links: true, numbers: true, mirrored: true},
                 regions: {}, playing: false};
  data.regions.forEach(function (r) { state.regions[r] = true; });

  const clusterOfMarker = M.cluster;
  const repOf = {};
  clusters.forEach(function (c, k) { repOf[c.marker] = k; });

  // ---- positions -------------------------------------------------------------------------
  function mirrorPoint(p) {
    const q = plane.point, n = plane.normal;
    const d = (p[0] - q[0]) * n[0] + (p[1] - q[1]) * n[1] + (p[2] - q[2]) * n[2];
    return [p[0] - 2 * d * n[0], p[1] - 2 * d * n[1], p[2] - 2 * d * n[2]];
  }

  // Marker positions (N x [x, y, z], NaN in gaps) at the current frame of the current clip.
  function markerPositions() {
    const out = new Array(N);
    const clip = clips[state.clip];
    for (let i = 0; i < NC; i++) {
      if (!clip) { out[i] = M.neutral[i]; continue; }
      const o = (state.frame * NC + i) * 3, n0 = M.neutral[i], r = clip.resolution_mm;
      out[i] = clip.track[o] === GAP ? [NaN, NaN, NaN]
        : [n0[0] + r * clip.track[o], n0[1] + r * clip.track[o + 1], n0[2] + r * clip.track[o + 2]];
    }
    for (let i = NC; i < N; i++) {
      const src = M.mirror_of[i];
      out[i] = clip && plane && src >= 0 ? mirrorPoint(out[src]) : M.neutral[i];
    }
    return out;
  }

  // Face vertices moved by the skin: v + sum_k w_k (p_m(t) - p_m(neutral)); a gap moves nothing.
  function meshVertices(pos) {
    const V = mesh.vertices.length;
    const x = new Array(V), y = new Array(V), z = new Array(V);
    for (let v = 0; v < V; v++) {
      const rest = mesh.vertices[v];
      let dx = 0, dy = 0, dz = 0;
      const idx = mesh.skin_marker[v], w = mesh.skin_weight[v];
      for (let k = 0; k < idx.length; k++) {
        if (!w[k]) continue;
        const p = pos[idx[k]], n0 = M.neutral[idx[k]];
        const ex = p[0] - n0[0], ey = p[1] - n0[1], ez = p[2] - n0[2];
        if (isFinite(ex) && isFinite(ey) && isFinite(ez)) { dx += w[k] * ex; dy += w[k] * ey; dz += w[k] * ez; }
      }
      x[v] = rest[0] + dx; y[v] = rest[1] + dy; z[v] = rest[2] + dz;
    }
    return {x: x, y: y, z: z};
  }

  // ---- what is shown -----------------------------------------------------------------------
  function markerVisible(i) {
    return state.regions[M.regions[i]] && (state.show.mirrored || M.mirror_of[i] < 0);
  }

  // The layout shown: the clusters (numbered as in guide.pdf) or an error map's own layout.
  function shownLayout() {
    const map = state.colour >= 0 ? errors[state.colour] : null;
    if (map && map.layout) return map.layout.map(function (m, k) { return {marker: m, number: k + 1}; });
    return clusters.map(function (c) { return {marker: c.marker, number: c.name, cluster: c}; });
  }

  function fmt(v, digits) { return v === null || v === undefined || !isFinite(v) ? "–" : Number(v).toFixed(digits); }

  // A marker's error in the current map; a mirrored marker shows its source's (it is not captured).
  function errorOf(i) {
    if (state.colour < 0) return null;
    const values = errors[state.colour].values;
    let v = values[i];
    if ((v === null || v === undefined) && M.mirror_of[i] >= 0) v = values[M.mirror_of[i]];
    return v === null || v === undefined ? null : v;
  }

  function hoverLayout(entry) {
    const i = entry.marker, c = entry.cluster;
    const lines = ["<b>#" + entry.number + " " + M.labels[i] + "</b>",
                   "region " + M.regions[i] + " · side " + (c ? c.side : M.sides[i] || "–")];
    if (c) {
      if (c.mirrored_from) lines.push("mirrored from " + c.mirrored_from);
      const members = c.members.filter(function (m) { return m !== i; });
      lines.push("replaces " + members.length + " marker" + (members.length === 1 ? "" : "s") + (members.length ? ":" : ""));
      for (let k = 0; k < members.length; k += 2) {
        lines.push(members.slice(k, k + 2).map(function (m) {
          return M.labels[m] + " (C " + fmt(M.correlation[m], 2) + ")";
        }).join(", "));
      }
    }
    const e = errorOf(i);
    if (e !== null) lines.push(errors[state.colour].name + ": " + fmt(e, 2) + " mm");
    return lines.join("<br>");
  }

  function hoverDense(i) {
    const lines = ["<b>" + M.labels[i] + "</b>", "region " + M.regions[i] + " · side " + (M.sides[i] || "–")];
    const k = clusterOfMarker[i];
    if (k >= 0) {
      const c = clusters[k];
      lines.push("replaced by #" + c.name + " " + c.label + " · member correlation " + fmt(M.correlation[i], 2));
    }
    if (M.mirror_of[i] >= 0) lines.push("mirrored from " + M.labels[M.mirror_of[i]]);
    const e = errorOf(i);
    if (state.colour >= 0) lines.push(errors[state.colour].name + ": " + (e === null ? "not measured" : fmt(e, 2) + " mm") +
                                      (M.mirror_of[i] >= 0 && e !== null ? " (its source marker's)" : ""));
    return lines.join("<br>");
  }

  function errorRange() {
    let hi = 0;
    errors.forEach(function (map) {
      const v = map.values.filter(function (x) { return x !== null && isFinite(x); }).sort(function (a, b) { return a - b; });
      if (v.length) hi = Math.max(hi, v[Math.min(v.length - 1, Math.floor(0.98 * v.length))]);
    });
    return hi > 0 ? hi : 1;
  }
  const errorMax = errors.length ? errorRange() : 1;
  const SCALE = "YlOrRd";

  function nanToNull(v) { return isFinite(v) ? v : null; }
  // Drawn marker position: off the skin by the stored lift (the data positions stay untouched).
  function drawn(pos, i, axis) { return nanToNull(pos[i][axis] + mesh.marker_lift[i][axis]); }

  let annotations = [], annotationMarkers = [];  // the layout markers' numbers and their markers, set by traces()
  // Where a number sits by its marker: [xshift, yshift (px, up), xanchor, yanchor]; the first is
  // the default, the others are tried in order when it would cover another number.
  const SIDES = [[2, 1, "left", "bottom"], [-2, 1, "right", "bottom"], [2, -1, "left", "top"],
                 [-2, -1, "right", "top"], [0, 5, "center", "bottom"], [0, -5, "center", "top"],
                 [9, 7, "left", "bottom"], [-9, 7, "right", "bottom"], [9, -7, "left", "top"],
                 [-9, -7, "right", "top"]];
  let sideOf = {};  // layout marker -> SIDES index, chosen by placeNumbers() for the current view
  // Layout markers the face hides from the current camera (behind it, or behind the nose...): their
  // numbers are SVG drawn over the WebGL scene, so they would float over the mesh. Set by placeNumbers().
  let hidden = {};

  // Does the ray from p along d (unit) hit a triangle of the face (Moller-Trumbore) more than 4 mm
  // away? Nearer hits are the marker's own skin (1.5 mm behind its lifted dot) and grazing bumps.
  function rayHitsFace(p, d, mv, faces) {
    for (let f = 0; f < faces.length; f++) {
      const a = faces[f][0], b = faces[f][1], c = faces[f][2];
      const e1x = mv.x[b] - mv.x[a], e1y = mv.y[b] - mv.y[a], e1z = mv.z[b] - mv.z[a];
      const e2x = mv.x[c] - mv.x[a], e2y = mv.y[c] - mv.y[a], e2z = mv.z[c] - mv.z[a];
      const hx = d[1] * e2z - d[2] * e2y, hy = d[2] * e2x - d[0] * e2z, hz = d[0] * e2y - d[1] * e2x;
      const det = e1x * hx + e1y * hy + e1z * hz;
      if (Math.abs(det) < 1e-12) continue;
      const sx = p[0] - mv.x[a], sy = p[1] - mv.y[a], sz = p[2] - mv.z[a];
      const u = (sx * hx + sy * hy + sz * hz) / det;
      if (u < 0 || u > 1) continue;
      const qx = sy * e1z - sz * e1y, qy = sz * e1x - sx * e1z, qz = sx * e1y - sy * e1x;
      const v = (d[0] * qx + d[1] * qy + d[2] * qz) / det;
      if (v < 0 || u + v > 1) continue;
      if ((e2x * qx + e2y * qy + e2z * qz) / det > 4.0) return true;
    }
    return false;
  }

  // Plotly's perspective camera in data space: the eye of its view matrix taken back through the
  // model matrix and the data scale (gl-plot3d's, column-major); null where Plotly hides them.
  function cameraInData() {
    const scene = (((gd._fullLayout || {}).scene || {})._scene) || {};
    const params = (scene.glplot || {}).cameraParams, scale = scene.dataScale;
    if (!params || !scale) return null;
    const v = params.view, m = params.model;
    const world = [0, 1, 2].map(function (i) { return -(v[i * 4] * v[12] + v[i * 4 + 1] * v[13] + v[i * 4 + 2] * v[14]); });
    const a = [[m[0], m[4], m[8]], [m[1], m[5], m[9]], [m[2], m[6], m[10]]];
    const b = [world[0] - m[12], world[1] - m[13], world[2] - m[14]];
    const det = a[0][0] * (a[1][1] * a[2][2] - a[1][2] * a[2][1]) - a[0][1] * (a[1][0] * a[2][2] - a[1][2] * a[2][0]) +
                a[0][2] * (a[1][0] * a[2][1] - a[1][1] * a[2][0]);
    if (!(Math.abs(det) > 1e-12)) return null;
    return [0, 1, 2].map(function (i) {  // Cramer's rule, then undo the data scale
      const c = a.map(function (row, r) { return row.map(function (x, k) { return k === i ? b[r] : x; }); });
      const d = c[0][0] * (c[1][1] * c[2][2] - c[1][2] * c[2][1]) - c[0][1] * (c[1][0] * c[2][2] - c[1][2] * c[2][0]) +
                c[0][2] * (c[1][0] * c[2][1] - c[1][1] * c[2][0]);
      return d / det / scale[i];
    });
  }

  // The layout markers hidden from the camera: rays from each marker to Plotly's perspective camera
  // (before the first draw, or without Plotly's internals, along the layout's eye direction: the
  // scene box is the data scaled alike on every axis); returns whether the set changed.
  function updateHidden() {
    const eyeCamera = ((gd._fullLayout || {}).scene || {}).camera || plotLayout.scene.camera;
    const e = eyeCamera.eye, length = Math.hypot(e.x, e.y, e.z) || 1;
    const along = [e.x / length, e.y / length, e.z / length];
    const camera = cameraInData();
    const pos = markerPositions();
    const mv = meshVertices(pos);
    const next = {};
    if (state.show.face) {
      shownLayout().forEach(function (entry) {
        const i = entry.marker;
        const p = [0, 1, 2].map(function (a) { return pos[i][a] + mesh.marker_lift[i][a]; });
        if (!p.every(isFinite)) return;
        let d = along;
        if (camera) {
          const to = [camera[0] - p[0], camera[1] - p[1], camera[2] - p[2]], n = Math.hypot(to[0], to[1], to[2]);
          if (n > 0) d = [to[0] / n, to[1] / n, to[2] / n];
        }
        if (rayHitsFace(p, d, mv, mesh.faces)) next[i] = true;
      });
    }
    const changed = Object.keys(next).join() !== Object.keys(hidden).join();
    hidden = next;
    return changed;
  }
  function traces() {
    const pos = markerPositions();
    const layoutEntries = shownLayout().filter(function (e) { return markerVisible(e.marker); });
    const isLayout = {};
    layoutEntries.forEach(function (e) { isLayout[e.marker] = true; });
    const out = [];
    // face
    const mv = meshVertices(pos);
    const fi = [], fj = [], fk = [];
    mesh.faces.forEach(function (f) {
      if (!state.show.mirrored && mesh.mirrored[f[0]] && mesh.mirrored[f[1]] && mesh.mirrored[f[2]]) return;
      fi.push(f[0]); fj.push(f[1]); fk.push(f[2]);
    });
    const face = {type: "mesh3d", name: "face", x: mv.x, y: mv.y, z: mv.z, i: fi, j: fj, k: fk,
                  visible: state.show.face, hoverinfo: "skip", flatshading: false, showscale: false,
                  lighting: {ambient: 0.55, diffuse: 0.6, specular: 0.05, roughness: 0.9},
                  lightposition: {x: 0, y: 200, z: 1000}};
    if (state.colour >= 0) {
      face.intensity = mesh.nearest_marker.map(function (m) { const v = errorOf(m); return v === null ? 0 : v; });
      face.colorscale = SCALE; face.reversescale = true; face.cmin = 0; face.cmax = errorMax;
    } else {
      face.vertexcolor = mesh.colours;
    }
    out.push(face);
    if (character) {
      const cv = characterVertices(state.frame);
      out.push({type: "mesh3d", name: "character", x: cv.x, y: cv.y, z: cv.z, color: "#d9c2a6",
                i: character.faces.map(function (f) { return f[0]; }), j: character.faces.map(function (f) { return f[1]; }),
                k: character.faces.map(function (f) { return f[2]; }), hoverinfo: "skip", flatshading: false,
                lighting: face.lighting, lightposition: face.lightposition});
    }
    // member links to the representative
    const lx = [], ly = [], lz = [], lc = [];
    if (state.colour < 0 || !errors[state.colour].layout) {
      layoutEntries.forEach(function (e) {
        if (!e.cluster) return;
        e.cluster.members.forEach(function (m) {
          if (m === e.marker || !markerVisible(m)) return;
          lx.push(drawn(pos, e.marker, 0), drawn(pos, m, 0), null);
          ly.push(drawn(pos, e.marker, 1), drawn(pos, m, 1), null);
          lz.push(drawn(pos, e.marker, 2), drawn(pos, m, 2), null);
        });
      });
    }
    out.push({type: "scatter3d", mode: "lines", name: "member links", x: lx, y: ly, z: lz, visible: state.show.links, hoverinfo: "skip",
              line: {color: "rgba(40,40,40,0.55)", width: 2}});
    // dense markers
    const dense = [];
    for (let i = 0; i < N; i++) if (markerVisible(i) && !isLayout[i]) dense.push(i);
    const denseTrace = {type: "scatter3d", mode: "markers", name: "dense markers",
      x: dense.map(function (i) { return drawn(pos, i, 0); }),
      y: dense.map(function (i) { return drawn(pos, i, 1); }),
      z: dense.map(function (i) { return drawn(pos, i, 2); }),
      customdata: dense, text: dense.map(hoverDense), hovertemplate: "%{text}<extra></extra>",
      visible: state.show.dense, marker: {size: 2.4, line: {width: 0}}};
    if (state.colour >= 0) {
      denseTrace.marker.color = dense.map(function (i) { const v = errorOf(i); return v === null ? NaN : v; });
      denseTrace.marker.colorscale = SCALE; denseTrace.marker.reversescale = true;
      denseTrace.marker.cmin = 0; denseTrace.marker.cmax = errorMax;
      denseTrace.marker.showscale = true;
      denseTrace.marker.colorbar = {title: {text: "mm"}, len: 0.5, thickness: 12, x: 0.02};
    } else {
      denseTrace.marker.color = dense.map(function (i) {
        const k = clusterOfMarker[i];
        return k >= 0 ? clusters[k].dense_colour : "#777777";
      });
    }
    out.push(denseTrace);
    // layout markers, numbered as in guide.pdf (numbers are SVG scene annotations: WebGL text
    // would cost most of the first draw)
    const lx3 = [], ly3 = [], lz3 = [];
    layoutEntries.forEach(function (e) {
      lx3.push(drawn(pos, e.marker, 0)); ly3.push(drawn(pos, e.marker, 1)); lz3.push(drawn(pos, e.marker, 2));
    });
    out.push({type: "scatter3d", mode: "markers", name: "layout markers", x: lx3, y: ly3, z: lz3,
      customdata: layoutEntries.map(function (e) { return e.marker; }),
      text: layoutEntries.map(function (e) { return String(e.number); }),
      hovertext: layoutEntries.map(hoverLayout), hovertemplate: "%{hovertext}<extra></extra>",
      marker: {size: 4.5, color: layoutEntries.map(function (e) {
        return e.cluster ? e.cluster.colour : "#1f3b73";
      })}});
    // the stabilization (head) markers every capture is posed from: squares, H1, H2 ... as in guide.pdf
    const heads = (data.stabilization || []).filter(function (h) { return markerVisible(h.marker); });
    out.push({type: "scatter3d", mode: "markers", name: "stabilization markers",
      x: heads.map(function (h) { return drawn(pos, h.marker, 0); }),
      y: heads.map(function (h) { return drawn(pos, h.marker, 1); }),
      z: heads.map(function (h) { return drawn(pos, h.marker, 2); }),
      customdata: heads.map(function (h) { return h.marker; }),
      hovertext: heads.map(function (h) { return h.name + " " + h.label + " (stabilization marker)"; }),
      hovertemplate: "%{hovertext}<extra></extra>",
      marker: {size: 5.5, symbol: "square", color: "#202020"}});
    const numbered = !state.show.numbers ? [] : layoutEntries.map(function (e, k) { return k; })
      .filter(function (k) { return lx3[k] !== null && ly3[k] !== null && lz3[k] !== null && !hidden[layoutEntries[k].marker]; });
    annotationMarkers = numbered.map(function (k) { return layoutEntries[k].marker; });
    annotations = numbered.map(function (k) {
      const side = SIDES[sideOf[layoutEntries[k].marker] || 0];
      return {x: lx3[k], y: ly3[k], z: lz3[k], text: String(layoutEntries[k].number), showarrow: false,
              xanchor: side[2], yanchor: side[3], xshift: side[0], yshift: side[1],
              font: {size: 11, color: "#000000"}, bgcolor: "rgba(255,255,255,0.55)", borderpad: 0};
    });
    return out;
  }

  // Fixed axis ranges (the view never rescales during replay) and a box scaled like the data.
  function sceneBox() {
    const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
    mesh.vertices.concat(M.neutral, character ? character.vertices : []).forEach(function (p) {
      for (let a = 0; a < 3; a++) if (isFinite(p[a])) { lo[a] = Math.min(lo[a], p[a]); hi[a] = Math.max(hi[a], p[a]); }
    });
    const pad = 15, span = [0, 1, 2].map(function (a) { return hi[a] - lo[a] + 2 * pad; });
    const big = Math.max(span[0], span[1], span[2]);
    const axis = function (a) { return {visible: false, range: [lo[a] - pad, hi[a] + pad], autorange: false}; };
    return {x: axis(0), y: axis(1), z: axis(2), ratio: {x: span[0] / big, y: span[1] / big, z: span[2] / big}};
  }
  const box = sceneBox();

  const plotLayout = {
    margin: {l: 0, r: 0, t: 0, b: 0}, showlegend: false, paper_bgcolor: "#ffffff", uirevision: "keep",
    hoverlabel: {align: "left", bgcolor: "#ffffff", font: {size: 12}},
    scene: {aspectmode: "manual", aspectratio: box.ratio, dragmode: "orbit", bgcolor: "#ffffff",
            xaxis: box.x, yaxis: box.y, zaxis: box.z,
            camera: {eye: {x: 0, y: 0.08, z: 1.25}, up: {x: 0, y: 1, z: 0}, center: {x: 0, y: 0, z: 0}}}
  };
  const config = {displaylogo: false, responsive: true, modeBarButtonsToRemove: ["toImage"]};

  let drawing = null, pending = false;
  function redraw() {
    if (drawing) { pending = true; return drawing; }
    const data = traces();
    const layout = Object.assign({}, plotLayout, {scene: Object.assign({}, plotLayout.scene, {annotations: annotations})});
    drawing = Plotly.react(gd, data, layout, config).then(function () {
      drawing = null;
      if (pending) { pending = false; return redraw(); }
    });
    return drawing;
  }

  // ---- panel -----------------------------------------------------------------------------
  document.getElementById("title").textContent = data.title || "mocaptk report";
  document.getElementById("summary").textContent = (data.summary || "").replace(/\s+$/, "") +
    "\n\nreport.html: " + data.size + " (plotly.js " + data.plotly_version + " embedded, works offline)";
  const nLayout = clusters.length;
  document.getElementById("subtitle").textContent = [
    (NC) + " dense markers" + (N > NC ? " + " + (N - NC) + " mirrored" : ""),
    nLayout ? nLayout + " layout markers (numbers as in guide.pdf)" : null,
    mesh.vertices.length + "-vertex face"].filter(Boolean).join(" · ");

  function checkbox(parent, text, checked, onChange, colour) {
    const label = document.createElement("label");
    const box = document.createElement("input");
    box.type = "checkbox"; box.checked = checked;
    box.addEventListener("change", function () { onChange(box.checked); redraw().then(placeNumbers); });
    label.appendChild(box);
    if (colour) { const s = document.createElement("span"); s.className = "swatch"; s.style.background = colour; label.appendChild(s); }
    label.appendChild(document.createTextNode(text));
    parent.appendChild(label);
    return box;
  }
  const show = document.getElementById("show");
  checkbox(show, "face", true, function (v) { state.show.face = v; });
  checkbox(show, "dense markers", true, function (v) { state.show.dense = v; });
  checkbox(show, "member links", true, function (v) { state.show.links = v; });
  checkbox(show, "numbers", true, function (v) { state.show.numbers = v; });
  if (N > NC) checkbox(show, "mirrored half", true, function (v) { state.show.mirrored = v; });
  const regionBox = document.getElementById("regions");
  data.regions.forEach(function (r) {
    checkbox(regionBox, r, true, function (v) { state.regions[r] = v; }, data.region_colours[r]);
  });
  const colouring = document.getElementById("colouring");
  const colourSelect = document.createElement("select");
  if (clusters.length) colourSelect.add(new Option("clusters (influence regions)", "-1"));
  errors.forEach(function (map, k) { colourSelect.add(new Option(map.name + " (mm)", String(k))); });
  colourSelect.value = String(state.colour);
  colourSelect.addEventListener("change", function () { pick(Number(colourSelect.value)); });
  colouring.appendChild(colourSelect);
  if (!errors.length) colouring.appendChild(document.createTextNode(" (held-out errors: see evaluate / compare reports)"));

  const rowsByMap = {};
  function pick(k) {
    state.colour = k; colourSelect.value = String(k);
    Object.keys(rowsByMap).forEach(function (key) { rowsByMap[key].forEach(function (tr) { tr.classList.toggle("picked", Number(key) === k); }); });
    redraw().then(placeNumbers);  // another layout: its own numbers
  }
  const tables = document.getElementById("tables");
  (data.tables || []).forEach(function (t) {
    const table = document.createElement("table");
    table.createCaption().textContent = t.title;
    const head = table.createTHead().insertRow();
    t.columns.forEach(function (c) { const th = document.createElement("th"); th.textContent = c; head.appendChild(th); });
    const body = table.createTBody();
    t.rows.forEach(function (row, r) {
      const tr = body.insertRow();
      row.forEach(function (cell) { tr.insertCell().textContent = cell === null ? "–" : String(cell); });
      const k = t.picks ? t.picks[r] : null;
      if (k !== null && k !== undefined) {
        tr.classList.add("pickable"); tr.title = "colour the face by this row's held-out error";
        (rowsByMap[k] = rowsByMap[k] || []).push(tr);
        tr.addEventListener("click", function () { pick(k); });
      }
    });
    tables.appendChild(table);
    if (t.note) { const p = document.createElement("p"); p.textContent = t.note; tables.appendChild(p); }
  });

  // ---- weight curves (retarget) -----------------------------------------------------------
  let curves = null;
  if (character && clips.length) {
    curves = document.createElement("div");
    curves.id = "curves";
    document.getElementById("view").appendChild(curves);
    const c0 = clips[0];
    const t = character.weights.map(function (_, f) { return f * c0.step / c0.source_rate_hz; });
    const lines = character.curves.map(function (k) {
      return {type: "scatter", mode: "lines", name: character.names[k], x: t, line: {width: 1.2},
              y: character.weights.map(function (w) { return w[k]; })};
    });
    Plotly.newPlot(curves, lines, {
      margin: {l: 40, r: 8, t: 6, b: 28}, showlegend: true, legend: {font: {size: 9}},
      xaxis: {title: {text: "s", standoff: 2}}, yaxis: {range: [0, 1], title: {text: "weight", standoff: 2}},
      shapes: [{type: "line", x0: 0, x1: 0, y0: 0, y1: 1, line: {color: "#c00", width: 1}}]
    }, {displaylogo: false, responsive: true});
  }

  // ---- time ------------------------------------------------------------------------------
  const slider = document.getElementById("time");
  const clock = document.getElementById("clock");
  const clipSelect = document.getElementById("clip");
  const play = document.getElementById("play");
  clips.forEach(function (c, k) { clipSelect.add(new Option(c.name, String(k))); });
  function ordinal(n) { return n === 1 ? "every frame" : "every " + n + (n === 2 ? "nd" : n === 3 ? "rd" : "th") + " frame"; }
  function showClock() {
    const c = clips[state.clip];
    if (!c) { clock.textContent = "neutral pose (no recording)"; return; }
    const source = state.frame * c.step;
    clock.textContent = (source / c.source_rate_hz).toFixed(2) + " s · frame " + source + "/" + c.source_frames +
      " @ " + fmt(c.source_rate_hz, 0) + " Hz · replay " + fmt(c.rate_hz, 1) + " Hz (" + ordinal(c.step) + ")";
    if (curves) Plotly.relayout(curves, {"shapes[0].x0": source / c.source_rate_hz, "shapes[0].x1": source / c.source_rate_hz});
  }
  function setClip(k) {
    state.clip = k; state.frame = 0; clipSelect.value = String(k);
    slider.max = String(clips[k] ? clips[k].frames - 1 : 0); slider.value = "0";
    showClock();
    return redraw();
  }
  function setFrame(f) {
    const c = clips[state.clip];
    state.frame = c ? Math.max(0, Math.min(c.frames - 1, Math.round(f))) : 0;
    slider.value = String(state.frame);
    showClock();
    return redraw();
  }
  slider.addEventListener("input", function () { setFrame(Number(slider.value)); });
  clipSelect.addEventListener("change", function () { setClip(Number(clipSelect.value)); });
  let playStart = 0, playFrom = 0;
  function tick(now) {
    if (!state.playing) return;
    const c = clips[state.clip];
    const f = playFrom + (now - playStart) / 1000 * c.rate_hz;
    if (f >= c.frames - 1) { setFrame(c.frames - 1); togglePlay(); return; }
    (drawing || Promise.resolve()).then(function () {
      setFrame(f);
      requestAnimationFrame(tick);
    });
  }
  function togglePlay() {
    if (!clips.length) return;
    state.playing = !state.playing;
    play.innerHTML = state.playing ? "&#10073;&#10073;" : "&#9654;";
    if (state.playing) {
      if (state.frame >= clips[state.clip].frames - 1) state.frame = 0;
      playStart = performance.now(); playFrom = state.frame;
      requestAnimationFrame(tick);
    }
  }
  play.addEventListener("click", togglePlay);
  if (!clips.length) { play.disabled = true; slider.disabled = true; clipSelect.disabled = true; }

  // Numbers placed on screen like guide.pdf's labels, as far as a few sides allow: each number,
  // in marker order, takes the first side where its box covers no number placed before it (the
  // boxes are the drawn annotations, so the view's projection is plotly's own). Chosen after the
  // first draw, a toggle, a picked row and a camera move, never per frame: replay keeps them.
  function placeNumbers() {
    if (updateHidden()) return redraw().then(placeNumbers);  // numbers of hidden markers go first
    const drawnBoxes = Array.prototype.slice.call(gd.querySelectorAll(".annotation-text-g"));
    if (!state.show.numbers || drawnBoxes.length !== annotations.length) return Promise.resolve();
    const placed = [];
    let changed = false;
    annotations.forEach(function (_, k) {
      const r = drawnBoxes[k].getBoundingClientRect();
      const marker = annotationMarkers[k];
      const now = SIDES[sideOf[marker] || 0];
      // the marker's screen point, from the box and the side it was drawn at
      const px = (now[2] === "left" ? r.left : now[2] === "right" ? r.right : (r.left + r.right) / 2) - now[0];
      const py = (now[3] === "bottom" ? r.bottom : r.top) + now[1];
      const box = function (side) {
        const x0 = side[2] === "left" ? px + side[0] : side[2] === "right" ? px + side[0] - r.width : px + side[0] - r.width / 2;
        const y0 = side[3] === "bottom" ? py - side[1] - r.height : py - side[1];
        return [x0, y0, x0 + r.width, y0 + r.height];
      };
      const free = function (b) {
        return placed.every(function (q) { return b[2] <= q[0] || q[2] <= b[0] || b[3] <= q[1] || q[3] <= b[1]; });
      };
      let pick = SIDES.findIndex(function (side) { return free(box(side)); });
      if (pick < 0) pick = sideOf[marker] || 0;  // nowhere free: where it was
      placed.push(box(SIDES[pick]));
      if (pick !== (sideOf[marker] || 0)) { sideOf[marker] = pick; changed = true; }
    });
    return changed ? redraw() : Promise.resolve();
  }
  let placing = null;
  function placeAfterCameraMoves() {  // gd.on exists once plotly has drawn
    gd.on("plotly_relayout", function (change) {
      if (!Object.keys(change).some(function (key) { return key.indexOf("scene.camera") === 0; })) return;
      clearTimeout(placing);
      placing = setTimeout(function () { (drawing || Promise.resolve()).then(placeNumbers); }, 150);
    });
  }

  window.mocaptkReport = {data: data, state: state, setFrame: setFrame, setClip: setClip, pick: pick,
                          markerPositions: markerPositions, ready: false, loadMs: null,
                          hidden: function () { return Object.keys(hidden).map(Number); },
                          camera: cameraInData,
                          view: function (eye) { return Plotly.relayout(gd, {"scene.camera.eye": eye}).then(placeNumbers).then(function () { return true; }); },
                          settled: function () { return drawing || Promise.resolve(); }};
  setClip(0).then(placeNumbers).then(function () {
    placeAfterCameraMoves();
    window.mocaptkReport.ready = true;
    window.mocaptkReport.loadMs = performance.now();  // since navigation start
    window.mocaptkReport.drawMs = performance.now() - started;
  });
})();
