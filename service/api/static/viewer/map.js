// The 3D map: three.js scene in the map frame (x east, y north, z up, metres). Holds the fused tile
// meshes (one flat colour per face: its label's), the tile grid coloured by state, and the session
// trajectories. Filtering (labels shown, minimum confidence) happens here, on the GPU index, without
// downloading anything again. Renders on demand only (a change, a camera move), not in a loop.

import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";

export const STATE_COLORS = {
  dirty: "#e6a23c", queued: "#9e9e9e", fusing: "#409eff", fused: "#67c23a", failed: "#f56c6c",
};
const BACKGROUND = new THREE.Color("#f2f2f2");
const MAX_VIEW_M = 4000; // the view box never grows beyond this around the orbit target
const VIEW_BACK = 0.6, VIEW_UP = 0.75; // camera offset south and up, per metre of the framed span

function hashHue(text) {
  let h = 2166136261; // FNV-1a, then the golden ratio spreads close hashes around the hue circle
  for (const ch of text) h = Math.imul(h ^ ch.codePointAt(0), 16777619) >>> 0;
  return (h * 0.6180339887498949) % 1;
}

export function sessionColor(sessionId) {
  return new THREE.Color().setHSL(hashHue(sessionId), 0.75, 0.42);
}

export class TileMap {
  constructor(canvas) {
    this.canvas = canvas;
    // preserveDrawingBuffer: the canvas keeps its pixels after compositing (screenshots, tests)
    this.renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(window.devicePixelRatio || 1);
    this.scene = new THREE.Scene();
    this.scene.background = BACKGROUND;
    this.camera = new THREE.PerspectiveCamera(50, 1, 0.5, 20000);
    this.camera.up.set(0, 0, 1);
    this.camera.position.set(0, -120, 120);
    this.controls = new OrbitControls(this.camera, canvas);
    this.controls.screenSpacePanning = false; // pan on the ground plane
    this.controls.maxPolarAngle = Math.PI * 0.49;
    this.controls.addEventListener("change", () => this.render());
    this.scene.add(new THREE.AmbientLight(0xffffff, 1.6));
    const sun = new THREE.DirectionalLight(0xffffff, 1.4);
    sun.position.set(0.4, -0.6, 1);
    this.scene.add(sun);
    this.grid = new THREE.Group();
    this.tracks = new THREE.Group();
    this.meshes = new THREE.Group();
    this.scene.add(this.grid, this.meshes, this.tracks);
    this.tileSize = 64;
    this.palette = new Map(); // label id -> [r, g, b] 0..255
    this.hidden = new Set(); // label ids not shown
    this.minConfidence = 0;
    this.shaded = false;
    this.tiles = new Map(); // "i,j" -> THREE.Mesh
    this.selected = null;
    this.pending = false;
    new ResizeObserver(() => this.resize()).observe(canvas);
    this.resize();
  }

  resize() {
    const { clientWidth: w, clientHeight: h } = this.canvas;
    if (!w || !h) return;
    this.renderer.setSize(w, h, false);
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
    this.render();
  }

  /** Render once, at the next frame (several changes in one task cost one render). */
  render() {
    if (this.pending) return;
    this.pending = true;
    requestAnimationFrame(() => this.renderNow());
  }

  renderNow() {
    this.pending = false;
    this.controls.update();
    this.renderer.render(this.scene, this.camera);
  }

  setPalette(labels) {
    this.palette = new Map(labels.map((l) => [l.id, l.color]));
  }

  // ------------------------------------------------------------------ fused meshes

