// A recording read as Foxglove reads it: @mcap/core's indexed reader (zstd chunks through
// @foxglove/wasm-zstd), each message decoded by its channel's encoding, the messages of
// Foxglove's own schemas (foxglove.PointCloud, foxglove.SceneUpdate, ...) checked against
// @foxglove/schemas' JSON Schemas, and the message paths of a layout's panels evaluated.
// For tests/test_foxglove.py.
//
//   node mcap_check.mjs REC.mcap [--layout LAYOUT.json --tab TITLE]
//
// Prints one JSON object: {"topics": {topic: {schemaName, encoding, messages, invalid, errors,
// first}}, "paths": {path: {topic, messages, values}}}: "invalid" counts messages of a Foxglove
// schema that do not validate (the first "errors" say why); "first" is the first message
// decoded (a point cloud's points unpacked by its fields); "values" counts the messages where
// the path gives a value, "numbers" those where it gives a number or an array of numbers.
import { McapIndexedReader } from "@mcap/core";
import foxgloveSchemas from "@foxglove/schemas/jsonschema.js"; // CommonJS: its exports as one object
import zstd from "@foxglove/wasm-zstd";
import { open, readFile } from "node:fs/promises";

function parseArgs(argv) {
  const opts = { file: null, layout: null, tab: null };
  for (let i = 0; i < argv.length; i++) {
    if (argv[i] === "--layout") opts.layout = argv[++i];
    else if (argv[i] === "--tab") opts.tab = argv[++i];
    else opts.file = argv[i];
  }
  return opts;
}

// A JSON Schema check of what Foxglove's schemas use: type, properties, required, items, const,
// oneOf (of consts), minimum, maximum. Returns the first problems found, as paths.
function validate(schema, value, path = "$", out = []) {
  if (out.length >= 5) return out;
  if (schema.oneOf) {
    if (!schema.oneOf.some((s) => validate(s, value, path, []).length === 0)) out.push(`${path}: matches no oneOf`);
    return out;
  }
  if ("const" in schema && value !== schema.const) out.push(`${path}: ${JSON.stringify(value)} != ${schema.const}`);
  const t = schema.type;
  const kind = Array.isArray(value) ? "array" : value === null ? "null" : typeof value;
  const ok = t === undefined || t === kind || (t === "integer" && Number.isInteger(value))
    || (t === "number" && kind === "number");
  if (!ok) {
    out.push(`${path}: ${kind}, expected ${t}`);
    return out;
  }
  if (schema.minimum !== undefined && value < schema.minimum) out.push(`${path}: ${value} < ${schema.minimum}`);
  if (schema.maximum !== undefined && value > schema.maximum) out.push(`${path}: ${value} > ${schema.maximum}`);
  if (kind === "object") {
    for (const r of schema.required ?? []) if (!(r in value)) out.push(`${path}.${r}: missing`);
    for (const [k, s] of Object.entries(schema.properties ?? {})) {
      if (k in value) validate(s, value[k], `${path}.${k}`, out);
    }
  }
  if (kind === "array" && schema.items) value.forEach((v, i) => validate(schema.items, v, `${path}[${i}]`, out));
  return out;
}

const NUMERIC = { 1: ["getUint8", 1], 2: ["getInt8", 1], 3: ["getUint16", 2], 4: ["getInt16", 2],
  5: ["getUint32", 4], 6: ["getInt32", 4], 7: ["getFloat32", 4], 8: ["getFloat64", 8] };

function points(cloud) {
  const data = Buffer.from(cloud.data, "base64");
  const view = new DataView(data.buffer, data.byteOffset, data.byteLength);
  const out = [];
  for (let base = 0; cloud.point_stride > 0 && base + cloud.point_stride <= data.length; base += cloud.point_stride) {
    const p = {};
    for (const f of cloud.fields) {
      const [get, size] = NUMERIC[f.type];
      if (f.offset + size > cloud.point_stride) throw new Error(`field ${f.name} beyond the stride`);
      const v = view[get](base + f.offset, true);
      p[f.name] = Number.isNaN(v) ? null : v;
    }
    out.push(p);
  }
  return out;
}

// A Foxglove message path: TOPIC, then .field, [i], [:] and {field==value} filters.
function evaluatePath(path, topics) {
  const topic = topics.filter((t) => path === t || path.startsWith(t + ".") || path.startsWith(t + "{"))
    .sort((a, b) => b.length - a.length)[0];
  if (topic === undefined) return { topic: null, steps: [] };
  const steps = [];
  const re = /\.([A-Za-z_][A-Za-z0-9_]*)|\[(\d+|:)\]|\{([A-Za-z_][A-Za-z0-9_]*)==("?)([^"}]*)\4\}/g;
  for (const m of path.slice(topic.length).matchAll(re)) {
    if (m[1] !== undefined) steps.push({ field: m[1] });
    else if (m[2] !== undefined) steps.push({ index: m[2] });
    else steps.push({ filter: m[3], equals: m[5] });
  }
  return { topic, steps };
}

