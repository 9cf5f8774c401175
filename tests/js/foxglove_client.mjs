// A Foxglove WebSocket client that is not ours: @foxglove/ws-protocol over `ws`, protobuf
// decoded with protobufjs from the schema the server advertises. For tests/test_foxglove.py.
//
//   node foxglove_client.mjs ws://127.0.0.1:8765 [--topic REGEX] [--timeout-s 15] [--connect-s 10]
//
// Subscribes to every advertised channel whose topic matches REGEX (default: all) and prints
// one JSON object a line: {"event": "open"}, {"event": "advertise", ...}, {"event": "status", ...},
// {"event": "message", "topic", "schemaName", "encoding", "log_time_ns", "data", "text"} and, last,
// {"event": "end", "reason"}. A foxglove.PointCloud comes out as {"frame_id", "timestamp_ns",
// "point_stride", "fields", "points": [{field: value}]}, its packed points read by their fields;
// a JSON channel's message as the object ("data", where integers beyond 2^53 are rounded, as in
// any JavaScript client) and as its text ("text"). Exits when the server closes the connection, at
// --timeout-s, or, before the first connection, after --connect-s of retries (exit code 3).
import wsProtocol from "@foxglove/ws-protocol"; // a CommonJS module: no named exports under ESM
import protobuf from "protobufjs";
import descriptor from "protobufjs/ext/descriptor/index.js";
import WebSocket from "ws";

const { FoxgloveClient } = wsProtocol;
// foxglove-sdk servers (0.x, and foxglove_bridge 3) accept only the subprotocol "foxglove.sdk.v1",
// the same protocol as ws-protocol's "foxglove.websocket.v1" under a new name; FoxgloveClient
// leaves the subprotocol to the WebSocket, so offer both.
const SUBPROTOCOLS = ["foxglove.sdk.v1", FoxgloveClient.SUPPORTED_SUBPROTOCOL];

function parseArgs(argv) {
  const opts = { url: null, topic: ".*", timeoutS: 15, connectS: 10 };
  for (let i = 0; i < argv.length; i++) {
    const a = argv[i];
    if (a === "--topic") opts.topic = argv[++i];
    else if (a === "--timeout-s") opts.timeoutS = Number(argv[++i]);
    else if (a === "--connect-s") opts.connectS = Number(argv[++i]);
    else if (opts.url === null) opts.url = a;
    else throw new Error(`foxglove_client: unexpected argument ${a}`);
  }
  if (opts.url === null) throw new Error("foxglove_client: give the server's ws:// URL");
  return opts;
}

const print = (obj) => process.stdout.write(JSON.stringify(obj) + "\n");

// foxglove.NumericType -> [size, DataView reader]
const NUMERIC = {
  1: [1, (v, o) => v.getUint8(o)],
  2: [1, (v, o) => v.getInt8(o)],
  3: [2, (v, o) => v.getUint16(o, true)],
  4: [2, (v, o) => v.getInt16(o, true)],
  5: [4, (v, o) => v.getUint32(o, true)],
  6: [4, (v, o) => v.getInt32(o, true)],
  7: [4, (v, o) => v.getFloat32(o, true)],
  8: [8, (v, o) => v.getFloat64(o, true)],
};

function timestampNs(ts) {
  if (!ts) return null;
  const sec = BigInt((ts.seconds ?? ts.sec ?? 0).toString());
  const nsec = BigInt((ts.nanos ?? ts.nsec ?? 0).toString());
  return (sec * 1000000000n + nsec).toString();
}

function pointCloud(msg) {
  const data = msg.data instanceof Uint8Array ? msg.data : new Uint8Array(msg.data ?? []); // absent: []
  const view = new DataView(data.buffer, data.byteOffset, data.byteLength);
  const fields = msg.fields.map((f) => ({ name: f.name, offset: f.offset, type: f.type }));
  const stride = msg.pointStride;
  const points = [];
  if (stride > 0) {
    for (let base = 0; base + stride <= data.byteLength; base += stride) {
      const p = {};
      for (const f of fields) {
        const [size, read] = NUMERIC[f.type] ?? [0, null];
        if (read === null || f.offset + size > stride) throw new Error(`bad field ${JSON.stringify(f)}`);
        const value = read(view, base + f.offset);
        p[f.name] = Number.isNaN(value) ? null : value;
      }
      points.push(p);
    }
  }
  return { frame_id: msg.frameId, timestamp_ns: timestampNs(msg.timestamp), point_stride: stride, fields, points };
}

