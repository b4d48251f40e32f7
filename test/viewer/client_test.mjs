// A Foxglove WebSocket client (the reference @foxglove/ws-protocol) against a running cvislam_server's viewer
// endpoint, during a real mission:
//  - a wrong token and a missing token are refused at the upgrade (HTTP 401), so no channel is ever advertised;
//  - with the mission's token, every channel is advertised with its schema, every message of every channel is
//    valid against the schema it names (foxglove.* against @foxglove/schemas' JSON Schemas, ours against the schema
//    the server advertised), each agent's live pose moves, and a merge of two maps is announced on the events channel.
//
//   node client_test.mjs --port P --mission M --token T --agents N [--tools DIR] [--timeout S] [--json OUT]
//
// Prints one JSON line of what it saw; exits 0 when everything above held, 1 (saying what was missing) otherwise.
import { writeFileSync } from "node:fs";
import { scriptArgs } from "./script_args.mjs";

const { args, require } = scriptArgs();
const { FoxgloveClient } = require("@foxglove/ws-protocol");
const WebSocket = require("ws");
const Ajv = require("ajv/dist/2020");
const foxgloveSchemas = require("@foxglove/schemas/jsonschema");

const port = Number(args.port);
const mission = args.mission;
const token = args.token;
const agents = Number(args.agents ?? 1);
const timeoutS = Number(args.timeout ?? 240);
const base = `ws://127.0.0.1:${port}/`;

// Resolves with the HTTP status of a refused upgrade, or "open" (and whether anything was advertised) if it was not.
function tryUpgrade(url, headers) {
  return new Promise((resolve) => {
    const ws = new WebSocket(url, [FoxgloveClient.SUPPORTED_SUBPROTOCOL], { headers });
    let advertised = false;
    ws.on("unexpected-response", (_req, res) => resolve({ status: res.statusCode, advertised }));
    ws.on("message", (data) => {
      if (String(data).includes('"advertise"')) advertised = true;
    });
    ws.on("open", () => setTimeout(() => { ws.close(); resolve({ status: "open", advertised }); }, 1000));
    ws.on("error", () => {});
  });
}

const failures = [];
const wrong = await tryUpgrade(`${base}?mission=${mission}&token=${"0".repeat(32)}`, {});
if (wrong.status !== 401 || wrong.advertised) failures.push(`a wrong token got ${JSON.stringify(wrong)}, not 401`);
const missing = await tryUpgrade(`${base}?mission=${mission}`, {});
if (missing.status !== 401 || missing.advertised) failures.push(`no token got ${JSON.stringify(missing)}, not 401`);
const wrongHeader = await tryUpgrade(`${base}?mission=${mission}`, { Authorization: `Bearer ${"f".repeat(32)}` });
if (wrongHeader.status !== 401) failures.push(`a wrong bearer token got ${JSON.stringify(wrongHeader)}, not 401`);

const ajv = new Ajv({ strict: false, allErrors: false });
const validators = new Map(); // channel id -> validate function
const channels = new Map(); // channel id -> channel
const bySubscription = new Map();
const counts = {}; // topic -> messages
const invalid = {}; // topic -> first error
const poses = new Map(); // agent -> set of rounded positions
const events = [];

const client = new FoxgloveClient({
  ws: new WebSocket(`${base}?mission=${encodeURIComponent(mission)}`, [FoxgloveClient.SUPPORTED_SUBPROTOCOL], {
    headers: { Authorization: `Bearer ${token}` },
  }),
});
client.on("error", (e) => failures.push(`client error: ${e?.message ?? e}`));
client.on("advertise", (list) => {
  for (const ch of list) {
    channels.set(ch.id, ch);
    const short = ch.schemaName.startsWith("foxglove.") ? ch.schemaName.slice("foxglove.".length) : null;
    const schema = short && foxgloveSchemas[short] ? foxgloveSchemas[short] : JSON.parse(ch.schema);
    validators.set(ch.id, ajv.compile(schema));
    if (ch.encoding !== "json") failures.push(`${ch.topic}: encoding ${ch.encoding}`);
    bySubscription.set(client.subscribe(ch.id), ch);
  }
});
const decoder = new TextDecoder();
client.on("message", ({ subscriptionId, data }) => {
  const ch = bySubscription.get(subscriptionId);
  if (!ch) return;
  counts[ch.topic] = (counts[ch.topic] ?? 0) + 1;
  const message = JSON.parse(decoder.decode(data));
  const validate = validators.get(ch.id);
  if (!validate(message) && !invalid[ch.topic]) invalid[ch.topic] = ajv.errorsText(validate.errors);
  const pose = ch.topic.match(/\/agent(\d+)\/pose$/);
  if (pose) {
    const p = message.pose.position;
    if (!poses.has(pose[1])) poses.set(pose[1], new Set());
    poses.get(pose[1]).add(`${p.x.toFixed(3)},${p.y.toFixed(3)},${p.z.toFixed(3)}`);
  }
  if (ch.topic.endsWith("/events")) events.push(message.message);
});

const expectedKinds = ["events", "stats", "keyframes", "tf", "points", "pose", "trajectory"];
function missingParts() {
  const out = [];
  const topics = [...channels.values()].map((c) => c.topic);
  for (const kind of expectedKinds) {
    if (!topics.some((t) => t.endsWith(`/${kind}`))) out.push(`no ${kind} channel`);
    else if (!Object.keys(counts).some((t) => t.endsWith(`/${kind}`))) out.push(`no ${kind} message`);
  }
  const moving = [...poses.values()].filter((s) => s.size >= 3).length;
  if (moving < agents) out.push(`${moving} of ${agents} agents' poses moved`);
  if (!events.some((e) => e.includes("merged into"))) out.push("no merge event");
  if (Object.keys(invalid).length > 0) out.push(`invalid messages: ${JSON.stringify(invalid)}`);
  return out;
}

const started = Date.now();
let still = missingParts();
while (still.length > 0 && Date.now() - started < timeoutS * 1000) {
  await new Promise((r) => setTimeout(r, 250));
  still = missingParts();
}
client.close();
failures.push(...still);
const report = {
  ok: failures.length === 0,
  failures,
  seconds: (Date.now() - started) / 1000,
  channels: [...channels.values()].map((c) => `${c.topic} ${c.schemaName}`),
  messages: counts,
  distinct_poses: Object.fromEntries([...poses].map(([a, s]) => [a, s.size])),
  events: events.slice(0, 20),
};
if (args.json) writeFileSync(args.json, JSON.stringify(report, null, 1));
console.log(JSON.stringify({ ok: report.ok, failures, seconds: report.seconds, messages: counts, distinct_poses: report.distinct_poses }));
process.exit(report.ok ? 0 : 1);
