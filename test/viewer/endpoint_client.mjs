// The WebSocket side of endpoint_test.sh, with the reference client libraries: refusals at the upgrade (401 for a
// wrong or missing token, 400 without the Foxglove subprotocol), then a client with the mission's token gets the
// serverInfo; hostile messages (not JSON, unknown operations, subscriptions to channels it was never told of,
// a message over the size limit) get a status back or end only that connection, and a new client still connects.
//
//   node endpoint_client.mjs --url ws(s)://127.0.0.1:P/ --mission M --token T [--tools DIR]
import { scriptArgs } from "./script_args.mjs";

const { args, require } = scriptArgs();
const WebSocket = require("ws");
const PROTOCOL = "foxglove.websocket.v1";
const failures = [];
const check = (ok, what) => { if (!ok) failures.push(what); };

function connect(query, { protocols = [PROTOCOL], headers = {} } = {}) {
  return new Promise((resolve) => {
    const ws = new WebSocket(`${args.url}${query}`, protocols, { headers });
    const texts = [];
    ws.on("unexpected-response", (_req, res) => resolve({ status: res.statusCode, texts }));
    ws.on("message", (data, binary) => { if (!binary) texts.push(JSON.parse(String(data))); });
    ws.on("open", () => resolve({ status: "open", ws, texts }));
    ws.on("error", (e) => resolve({ status: `error ${e.message}`, texts }));
  });
}
const wait = (ms) => new Promise((r) => setTimeout(r, ms));
const token = args.token;
const mission = args.mission;

check((await connect(`?mission=${mission}&token=${"f".repeat(32)}`)).status === 401, "a wrong token is not 401");
check((await connect(`?mission=${mission}`)).status === 401, "a missing token is not 401");
check((await connect(`?mission=other&token=${token}`)).status === 401, "another mission's token is not 401");
check((await connect(`?token=${token}`)).status === 401, "no mission named (tokens on) is not 401");
check((await connect(`?mission=${mission}&token=${token}`, { protocols: ["other"] })).status === 400,
  "an upgrade without the Foxglove subprotocol is not 400");

const c = await connect(`?mission=${mission}`, { headers: { Authorization: `Bearer ${token}` } });
check(c.status === "open", `the mission's bearer token did not open it (${c.status})`);
if (c.ws) {
  check(c.ws.protocol === PROTOCOL, "the subprotocol was not selected");
  await wait(300);
  check(c.texts[0]?.op === "serverInfo", "no serverInfo first");
  for (const hostile of ["not json", "[]", '{"op":"subscribe","subscriptions":[{"id":1,"channelId":99}]}',
    '{"op":"clientAdvertise","channels":[]}', '{"op":"subscribe","subscriptions":"x"}']) {
    const before = c.texts.length;
    c.ws.send(hostile);
    await wait(150);
    check(c.texts.slice(before).some((m) => m.op === "status"), `no status for ${hostile}`);
  }
  check(c.ws.readyState === WebSocket.OPEN, "a hostile message closed the connection");
  // Over the size limit (64 KiB): the server may close this connection, and nothing else.
  c.ws.send("x".repeat(200000));
  await wait(300);
  c.ws.terminate();
}
const again = await connect(`?mission=${mission}&token=${token}`);
check(again.status === "open", `a new client could not connect after the hostile one (${again.status})`);
again.ws?.close();
console.log(JSON.stringify({ url: args.url, ok: failures.length === 0, failures }));
process.exit(failures.length === 0 ? 0 : 1);
