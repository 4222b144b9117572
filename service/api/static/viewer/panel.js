// The tile panel: a clicked tile's state, versions (with downloads), submaps, fusion jobs and the
// operator's re-fuse. API data is only ever set as text (session ids come from vehicles).

import { ApiError, download, getJson, postJson, request } from "./api.js";

function el(tag, props = {}, ...children) {
  const node = document.createElement(tag);
  Object.assign(node, props);
  node.append(...children.filter((c) => c !== null && c !== undefined));
  return node;
}

function table(headers, rows) {
  const head = el("tr", {}, ...headers.map((h) => el("th", { textContent: h })));
  return el("table", {}, el("thead", {}, head), el("tbody", {}, ...rows));
}

function row(...cells) {
  return el("tr", {}, ...cells.map((c) => (c instanceof Node ? el("td", {}, c) : el("td", { textContent: String(c) }))));
}

function when(iso) {
  return iso ? new Date(iso).toLocaleString() : "—";
}

const FINISHED = new Set(["succeeded", "failed"]);

export class TilePanel {
  constructor(root, { onClose }) {
    this.root = root;
    this.onClose = onClose;
    this.tile = null;
    this.generation = 0; // a newer open() makes older answers stale
  }

  get isOpen() {
    return this.tile !== null;
  }

  close() {
    this.tile = null;
    this.generation += 1;
    this.root.hidden = true;
    this.root.replaceChildren();
    this.onClose();
  }

  /** Show tile (i, j); its problems (404, 403) are shown in the panel, never thrown. */
  async open(i, j) {
    const generation = ++this.generation;
    this.root.hidden = false;
    this.message = el("p", { className: "problem", id: "panel-msg" });
    this.root.replaceChildren(
      el("div", { className: "panel-head" },
        el("h2", { textContent: `Tile (${i}, ${j})` }),
        el("button", { textContent: "×", title: "close", className: "close", onclick: () => this.close() })),
      this.message,
    );
    this.tile = { i, j };
    try {
      const tile = await getJson(`v1/tiles/${i}/${j}`);
      if (generation !== this.generation) return;
      this.tile = tile;
      this.root.append(this.summary(tile), this.actions(tile));
      const [versions, submaps] = await Promise.all([
        getJson(`v1/tiles/${i}/${j}/versions?limit=20`),
        getJson(`v1/tiles/${i}/${j}/submaps?limit=50`),
      ]);
      if (generation !== this.generation) return;
      this.root.append(this.versions(tile, versions), this.submaps(tile, submaps), this.jobsSection(tile));
    } catch (err) {
      if (generation === this.generation) this.show(err);
    }
  }

  /** The polled tile listing changed this tile: update its state line. */
  update(tile) {
    if (!this.tile || tile.i !== this.tile.i || tile.j !== this.tile.j || !this.stateLine) return;
    this.stateLine.replaceChildren(...this.stateText(tile));
  }

  show(err) {
    this.message.textContent = err instanceof ApiError ? err.message : `error: ${err.message}`;
  }

  stateText(t) {
    const progress = t.state === "fusing" ? ` ${Math.round(t.progress * 100)} %` : "";
    const parts = [
      el("span", { className: `state ${t.state}`, textContent: t.state + progress }),
      ` · version ${t.version} · ${t.submaps} submaps · ${t.sessions} sessions · fused ${when(t.fused_at)}`,
    ];
    if (t.last_error) parts.push(el("div", { className: "problem", textContent: `last error: ${t.last_error}` }));
    return parts;
  }

  summary(t) {
    this.stateLine = el("p", { className: "tile-state" }, ...this.stateText(t));
    return this.stateLine;
  }

  actions(t) {
    const name = (fmt) => `tile_${t.i}_${t.j}_v${t.version}.${fmt}`;
    const get = (fmt) => () =>
      download(`v1/tiles/${t.i}/${t.j}/mesh?format=${fmt}`, name(fmt)).catch((err) => this.show(err));
    const fused = t.version > 0;
    return el("div", { className: "actions" },
      el("button", { textContent: "Download PLY", disabled: !fused, onclick: get("ply"), id: "download-ply" }),
      el("button", { textContent: "Download GLB", disabled: !fused, onclick: get("glb"), id: "download-glb" }),
      el("button", { textContent: "Re-fuse (operator)", id: "refuse", onclick: () => this.refuse(t) }));
  }

