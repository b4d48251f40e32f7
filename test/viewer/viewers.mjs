// Load for the viewer endpoint: N Foxglove clients on one mission, each subscribed to every channel; the last
// `--stalled` of them never read their socket after the upgrade (the server must drop their oldest messages, not
// hold anything up or grow without bound). Runs until the server closes the connections or --seconds pass, then
// prints one JSON line: bytes and messages received per reading client, per second of connection.
//
//   node viewers.mjs --port P --mission M --token T --clients 10 --stalled 1 [--seconds S] [--tools DIR]
import { scriptArgs } from "./script_args.mjs";

const { args, require } = scriptArgs();
const { FoxgloveClient } = require("@foxglove/ws-protocol");
const WebSocket = require("ws");

const n = Number(args.clients ?? 1);
const stalled = Number(args.stalled ?? 0);
const seconds = Number(args.seconds ?? 600);
const url = `ws://127.0.0.1:${args.port}/?mission=${encodeURIComponent(args.mission)}&token=${args.token}`;
const clients = [];
for (let i = 0; i < n; i++) {
  const ws = new WebSocket(url, [FoxgloveClient.SUPPORTED_SUBPROTOCOL]);
  const c = { bytes: 0, messages: 0, opened: 0, closed: 0, stalled: i >= n - stalled };
  ws.on("open", () => {
    c.opened = Date.now();
  });
  ws.on("message", (data, binary) => {
    c.bytes += data.length;
    if (binary) c.messages++;
    if (!binary) {
      const op = JSON.parse(String(data));
      if (op.op === "advertise") {
        ws.send(JSON.stringify({ op: "subscribe", subscriptions: op.channels.map((ch) => ({ id: ch.id, channelId: ch.id })) }));
        // A stalled client subscribes, then stops reading: the kernel's buffers fill and the server must cope.
        if (c.stalled) setTimeout(() => ws._socket.pause(), 200);
      }
    }
  });
  ws.on("close", () => {
    c.closed = Date.now();
  });
  ws.on("error", () => {});
  clients.push({ ws, c });
}
const started = Date.now();
// Until the server has closed every reading client (a stalled one never hears of it).
while (Date.now() - started < seconds * 1000 && clients.some(({ c }) => !c.stalled && !c.closed)) {
  await new Promise((r) => setTimeout(r, 500));
}
const reading = clients.filter(({ c }) => !c.stalled).map(({ c }) => {
  const s = ((c.closed || Date.now()) - c.opened) / 1000;
  return { bytes_per_s: Math.round(c.bytes / s), messages_per_s: +(c.messages / s).toFixed(1), seconds: +s.toFixed(1) };
});
console.log(JSON.stringify({ clients: n, stalled, reading }));
for (const { ws } of clients) ws.terminate();
process.exit(0);
