// The official Foxglove WebSocket client (npm @foxglove/ws-protocol, FoxgloveClient, which
// offers the subprotocol it names: foxglove.websocket.v1) as a viewer runs it: connect
// (retrying while the server starts), subscribe to every channel advertised, collect every
// message until the server closes or the time is up. Writes one JSON object to --out:
//   {protocol, serverInfo, channels, messages: [[topic, logTimeNs (string), base64], ...],
//    closed: "server" | "client", error}
// Exit status 0 when it connected, 1 when it could not (the error in the JSON and on stderr).
//
//   node foxglove_client.mjs --url ws://127.0.0.1:8765 --out got.json
//        [--seconds 60] [--connect-timeout 120] [--close-after N] [--subprotocol NAME]
//
// --close-after N: disconnect by itself after N messages (a viewer closing its tab).
// --subprotocol NAME: offer NAME instead of the client's own (measure_servers.py only).
import { writeFileSync } from "node:fs";
import { parseArgs } from "node:util";

import wsProtocol from "@foxglove/ws-protocol"; // CommonJS: its exports as one object
import WebSocket from "ws";

const { FoxgloveClient } = wsProtocol;

const { values: opt } = parseArgs({
  options: {
    url: { type: "string" },
    out: { type: "string" },
    seconds: { type: "string", default: "60" },
    "connect-timeout": { type: "string", default: "120" },
    "close-after": { type: "string", default: "0" },
    subprotocol: { type: "string" },
  },
});
if (!opt.url || !opt.out) {
  console.error("foxglove_client.mjs: --url and --out are required");
  process.exit(2);
}
const seconds = Number(opt.seconds);
const connectTimeout = Number(opt["connect-timeout"]);
const closeAfter = Number(opt["close-after"]);

const result = { protocol: null, serverInfo: null, channels: [], messages: [], closed: null,
                 error: null };
let finished = false;

function finish(code) {
  if (finished) return;
  finished = true;
  writeFileSync(opt.out, JSON.stringify(result));
  process.exit(code);
}

const t0 = Date.now();

function connect() {
  const ws = new WebSocket(opt.url, [opt.subprotocol ?? FoxgloveClient.SUPPORTED_SUBPROTOCOL]);
  // ws's own events, before FoxgloveClient takes the on* handlers: a refused connection
  // (the server not listening yet) is retried, any other failure is the result
  let opened = false;
  ws.once("open", () => { opened = true; });
  ws.once("error", (err) => {
    if (opened) return;
    if (err.code === "ECONNREFUSED" && (Date.now() - t0) / 1000 < connectTimeout) {
      setTimeout(connect, 200);
      return;
    }
    result.error = String(err.message ?? err);
    console.error(`foxglove_client.mjs: ${result.error}`);
    finish(1);
  });
  const client = new FoxgloveClient({ ws });
  const channels = new Map(); // channel id -> channel
  const subs = new Map(); // subscription id -> channel
  client.on("open", () => {
    result.protocol = ws.protocol;
    setTimeout(() => {
      result.closed = "client";
      client.close();
      finish(0);
    }, seconds * 1000);
  });
  client.on("serverInfo", (info) => { result.serverInfo = info; });
  client.on("advertise", (chans) => {
    for (const ch of chans) {
      channels.set(ch.id, ch);
      result.channels.push(ch);
      subs.set(client.subscribe(ch.id), ch);
    }
  });
  client.on("message", ({ subscriptionId, timestamp, data }) => {
    const ch = subs.get(subscriptionId);
    const bytes = Buffer.from(data.buffer, data.byteOffset, data.byteLength);
    result.messages.push([ch ? ch.topic : null, timestamp.toString(), bytes.toString("base64")]);
    if (closeAfter > 0 && result.messages.length >= closeAfter) {
      result.closed = "client";
      client.close();
      // wait for the close handshake to finish before leaving
    }
  });
  client.on("close", () => {
    if (!opened) return; // a refused attempt: retried above
    if (result.closed === null) result.closed = "server";
    finish(0);
  });
}

connect();
