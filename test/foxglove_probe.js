// A Foxglove WebSocket client for the tests, on the protocol's reference implementation (@foxglove/ws-protocol).
// Usage: node --experimental-websocket foxglove_probe.js '<json request>'   (NODE_PATH: where ws-protocol is)
// Request: {url, topics: [...], count, publish: {topic, schemaName, data: base64, period_ms, repeat} | null,
// timeout_ms}
// It subscribes to `topics` once advertised, keeps the first `count` messages of each, sends `publish` every
// period_ms (at least `repeat` times), and prints one JSON object when each topic has its messages or the time is up:
// {impl, server, channels, messages: {topic: [{log_time, data: base64}]}, times: [ns], errors}.
"use strict";
const { FoxgloveClient } = require("@foxglove/ws-protocol");

const request = JSON.parse(process.argv[2]);
const result = { impl: "node", server: null, channels: [], messages: {}, times: [], errors: [] };
const WS = typeof WebSocket !== "undefined" ? WebSocket : require("ws");
// foxglove-sdk servers name the same v1 protocol foxglove.sdk.v1; ws-protocol's own name is offered too.
const subprotocols = [FoxgloveClient.SUPPORTED_SUBPROTOCOL, "foxglove.sdk.v1"];
const client = new FoxgloveClient({ ws: new WS(request.url, subprotocols) });
const topicOf = new Map(); // subscription id -> topic
let publishTimer = null;
let sent = 0;
let finished = false;

function finish() {
  if (finished) return;
  finished = true;
  if (publishTimer) clearInterval(publishTimer);
  process.stdout.write(JSON.stringify(result) + "\n");
  try { client.close(); } catch (e) { /* closing anyway */ }
  setTimeout(() => process.exit(0), 100);
}

function done() {
  const heard = request.topics.every((t) => (result.messages[t] || []).length >= request.count);
  return heard && (!request.publish || sent >= request.publish.repeat);
}

client.on("error", (err) => result.errors.push(String(err && err.message ? err.message : err)));
client.on("close", () => finish());
client.on("serverInfo", (info) => {
  result.server = info;
  const pub = request.publish;
  if (pub) {
    const channelId = client.advertise({ topic: pub.topic, encoding: "cdr", schemaName: pub.schemaName });
    const data = Uint8Array.from(Buffer.from(pub.data, "base64"));
    publishTimer = setInterval(() => {
      client.sendMessage(channelId, data);
      sent += 1;
      if (done()) finish();
    }, pub.period_ms);
  }
});
client.on("advertise", (channels) => {
  for (const ch of channels) {
    result.channels.push(ch);
    if (request.topics.includes(ch.topic)) topicOf.set(client.subscribe(ch.id), ch.topic);
  }
});
client.on("message", ({ subscriptionId, timestamp, data }) => {
  const topic = topicOf.get(subscriptionId);
  if (topic === undefined) return;
  const kept = (result.messages[topic] = result.messages[topic] || []);
  if (kept.length < request.count) {
    const bytes = Buffer.from(data.buffer, data.byteOffset, data.byteLength);
    kept.push({ log_time: timestamp.toString(), data: bytes.toString("base64") });
  }
  if (done()) finish();
});
client.on("time", ({ timestamp }) => result.times.push(timestamp.toString()));
setTimeout(finish, request.timeout_ms);