  /** Show tile `key`'s parsed PLY (see ply.js), replacing what it showed. */
  setTileMesh(key, ply) {
    this.removeTileMesh(key);
    const faces = ply.faces.length / 3;
    const positions = new Float32Array(faces * 9);
    const colors = new Float32Array(faces * 9);
    const minConfidence = new Float32Array(faces);
    const color = new THREE.Color();
    for (let f = 0; f < faces; f += 1) {
      const [r, g, b] = this.palette.get(ply.faceLabel[f]) || [0, 0, 0];
      color.setRGB(r / 255, g / 255, b / 255, THREE.SRGBColorSpace); // to the linear working space
      let lowest = Infinity;
      for (let k = 0; k < 3; k += 1) {
        const v = ply.faces[3 * f + k];
        positions.set(ply.positions.subarray(3 * v, 3 * v + 3), 9 * f + 3 * k);
        colors.set([color.r, color.g, color.b], 9 * f + 3 * k);
        lowest = Math.min(lowest, ply.confidence[v]);
      }
      minConfidence[f] = lowest;
    }
    const geometry = new THREE.BufferGeometry();
    geometry.setAttribute("position", new THREE.BufferAttribute(positions, 3));
    geometry.setAttribute("color", new THREE.BufferAttribute(colors, 3));
    geometry.computeVertexNormals(); // per face: the geometry is not indexed by vertex
    geometry.computeBoundingSphere();
    const mesh = new THREE.Mesh(geometry, this.material());
    mesh.userData = { key, faceLabel: ply.faceLabel, minConfidence };
    this.filterMesh(mesh);
    this.tiles.set(key, mesh);
    this.meshes.add(mesh);
    this.render();
  }

  removeTileMesh(key) {
    const mesh = this.tiles.get(key);
    if (!mesh) return;
    this.meshes.remove(mesh);
    mesh.geometry.dispose();
    mesh.material.dispose();
    this.tiles.delete(key);
    this.render();
  }

  setTileVisible(key, visible) {
    const mesh = this.tiles.get(key);
    if (mesh && mesh.visible !== visible) {
      mesh.visible = visible;
      this.render();
    }
  }

  material() {
    const options = { vertexColors: true, side: THREE.DoubleSide };
    // Unlit by default: every face shows its label's colour exactly, as in the legend.
    return this.shaded ? new THREE.MeshLambertMaterial(options) : new THREE.MeshBasicMaterial(options);
  }

  setShaded(shaded) {
    this.shaded = shaded;
    for (const mesh of this.tiles.values()) {
      mesh.material.dispose();
      mesh.material = this.material();
    }
    this.render();
  }

  /** The faces to draw: label shown and every vertex at least `minConfidence` (as the API's filter). */
  filterMesh(mesh) {
    const { faceLabel, minConfidence } = mesh.userData;
    const kept = new Uint32Array(faceLabel.length * 3);
    let n = 0;
    for (let f = 0; f < faceLabel.length; f += 1) {
      if (this.hidden.has(faceLabel[f]) || minConfidence[f] < this.minConfidence) continue;
      kept[n++] = 3 * f;
      kept[n++] = 3 * f + 1;
      kept[n++] = 3 * f + 2;
    }
    mesh.geometry.setIndex(new THREE.BufferAttribute(kept.slice(0, n), 1));
  }

  setFilter({ minConfidence, hidden }) {
    this.minConfidence = minConfidence;
    this.hidden = new Set(hidden);
    for (const mesh of this.tiles.values()) this.filterMesh(mesh);
    this.render();
  }

  /** Triangles drawn now (visible tiles, after the filters). */
  triangleCount() {
    let count = 0;
    for (const mesh of this.tiles.values()) if (mesh.visible) count += mesh.geometry.index.count / 3;
    return count;
  }

  // ------------------------------------------------------------------ tile grid

