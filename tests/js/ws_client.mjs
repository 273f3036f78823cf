// Connects to a Foxglove WebSocket server with @foxglove/ws-protocol's FoxgloveClient and its
// default subprotocol (foxglove.websocket.v1, what Lichtblick and Studio 1.x use), subscribes
// to the channel named on the command line and counts the messages of SECONDS seconds.
// Prints one JSON line: {"subprotocol", "channels", "messages", "seconds"}.
import wsProtocol from "@foxglove/ws-protocol";
import WebSocket from "ws";

const { FoxgloveClient } = wsProtocol;
const [url, topic, seconds] = [process.argv[2], process.argv[3], Number(process.argv[4] || 3)];
const ws = new WebSocket(url, [FoxgloveClient.SUPPORTED_SUBPROTOCOL]);
const client = new FoxgloveClient({ ws });
const channels = [];
let messages = 0;
let started = null;
client.on("advertise", (advertised) => {
  for (const ch of advertised) {
    channels.push(ch.topic);
    if (ch.topic === topic && started === null) {
      client.subscribe(ch.id);
      started = Date.now();
      setTimeout(() => {
        console.log(JSON.stringify({ subprotocol: ws.protocol, channels, messages, seconds }));
        client.close();
        process.exit(0);
      }, seconds * 1000);
    }
  }
});
client.on("message", () => { messages += 1; });
client.on("error", (e) => { console.error(String(e)); process.exit(1); });
setTimeout(() => { console.error(`no channel ${topic} in ${channels}`); process.exit(2); }, 20000);