function decoderFor(channel) {
  if (channel.encoding === "json") {
    // the text too: JSON.parse rounds integers beyond 2^53, such as timestamp_ns
    const text = new TextDecoder();
    return (bytes) => {
      const raw = text.decode(bytes);
      return { parsed: JSON.parse(raw), raw };
    };
  }
  if (channel.encoding === "protobuf") {
    const set = descriptor.FileDescriptorSet.decode(Buffer.from(channel.schema, "base64"));
    const type = protobuf.Root.fromDescriptor(set).lookupType(channel.schemaName);
    return (bytes) => {
      const msg = type.decode(bytes);
      return channel.schemaName === "foxglove.PointCloud" ? pointCloud(msg) : type.toObject(msg, { longs: String });
    };
  }
  return null;
}

function main() {
  const opts = parseArgs(process.argv.slice(2));
  const topic = new RegExp(opts.topic);
  const deadline = Date.now() + opts.connectS * 1000;
  const end = (reason, code = 0) => {
    print({ event: "end", reason });
    process.exit(code);
  };
  setTimeout(() => end("timeout"), opts.timeoutS * 1000).unref();

  // One WebSocket and one FoxgloveClient per attempt, every listener attached at once: the server
  // advertises its channels right after the handshake, so a listener added later misses them.
  const attempt = () => {
    const ws = new WebSocket(opts.url, SUBPROTOCOLS);
    const client = new FoxgloveClient({ ws });
    const subs = new Map(); // subscription id -> {topic, schemaName, encoding, decode}
    let opened = false;
    client.on("open", () => {
      opened = true;
      print({ event: "open", protocol: ws.protocol });
    });
    client.on("error", (err) => {
      if (opened) end(`error: ${err?.message ?? err}`, 4);
    });
    client.on("close", () => {
      if (opened) end("closed by the server");
      else if (Date.now() >= deadline) end(`no server at ${opts.url} within ${opts.connectS} s`, 3);
      else setTimeout(attempt, 100);
    });
    const wanted = new Map(); // channel id -> {topic, schemaName, encoding, decode, subId, retries}
    const subscribe = (channelId) => {
      const sub = wanted.get(channelId);
      sub.subId = client.subscribe(channelId);
      subs.set(sub.subId, sub);
    };
    client.on("advertise", (channels) => {
      for (const ch of channels) {
        print({ event: "advertise", topic: ch.topic, encoding: ch.encoding, schemaName: ch.schemaName,
                schemaEncoding: ch.schemaEncoding ?? null });
        if (!topic.test(ch.topic)) continue;
        const decode = decoderFor(ch);
        if (decode === null) continue;
        wanted.set(ch.id, { topic: ch.topic, schemaName: ch.schemaName, encoding: ch.encoding, decode, retries: 0 });
        subscribe(ch.id);
      }
    });
    // foxglove-sdk 0.30 can refuse a subscription sent right after a channel's advertisement
    // ("Unknown channel ID"); subscribe again a little later, at most 20 times a channel.
    client.on("status", ({ level, message }) => {
      print({ event: "status", level, message });
      const m = /Unknown channel ID: (\d+)/.exec(message);
      const sub = m ? wanted.get(Number(m[1])) : undefined;
      if (sub === undefined || sub.retries >= 20) return;
      sub.retries += 1;
      subs.delete(sub.subId);
      client.unsubscribe(sub.subId);
      setTimeout(() => subscribe(Number(m[1])), 50);
    });
    client.on("message", ({ subscriptionId, timestamp, data: view }) => {
      const sub = subs.get(subscriptionId);
      if (!sub) return;
      const bytes = new Uint8Array(view.buffer, view.byteOffset, view.byteLength);
      let decoded;
      try {
        decoded = sub.decode(bytes);
      } catch (err) {
        end(`error: cannot decode a message of ${sub.topic}: ${err.message ?? err}`, 4);
      }
      const [data, text] = sub.encoding === "json" ? [decoded.parsed, decoded.raw] : [decoded, null];
      print({ event: "message", topic: sub.topic, schemaName: sub.schemaName, encoding: sub.encoding,
              log_time_ns: timestamp.toString(), data, text });
    });
  };
  attempt();
}

try {
  main();
} catch (err) {
  print({ event: "end", reason: `error: ${err.message ?? err}` });
  process.exit(4);
}
