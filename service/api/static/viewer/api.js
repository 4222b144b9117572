// The fleetmap HTTP API as the viewer uses it: the bearer token (kept in this browser's
// localStorage only), requests relative to the page (so the viewer works behind a path prefix),
// and RFC 9457 problem documents turned into errors whose message is the problem's `detail`.

const TOKEN_KEY = "fleetmap-token";

export function storedToken() {
  return localStorage.getItem(TOKEN_KEY) || "";
}

export function storeToken(token) {
  localStorage.setItem(TOKEN_KEY, token);
}

/** An API answer that is not a success: `status`, and the problem document's `detail` as message. */
export class ApiError extends Error {
  constructor(status, detail, problem) {
    super(detail);
    this.name = "ApiError";
    this.status = status;
    this.problem = problem;
  }
}

export function url(path) {
  return new URL(path, document.baseURI).href;
}

async function problemOf(resp) {
  let problem = null;
  try {
    problem = await resp.json();
  } catch {
    // not a problem document (a proxy's HTML page): fall back to the status line
  }
  const detail = (problem && (problem.detail || problem.title)) || `${resp.status} ${resp.statusText}`;
  return new ApiError(resp.status, detail, problem);
}

/** fetch with the bearer token; `ok` answers and 304 are returned, anything else throws ApiError. */
export async function request(path, { method = "GET", headers = {}, body, cache = "default" } = {}) {
  const token = storedToken();
  const all = { ...headers };
  if (token) all.Authorization = `Bearer ${token}`;
  const resp = await fetch(url(path), { method, headers: all, body, cache });
  if (!resp.ok && resp.status !== 304) throw await problemOf(resp);
  return resp;
}

/** Whether the service wants no token (FLEETMAP_AUTH=off, e.g. `fleetmap demo`): the page served at `/`
 * says so in its `fleetmap-auth` meta tag; then the viewer connects without asking for one. */
export function authIsOff() {
  const meta = document.querySelector('meta[name="fleetmap-auth"]');
  return Boolean(meta && meta.content === "off");
}

export async function getJson(path) {
  return (await request(path)).json();
}

export async function postJson(path) {
  return (await request(path, { method: "POST" })).json();
}

/** Every item of a paginated listing (`{items, next_cursor}`), at most `maxPages` pages. */
export async function getAll(path, maxPages = 10) {
  const items = [];
  let cursor = null;
  for (let page = 0; page < maxPages; page += 1) {
    const sep = path.includes("?") ? "&" : "?";
    const body = await getJson(cursor ? `${path}${sep}cursor=${encodeURIComponent(cursor)}` : path);
    items.push(...body.items);
    cursor = body.next_cursor;
    if (!cursor) break;
  }
  return items;
}

/** Save an authenticated download (the bearer token rules out a plain link) under `filename`. */
export async function download(path, filename) {
  const resp = await request(path, { cache: "no-store" });
  const blobUrl = URL.createObjectURL(await resp.blob());
  const a = document.createElement("a");
  a.href = blobUrl;
  a.download = filename;
  document.body.append(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(blobUrl), 10_000);
}
