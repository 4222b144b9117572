// The fleetmap viewer: wires the token box, the legend and filters, the 3D map and the tile panel
// to the API, and keeps the view live. Only the tiles in view are listed and their meshes loaded;
// each mesh is revalidated with its ETag (If-None-Match → 304: nothing downloaded), and the
// response is kept in the browser's Cache Storage so a reload of the page re-downloads nothing
// either. `window.fleetmapViewer` is a small hook for tests and the console.

import { ApiError, authIsOff, getAll, getJson, request, storeToken, storedToken, url } from "./api.js";
import { parsePly } from "./ply.js";
import { STATE_COLORS, TileMap, sessionColor } from "./map.js";
import { TilePanel } from "./panel.js";

const POLL_MS = 3000; // tile states in view
const TRACKS_EVERY = 5; // polls between trajectory refreshes (also on a view change or a new version)
const MAX_IN_VIEW = 64; // meshes loaded for one view, nearest the orbit target first
const MAX_KEPT = 128; // meshes kept in memory; the least recently seen beyond that are dropped
const PARALLEL = 4; // mesh downloads at once
const CACHE_NAME = "fleetmap-meshes-v1";

const $ = (id) => document.getElementById(id);
const keyOf = (t) => `${t.i},${t.j}`;

/** `#view=cx,cy,span` (map frame, metres): a view to open or share; null if absent or malformed. */
function viewFromHash() {
  const match = /(?:^#|&)view=([^&]+)/.exec(window.location.hash);
  const view = match ? match[1].split(",").map(Number) : [];
  return view.length === 3 && view.every(Number.isFinite) && view[2] > 0 ? view : null;
}

const hook = {
  ready: false, // the first refresh finished: tiles listed, the meshes in view loaded
  tilesLoaded: 0, // meshes held now
  meshRequests: [], // {tile, status, version} per mesh request (200: downloaded, 304: kept)
  errors: [], // every message shown to the user
  triangleCount: () => 0, // triangles drawn now (tiles in view, after the label and confidence filters)
  refresh: () => Promise.resolve(), // refresh({revalidate}) → a promise: list, load, draw
  tiles: () => [], // the tiles in view: [{i, j, state, version}]
  screenOf: () => null, // canvas pixel of a map-frame point
};
window.fleetmapViewer = hook;

async function openCache() {
  try {
    return window.caches ? await window.caches.open(CACHE_NAME) : null; // secure contexts only
  } catch {
    return null; // storage refused (private mode): ETags are then kept in memory only
  }
}

class Viewer {
  constructor() {
    this.map = null;
    this.panel = new TilePanel($("panel"), { onClose: () => this.map && this.map.select(null) });
    this.meshes = new Map(); // "i,j" -> {etag, version, seen}
    this.tiles = []; // the listing of the view
    this.sessions = [];
    this.hiddenSessions = new Set();
    this.polls = 0;
    this.lastBox = null;
    this.current = Promise.resolve();
    this.queued = null;
    this.connected = false;
  }

  async start() {
    $("token").value = storedToken();
    $("connect").onclick = () => this.connect().catch((err) => this.fail(err));
    $("token").addEventListener("keydown", (e) => {
      if (e.key === "Enter") $("connect").click();
    });
    try {
      this.map = new TileMap($("view"));
    } catch (err) {
      this.fail(new Error(`WebGL is unavailable in this browser: ${err.message}`));
      return;
    }
    hook.triangleCount = () => this.map.triangleCount();
    hook.refresh = (options) => this.refresh(options);
    hook.tiles = () => this.tiles.map(({ i, j, state, version }) => ({ i, j, state, version }));
    hook.screenOf = (x, y, z) => this.map.screenOf(x, y, z);
    this.bindControls();
    this.cache = await openCache();
    setInterval(() => {
      if (this.connected && $("live").checked) this.refresh().catch(() => {});
    }, POLL_MS);
    if (storedToken() || authIsOff()) await this.connect();
    else this.say("Enter a bearer token (fleetmap token create --role reader --name NAME) and connect.");
  }

  bindControls() {
    const slider = $("confidence");
    slider.addEventListener("input", () => this.applyFilter());
    $("shaded").addEventListener("change", () => this.map.setShaded($("shaded").checked));
    for (const id of ["show-gps", "show-refined"]) $(id).addEventListener("change", () => this.drawTracks());
    let settle = null;
    this.map.controls.addEventListener("end", () => {
      const view = this.map.currentView().map((v) => v.toFixed(1)).join(",");
      window.history.replaceState(null, "", `#view=${view}`); // a reload or a shared link keeps the view
      clearTimeout(settle);
      settle = setTimeout(() => this.connected && this.refresh().catch(() => {}), 300);
    });
    window.addEventListener("hashchange", () => {
      const view = viewFromHash();
      if (!view) return;
      this.map.frameAt(...view);
      if (this.connected) this.refresh().catch(() => {});
    });
    let down = null;
    const canvas = $("view");
    canvas.addEventListener("pointerdown", (e) => (down = [e.clientX, e.clientY]));
    canvas.addEventListener("pointerup", (e) => {
      if (!down || Math.hypot(e.clientX - down[0], e.clientY - down[1]) > 4 || !this.connected) return;
      const rect = canvas.getBoundingClientRect();
      const p = this.map.pick(e.clientX - rect.left, e.clientY - rect.top);
      if (p) this.openTile(Math.floor(p.x / this.map.tileSize), Math.floor(p.y / this.map.tileSize));
    });
  }

  openTile(i, j) {
    this.map.select(i, j);
    this.panel.open(i, j);
  }

  say(text) {
    $("msg").textContent = text;
    $("msg").className = "";
  }

  fail(err) {
    const text = err instanceof ApiError ? `${err.message} (HTTP ${err.status})` : `error: ${err.message}`;
    $("msg").textContent = text;
    $("msg").className = "problem";
    hook.errors.push(text);
  }

  async connect() {
    if (!this.map) return; // no WebGL: said so at start
    storeToken($("token").value.trim());
    if (!storedToken() && !authIsOff()) {
      this.say("Enter a bearer token first.");
      return;
    }
    this.connected = false;
    const [labels, capabilities] = await Promise.all([getJson("v1/labels"), getJson("v1/capabilities")]);
    this.map.tileSize = capabilities.tile_size_m;
    this.map.setPalette(labels);
    this.buildLegend(labels);
    this.applyFilter(); // the map filters each mesh as it arrives
    const view = viewFromHash();
    if (view) this.map.frameAt(...view);
    else await this.frameFusedTiles();
    this.connected = true;
    await this.refresh();
  }

  /** Frame the fused tiles of the first page of the listing (all tiles while none is fused). */
  async frameFusedTiles() {
    const all = await getJson("v1/tiles?limit=1000");
    const fused = all.items.filter((t) => t.version > 0);
    const shown = fused.length ? fused : all.items;
    if (!shown.length) {
      this.map.frame([-64, -64, 64, 64]);
      return;
    }
    const s = this.map.tileSize;
    const is = shown.map((t) => t.i), js = shown.map((t) => t.j);
    this.map.frame([Math.min(...is) * s, Math.min(...js) * s, (Math.max(...is) + 1) * s, (Math.max(...js) + 1) * s]);
  }

  buildLegend(labels) {
    const list = $("legend");
    list.replaceChildren();
    for (const label of labels) {
      const box = Object.assign(document.createElement("input"), { type: "checkbox", checked: true });
      box.dataset.label = String(label.id);
      box.addEventListener("change", () => this.applyFilter());
      const swatch = Object.assign(document.createElement("span"), { className: "swatch" });
      swatch.style.background = `rgb(${label.color.join(",")})`;
      const item = document.createElement("label");
      item.append(box, swatch, ` ${label.name}`);
      list.append(item);
    }
  }

  applyFilter() {
    const minConfidence = Number($("confidence").value);
    $("confidence-value").textContent = minConfidence.toFixed(2);
    const hidden = [...document.querySelectorAll("#legend input")].filter((b) => !b.checked).map((b) => Number(b.dataset.label));
    this.map.setFilter({ minConfidence, hidden });
    $("triangles").textContent = `${this.map.triangleCount().toLocaleString()} triangles`;
  }

  /** One refresh at a time; calls during one share the next (a revalidating call wins). */
  refresh({ revalidate = false } = {}) {
    if (this.queued) {
      this.queued.revalidate ||= revalidate;
      return this.queued.promise;
    }
    const job = { revalidate };
    job.promise = this.current.then(() => {
      this.queued = null;
      return this.refreshOnce(job);
    });
    this.queued = job;
    this.current = job.promise.catch(() => {});
    return job.promise;
  }

  async refreshOnce({ revalidate }) {
    try {
      const box = this.map.viewBox();
      const bbox = box.map((v) => v.toFixed(1)).join(",");
      this.tiles = await getAll(`v1/tiles?bbox=${bbox}&limit=1000`, 5);
      this.map.setGrid(this.tiles);
      for (const t of this.tiles) this.panel.update(t);
      const changed = await this.loadMeshes(revalidate);
      this.polls += 1;
      const moved = !this.lastBox || box.some((v, k) => Math.abs(v - this.lastBox[k]) > this.map.tileSize / 2);
      if (moved || changed || this.polls % TRACKS_EVERY === 0) {
        this.lastBox = box;
        await this.loadTracks(bbox);
      }
      hook.tilesLoaded = this.map.tiles.size;
      hook.ready = true;
      const fused = this.tiles.filter((t) => t.state === "fused").length;
      this.say(`${this.tiles.length} tiles in view (${fused} fused) · updated ${new Date().toLocaleTimeString()}`);
    } catch (err) {
      this.fail(err);
    }
  }

  /** Load the meshes in view whose version changed (all of them when revalidating); true if any did. */
  async loadMeshes(revalidate) {
    const target = this.map.controls.target;
    const s = this.map.tileSize;
    const distance = (t) => Math.hypot((t.i + 0.5) * s - target.x, (t.j + 0.5) * s - target.y);
    const inView = this.tiles.filter((t) => t.version > 0).sort((a, b) => distance(a) - distance(b)).slice(0, MAX_IN_VIEW);
    const keys = new Set(inView.map(keyOf));
    for (const key of this.map.tiles.keys()) this.map.setTileVisible(key, keys.has(key));
    const todo = inView.filter((t) => revalidate || this.meshes.get(keyOf(t))?.version !== t.version);
    let changed = false;
    const queue = [...todo];
    const worker = async () => {
      for (let t = queue.shift(); t; t = queue.shift()) {
        try {
          changed = (await this.loadMesh(t)) || changed;
        } catch (err) {
          this.fail(new Error(`tile (${t.i}, ${t.j}): ${err.message}`));
        }
      }
    };
    await Promise.all(Array.from({ length: PARALLEL }, worker));
    const now = Date.now();
    for (const key of keys) if (this.meshes.has(key)) this.meshes.get(key).seen = now;
    this.evict(keys);
    $("triangles").textContent = `${this.map.triangleCount().toLocaleString()} triangles`;
    return changed;
  }

  /** GET the tile's mesh with its ETag; true if a new mesh was downloaded, false on 304. */
  async loadMesh(t) {
    const key = keyOf(t);
    const path = `v1/tiles/${t.i}/${t.j}/mesh?format=ply`;
    const held = this.meshes.get(key);
    let etag = held?.etag;
    let stored = null;
    if (!held && this.cache) {
      stored = await this.cache.match(url(path));
      etag = stored?.headers.get("ETag") || undefined;
    }
    const resp = await request(path, { headers: etag ? { "If-None-Match": etag } : {}, cache: "no-store" });
    const version = Number(resp.headers.get("X-Tile-Version")) || t.version;
    hook.meshRequests.push({ tile: key, status: resp.status, version });
    if (resp.status === 304) {
      if (!held) this.map.setTileMesh(key, parsePly(await stored.arrayBuffer()));
      this.meshes.set(key, { etag, version, seen: Date.now() });
      return false;
    }
    const buffer = await resp.arrayBuffer();
    this.map.setTileMesh(key, parsePly(buffer));
    const fresh = resp.headers.get("ETag");
    this.meshes.set(key, { etag: fresh, version, seen: Date.now() });
    if (this.cache && fresh) {
      const headers = { ETag: fresh, "X-Tile-Version": String(version) };
      await this.cache.put(url(path), new Response(buffer, { headers })).catch(() => {});
    }
    return true;
  }

  evict(inView) {
    if (this.meshes.size <= MAX_KEPT) return;
    const old = [...this.meshes.entries()].filter(([key]) => !inView.has(key)).sort((a, b) => a[1].seen - b[1].seen);
    for (const [key] of old.slice(0, this.meshes.size - MAX_KEPT)) {
      this.meshes.delete(key);
      this.map.removeTileMesh(key);
    }
  }

  async loadTracks(bbox) {
    const page = await getJson(`v1/sessions?bbox=${bbox}&limit=200&max_points=1000`);
    this.sessions = page.items;
    const list = $("sessions");
    list.replaceChildren();
    for (const session of this.sessions) {
      const box = Object.assign(document.createElement("input"), {
        type: "checkbox", checked: !this.hiddenSessions.has(session.session_id),
      });
      box.addEventListener("change", () => {
        if (box.checked) this.hiddenSessions.delete(session.session_id);
        else this.hiddenSessions.add(session.session_id);
        this.drawTracks();
      });
      const swatch = Object.assign(document.createElement("span"), { className: "swatch" });
      swatch.style.background = `#${sessionColor(session.session_id).getHexString()}`;
      const refined = session.points.filter((p) => p.pose_refined_t).length;
      const item = document.createElement("label");
      item.title = `${session.agent_id}: ${session.submaps} submaps, ${refined} of those shown refined`;
      item.append(box, swatch, ` ${session.session_id}`);
      list.append(item);
    }
    $("sessions-note").textContent = page.next_cursor ? "(the first 200 sessions in view)" : "";
    this.drawTracks();
  }

  drawTracks() {
    this.map.setTracks(this.sessions, {
      gps: $("show-gps").checked, refined: $("show-refined").checked, hiddenSessions: this.hiddenSessions,
    });
  }
}

for (const [state, color] of Object.entries(STATE_COLORS)) {
  const item = document.createElement("span");
  item.className = "state-key";
  const swatch = Object.assign(document.createElement("span"), { className: "swatch" });
  swatch.style.background = color;
  item.append(swatch, ` ${state}`);
  $("states").append(item);
}

new Viewer().start().catch((err) => {
  $("msg").textContent = err.message;
  $("msg").className = "problem";
  hook.errors.push(err.message);
});