  /** The ground grid: one square per tile of `tiles` (the API's Tile JSON), filled by state. */
  setGrid(tiles) {
    for (const child of [...this.grid.children]) {
      child.geometry.dispose();
      child.material.dispose();
      this.grid.remove(child);
    }
    if (!tiles.length) {
      this.render();
      return;
    }
    const s = this.tileSize;
    const fill = [];
    const fillColors = [];
    const edges = [];
    const edgeColors = [];
    const pastel = new THREE.Color();
    const strong = new THREE.Color();
    for (const t of tiles) {
      const x0 = t.i * s, y0 = t.j * s, x1 = x0 + s, y1 = y0 + s;
      strong.set(STATE_COLORS[t.state] || "#000000");
      pastel.copy(strong).lerp(BACKGROUND, 0.7);
      fill.push(x0, y0, 0, x1, y0, 0, x1, y1, 0, x0, y0, 0, x1, y1, 0, x0, y1, 0);
      for (let k = 0; k < 6; k += 1) fillColors.push(pastel.r, pastel.g, pastel.b);
      const inset = s * 0.01;
      const [a0, b0, a1, b1] = [x0 + inset, y0 + inset, x1 - inset, y1 - inset];
      edges.push(a0, b0, 0, a1, b0, 0, a1, b0, 0, a1, b1, 0, a1, b1, 0, a0, b1, 0, a0, b1, 0, a0, b0, 0);
      for (let k = 0; k < 8; k += 1) edgeColors.push(strong.r, strong.g, strong.b);
    }
    // The grid is the ground layer: drawn first and without depth, so meshes always cover it.
    const layer = { vertexColors: true, depthWrite: false, depthTest: false };
    const fillGeometry = new THREE.BufferGeometry();
    fillGeometry.setAttribute("position", new THREE.Float32BufferAttribute(fill, 3));
    fillGeometry.setAttribute("color", new THREE.Float32BufferAttribute(fillColors, 3));
    const fills = new THREE.Mesh(fillGeometry, new THREE.MeshBasicMaterial({ ...layer, side: THREE.DoubleSide }));
    const edgeGeometry = new THREE.BufferGeometry();
    edgeGeometry.setAttribute("position", new THREE.Float32BufferAttribute(edges, 3));
    edgeGeometry.setAttribute("color", new THREE.Float32BufferAttribute(edgeColors, 3));
    const outlines = new THREE.LineSegments(edgeGeometry, new THREE.LineBasicMaterial(layer));
    fills.renderOrder = -2;
    outlines.renderOrder = -1;
    this.grid.add(fills, outlines);
    this.drawSelection();
    this.render();
  }

  select(i, j) {
    this.selected = i === null ? null : [i, j];
    this.drawSelection();
    this.render();
  }

  drawSelection() {
    const old = this.grid.getObjectByName("selection");
    if (old) {
      old.geometry.dispose();
      old.material.dispose();
      this.grid.remove(old);
    }
    if (!this.selected) return;
    const s = this.tileSize;
    const [x0, y0] = [this.selected[0] * s, this.selected[1] * s];
    const ring = [x0, y0, 0, x0 + s, y0, 0, x0 + s, y0 + s, 0, x0, y0 + s, 0];
    const geometry = new THREE.BufferGeometry();
    geometry.setAttribute("position", new THREE.Float32BufferAttribute(ring, 3));
    const line = new THREE.LineLoop(geometry, new THREE.LineBasicMaterial({ color: "#1a1a1a", depthTest: false }));
    line.name = "selection";
    line.renderOrder = 10;
    this.grid.add(line);
  }

  // ------------------------------------------------------------------ trajectories

  /** Session trajectories (the API's SessionTrack): GPS dashed grey, refined solid in the session's colour. */
  setTracks(sessions, { gps, refined, hiddenSessions }) {
    for (const child of [...this.tracks.children]) {
      child.geometry.dispose();
      child.material.dispose();
      this.tracks.remove(child);
    }
    for (const session of sessions) {
      if (hiddenSessions.has(session.session_id)) continue;
      const points = session.points;
      if (gps && points.length > 1) {
        const dashed = new THREE.LineDashedMaterial({ color: "#777777", dashSize: 2, gapSize: 1.5 });
        const line = this.polyline(points.map((p) => p.pose_gps_t), dashed);
        line.computeLineDistances();
        this.tracks.add(line);
      }
      const aligned = points.filter((p) => p.pose_refined_t).map((p) => p.pose_refined_t);
      if (refined && aligned.length > 1) {
        const color = sessionColor(session.session_id);
        this.tracks.add(this.polyline(aligned, new THREE.LineBasicMaterial({ color, depthTest: false })));
        // a dot per submap pose: a one-pixel line alone is lost on a large map
        const dots = new THREE.PointsMaterial({ color, size: 7, sizeAttenuation: false, depthTest: false });
        this.tracks.add(this.overlay(new THREE.Points(this.positions(aligned), dots)));
      }
    }
    this.render();
  }

