// Connects to a Foxglove WebSocket server with @foxglove/ws-protocol's FoxgloveClient and its
// default subprotocol (foxglove.websocket.v1, what Lichtblick and Studio 1.x use), subscribes
// to the channel named on the command line and counts the messages of SECONDS seconds.
// TOPIC "json": every JSON channel instead, each message validated against its channel's
// schema with ajv (issue 38). Prints one JSON line:
// {"subprotocol", "channels", "messages", "seconds", "json": {topic: count}, "invalid": {topic: error}}.
import wsProtocol from "@foxglove/ws-protocol";
import Ajv2020 from "ajv/dist/2020.js";
import WebSocket from "ws";

const { FoxgloveClient } = wsProtocol;
const [url, topic, seconds] = [process.argv[2], process.argv[3], Number(process.argv[4] || 3)];
const ws = new WebSocket(url, [FoxgloveClient.SUPPORTED_SUBPROTOCOL]);
const client = new FoxgloveClient({ ws });
const ajv = new Ajv2020({ strict: true });
const channels = [];
const bySubscription = new Map(); // subscription id -> {topic, validate}
const json = {};
const invalid = {};
const decoder = new TextDecoder();
let messages = 0;
let started = null;
function finishIn(ms) {
  started = Date.now();
  setTimeout(() => {
    console.log(JSON.stringify({ subprotocol: ws.protocol, channels, messages, seconds, json, invalid }));
    client.close();
    process.exit(0);
  }, ms);
}
client.on("advertise", (advertised) => {
  for (const ch of advertised) {
    channels.push(ch.topic);
    if (topic === "json" && ch.encoding === "json") {
      const id = client.subscribe(ch.id);
      bySubscription.set(id, { topic: ch.topic, validate: ajv.compile(JSON.parse(ch.schema)) });
      if (started === null) finishIn(seconds * 1000);
    } else if (ch.topic === topic && started === null) {
      client.subscribe(ch.id);
      finishIn(seconds * 1000);
    }
  }
});
client.on("message", ({ subscriptionId, data }) => {
  messages += 1;
  const sub = bySubscription.get(subscriptionId);
  if (!sub) return;
  json[sub.topic] = (json[sub.topic] || 0) + 1;
  const value = JSON.parse(decoder.decode(data));
  if (!sub.validate(value) && !(sub.topic in invalid)) {
    const e = sub.validate.errors[0];
    invalid[sub.topic] = `${e.instancePath || "<root>"}: ${e.message}`;
  }
});
client.on("error", (e) => { console.error(String(e)); process.exit(1); });
setTimeout(() => { console.error(`no channel ${topic} in ${channels}`); process.exit(2); }, 20000);