  versions(t, page) {
    const rows = page.items.map((v) => row(
      v.version, when(v.fused_at), v.faces ?? "—", v.job_id ? v.job_id.slice(0, 8) : "—",
      el("span", {},
        el("button", { textContent: "ply", onclick: () => this.fetchFile(v.links.ply, `tile_${t.i}_${t.j}_v${v.version}.ply`) }),
        el("button", { textContent: "glb", onclick: () => this.fetchFile(v.links.glb, `tile_${t.i}_${t.j}_v${v.version}.glb`) })),
    ));
    const body = rows.length ? table(["version", "fused", "faces", "job", "download"], rows) : el("p", { textContent: "never fused" });
    return el("section", { id: "versions" }, el("h3", { textContent: "Versions" }), body);
  }

  fetchFile(link, filename) {
    download(link, filename).catch((err) => this.show(err));
  }

  submaps(t, page) {
    const tbody = el("tbody");
    const section = el("section", { id: "submaps" }, el("h3", { textContent: "Submaps" }));
    const add = (items) => tbody.append(...items.map((s) => row(s.session_id, s.seq, s.agent_id, s.refined ? "refined" : "GPS only")));
    add(page.items);
    const head = el("tr", {}, ...["session", "seq", "agent", "pose"].map((h) => el("th", { textContent: h })));
    section.append(el("table", {}, el("thead", {}, head), tbody));
    let cursor = page.next_cursor;
    if (cursor) {
      const more = el("button", { textContent: "more" });
      more.onclick = async () => {
        try {
          const next = await getJson(`v1/tiles/${t.i}/${t.j}/submaps?limit=50&cursor=${encodeURIComponent(cursor)}`);
          add(next.items);
          cursor = next.next_cursor;
          if (!cursor) more.remove();
        } catch (err) {
          this.show(err);
        }
      };
      section.append(more);
    }
    return section;
  }

  jobsSection(t) {
    const section = el("section", { id: "jobs" }, el("h3", { textContent: "Fusion jobs" }));
    const load = el("button", { textContent: "Show jobs (operator)", id: "show-jobs" });
    load.onclick = async () => {
      try {
        const jobs = await getJson(`v1/tiles/${t.i}/${t.j}/jobs?limit=20`);
        const rows = jobs.items.map((job) => row(
          job.id.slice(0, 8), job.kind, job.state, `${Math.round(job.progress * 100)} %`, job.trigger,
          when(job.created_at), job.error || "",
        ));
        load.replaceWith(rows.length ? table(["job", "kind", "state", "progress", "trigger", "created", "error"], rows)
          : el("p", { textContent: "no fusion job yet" }));
      } catch (err) {
        this.show(err);
      }
    };
    section.append(load);
    return section;
  }

  async refuse(t) {
    const generation = this.generation;
    try {
      const accepted = await postJson(`v1/tiles/${t.i}/${t.j}/fuse`);
      this.message.textContent = "";
      const status = el("p", { id: "refuse-status", textContent: `fusion job ${accepted.job_id} accepted` });
      this.root.querySelector(".actions").after(status);
      this.follow(accepted.job_id, status, generation);
    } catch (err) {
      this.show(err);
    }
  }

  /** Follow a job until it ends (or the panel shows another tile). */
  async follow(jobId, status, generation) {
    while (generation === this.generation) {
      try {
        const job = await (await request(`v1/jobs/${jobId}`, { cache: "no-store" })).json();
        status.textContent = `fusion job ${jobId.slice(0, 8)} (${job.kind}): ${job.state} ${Math.round(job.progress * 100)} %`
          + (job.error ? ` — ${job.error}` : "");
        if (FINISHED.has(job.state)) return;
      } catch (err) {
        this.show(err);
        return;
      }
      await new Promise((resolve) => setTimeout(resolve, 2000));
    }
  }
}