  positions(points) {
    const geometry = new THREE.BufferGeometry();
    geometry.setAttribute("position", new THREE.Float32BufferAttribute(points.flat(), 3));
    return geometry;
  }

  /** Drawn after (over) the meshes: trajectories run on the road surface and would be hidden in it. */
  overlay(object) {
    object.renderOrder = 10;
    return object;
  }

  polyline(points, material) {
    material.depthTest = false;
    return this.overlay(new THREE.Line(this.positions(points), material));
  }

  // ------------------------------------------------------------------ camera and picking

  /** Look at a map-frame box [xmin, ymin, xmax, ymax] from the south, above. */
  frame([xmin, ymin, xmax, ymax]) {
    this.frameAt((xmin + xmax) / 2, (ymin + ymax) / 2, Math.max(xmax - xmin, ymax - ymin, 32));
  }

  /** Look at map-frame point (cx, cy, 0) from the south, above, seeing about `span` metres of it. */
  frameAt(cx, cy, span) {
    this.controls.target.set(cx, cy, 0);
    this.camera.position.set(cx, cy - span * VIEW_BACK, span * VIEW_UP);
    this.camera.lookAt(cx, cy, 0);
    this.render();
  }

  /** [cx, cy, span] of the current view (see frameAt; the orbit angle is not kept). */
  currentView() {
    const t = this.controls.target;
    return [t.x, t.y, this.camera.position.distanceTo(t) / Math.hypot(VIEW_BACK, VIEW_UP)];
  }

  /** Where the ray through canvas pixel (px, py) meets the loaded meshes, else the ground z = 0. */
  pick(px, py) {
    const ndc = new THREE.Vector2((px / this.canvas.clientWidth) * 2 - 1, -(py / this.canvas.clientHeight) * 2 + 1);
    const ray = new THREE.Raycaster();
    ray.setFromCamera(ndc, this.camera);
    const hit = ray.intersectObjects([...this.tiles.values()].filter((m) => m.visible), false)[0];
    if (hit) return hit.point;
    const ground = new THREE.Vector3();
    return ray.ray.intersectPlane(new THREE.Plane(new THREE.Vector3(0, 0, 1), 0), ground) ? ground : null;
  }

  /** Canvas pixel (CSS pixels from its top left) where map-frame point (x, y, z) is drawn. */
  screenOf(x, y, z = 0) {
    const p = new THREE.Vector3(x, y, z).project(this.camera);
    return { x: ((p.x + 1) / 2) * this.canvas.clientWidth, y: ((1 - p.y) / 2) * this.canvas.clientHeight };
  }

  /** The map-frame box [xmin, ymin, xmax, ymax] of the ground the camera sees (capped far away). */
  viewBox() {
    const target = this.controls.target;
    const xs = [target.x], ys = [target.y];
    const plane = new THREE.Plane(new THREE.Vector3(0, 0, 1), 0);
    const ray = new THREE.Raycaster();
    const point = new THREE.Vector3();
    for (const [x, y] of [[-1, -1], [1, -1], [1, 1], [-1, 1], [0, 1], [-1, 0], [1, 0]]) {
      ray.setFromCamera(new THREE.Vector2(x, y), this.camera);
      const hit = ray.ray.intersectPlane(plane, point);
      const p = hit && hit.distanceTo(this.camera.position) < MAX_VIEW_M ? hit : ray.ray.at(MAX_VIEW_M, point);
      xs.push(p.x);
      ys.push(p.y);
    }
    const clamp = (v, c) => Math.min(Math.max(v, c - MAX_VIEW_M), c + MAX_VIEW_M);
    return [
      clamp(Math.min(...xs), target.x), clamp(Math.min(...ys), target.y),
      clamp(Math.max(...xs), target.x), clamp(Math.max(...ys), target.y),
    ];
  }
}