function apply(steps, value) {
  let v = value;
  for (const s of steps) {
    if (v === undefined || v === null) return undefined;
    if (s.field !== undefined) v = v[s.field];
    else if (s.index === ":") { if (!Array.isArray(v)) return undefined; }
    else if (s.index !== undefined) v = Array.isArray(v) ? v[Number(s.index)] : undefined;
    else if (String(v[s.filter]) !== s.equals) return undefined;
  }
  return v;
}

const isNumbers = (v) => typeof v === "number" || (Array.isArray(v) && v.length > 0 && v.every((x) => typeof x === "number"));

function layoutPaths(layout, tabTitle) {
  const panels = layout.configById;
  const tab = Object.values(panels).find((p) => Array.isArray(p.tabs));
  const leaves = (n) => (typeof n === "string" ? [n] : n ? [...leaves(n.first), ...leaves(n.second)] : []);
  const ids = leaves(tab.tabs.find((t) => t.title === tabTitle).layout);
  const paths = [];
  for (const id of ids) {
    const cfg = panels[id];
    for (const t of Object.keys(cfg.topics ?? {})) paths.push(t);
    for (const p of cfg.paths ?? []) paths.push(p.value);
    if (cfg.xAxisPath) paths.push(cfg.xAxisPath.value);
    if (cfg.topicPath) paths.push(cfg.topicPath);
  }
  return paths;
}

async function main() {
  const opts = parseArgs(process.argv.slice(2));
  await zstd.isLoaded;
  const handle = await open(opts.file, "r");
  const size = (await handle.stat()).size;
  const readable = {
    size: async () => BigInt(size),
    read: async (offset, length) => {
      const buf = Buffer.alloc(Number(length));
      await handle.read(buf, 0, Number(length), Number(offset));
      return new Uint8Array(buf.buffer, buf.byteOffset, buf.byteLength);
    },
  };
  const reader = await McapIndexedReader.Initialize({
    readable,
    decompressHandlers: { zstd: (data, decompressedSize) => zstd.decompress(data, Number(decompressedSize)) },
  });
  const topics = {};
  const decoded = {}; // topic -> decoded messages (JSON channels)
  const text = new TextDecoder();
  for await (const msg of reader.readMessages()) {
    const ch = reader.channelsById.get(msg.channelId);
    const schema = reader.schemasById.get(ch.schemaId);
    const t = (topics[ch.topic] ??= { schemaName: schema?.name ?? null, encoding: ch.messageEncoding, messages: 0,
      invalid: 0, errors: [], first: null });
    t.messages += 1;
    if (ch.messageEncoding !== "json") continue;
    const value = JSON.parse(text.decode(msg.data));
    const official = schema && schema.name.startsWith("foxglove.") ? foxgloveSchemas[schema.name.slice(9)] : null;
    if (official) {
      const problems = validate(official, value);
      if (problems.length) {
        t.invalid += 1;
        if (t.errors.length < 5) t.errors.push(...problems.slice(0, 5 - t.errors.length));
      }
    } else if (schema && schema.name.startsWith("foxglove.")) {
      t.errors.push(`no schema ${schema.name} in @foxglove/schemas`);
    }
    if (t.first === null) t.first = schema?.name === "foxglove.PointCloud" ? { ...value, points: points(value) } : value;
    (decoded[ch.topic] ??= []).push(value);
  }
  const paths = {};
  if (opts.layout) {
    const layout = JSON.parse(await readFile(opts.layout, "utf8"));
    for (const p of layoutPaths(layout, opts.tab)) {
      const { topic, steps } = evaluatePath(p, Object.keys(topics));
      const msgs = topic === null ? [] : decoded[topic] ?? [];
      const got = msgs.map((m) => apply(steps, m));
      paths[p] = { topic, messages: msgs.length, values: got.filter((v) => v !== undefined).length,
        numbers: got.filter(isNumbers).length };
    }
  }
  await handle.close();
  process.stdout.write(JSON.stringify({ topics, paths }) + "\n");
}

main().catch((err) => {
  process.stdout.write(JSON.stringify({ error: String(err?.stack ?? err) }) + "\n");
  process.exit(4);
});
