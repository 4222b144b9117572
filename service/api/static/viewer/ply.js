// Reader of the fused tile PLY (API.md: binary little endian, map frame, metres): vertex x, y, z,
// red, green, blue, label, confidence; face vertex_indices and label. The header is read, not
// assumed, so extra properties or another property order still parse; polygons are fanned.

const SCALARS = {
  char: [1, "getInt8"], int8: [1, "getInt8"],
  uchar: [1, "getUint8"], uint8: [1, "getUint8"],
  short: [2, "getInt16"], int16: [2, "getInt16"],
  ushort: [2, "getUint16"], uint16: [2, "getUint16"],
  int: [4, "getInt32"], int32: [4, "getInt32"],
  uint: [4, "getUint32"], uint32: [4, "getUint32"],
  float: [4, "getFloat32"], float32: [4, "getFloat32"],
  double: [8, "getFloat64"], float64: [8, "getFloat64"],
};

function scalar(type) {
  const found = SCALARS[type];
  if (!found) throw new Error(`PLY: unknown property type ${type}`);
  return found;
}

function parseHeader(bytes) {
  const end = "end_header\n";
  const head = new TextDecoder("ascii").decode(bytes.subarray(0, Math.min(bytes.length, 4096)));
  const stop = head.indexOf(end);
  if (!head.startsWith("ply\n") || stop < 0) throw new Error("PLY: not a PLY file");
  const elements = [];
  let format = null;
  for (const line of head.slice(0, stop).split("\n").slice(1)) {
    const words = line.trim().split(/\s+/);
    if (words[0] === "format") format = words[1];
    else if (words[0] === "element") elements.push({ name: words[1], count: Number(words[2]), props: [] });
    else if (words[0] === "property") {
      const props = elements[elements.length - 1].props;
      if (words[1] === "list") props.push({ name: words[4], count: scalar(words[2]), item: scalar(words[3]) });
      else props.push({ name: words[2], type: scalar(words[1]) });
    }
  }
  if (format !== "binary_little_endian") throw new Error(`PLY: format ${format} is not binary_little_endian`);
  return { elements, offset: stop + end.length };
}

/**
 * Parse a fused tile PLY into flat arrays: `positions` (Float32Array, 3 per vertex), `vertexLabel`
 * (Uint8Array), `confidence` (Float32Array, 1 where absent), `faces` (Uint32Array, 3 per triangle)
 * and `faceLabel` (Uint8Array; the first vertex's label where absent).
 */
export function parsePly(buffer) {
  const bytes = new Uint8Array(buffer);
  const { elements, offset } = parseHeader(bytes);
  const view = new DataView(buffer);
  let at = offset;
  const out = {};
  for (const el of elements) {
    if (el.name === "vertex") {
      out.positions = new Float32Array(el.count * 3);
      out.vertexLabel = new Uint8Array(el.count);
      out.confidence = new Float32Array(el.count).fill(1);
    }
    const triangles = [];
    const labels = [];
    for (let n = 0; n < el.count; n += 1) {
      let polygon = null;
      let label = -1;
      for (const p of el.props) {
        if (p.count) {
          const k = view[p.count[1]](at, true);
          at += p.count[0];
          const items = new Array(k);
          for (let m = 0; m < k; m += 1, at += p.item[0]) items[m] = view[p.item[1]](at, true);
          if (p.name === "vertex_indices" || p.name === "vertex_index") polygon = items;
          continue;
        }
        const value = view[p.type[1]](at, true);
        at += p.type[0];
        if (el.name === "vertex") {
          if (p.name === "x") out.positions[3 * n] = value;
          else if (p.name === "y") out.positions[3 * n + 1] = value;
          else if (p.name === "z") out.positions[3 * n + 2] = value;
          else if (p.name === "label") out.vertexLabel[n] = value;
          else if (p.name === "confidence") out.confidence[n] = value;
        } else if (p.name === "label") label = value;
      }
      if (el.name === "face" && polygon) {
        for (let m = 1; m + 1 < polygon.length; m += 1) {
          triangles.push(polygon[0], polygon[m], polygon[m + 1]);
          labels.push(label >= 0 ? label : out.vertexLabel[polygon[0]]);
        }
      }
    }
    if (el.name === "face") {
      out.faces = Uint32Array.from(triangles);
      out.faceLabel = Uint8Array.from(labels);
    }
  }
  if (at > bytes.length) throw new Error("PLY: truncated body");
  if (!out.positions || !out.faces) throw new Error("PLY: no vertex or face element");
  const vertices = out.positions.length / 3;
  if (out.faces.some((v) => v >= vertices)) throw new Error("PLY: a face refers to a missing vertex");
  return out;
}
