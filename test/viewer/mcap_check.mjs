// A recording of the viewer's channels (cvislam_server --record, cvislam_mapctl export --mcap) read back by the
// reference MCAP reader (@mcap/core, CRCs checked) and by the project's own (mcap_interop_tool list): both must see
// the same messages, every channel must be JSON with a schema, every message must be valid against its schema
// (foxglove.* against @foxglove/schemas), and each expected topic suffix must have messages.
//
//   node mcap_check.mjs --file F --tool mcap_interop_tool --expect events,keyframes,points,pose [--tools DIR]
//
// Prints one JSON line (messages per topic, bytes); exits 1 saying what differs or is missing.
import { execFileSync } from "node:child_process";
import fs from "node:fs";
import zlib from "node:zlib";
import { scriptArgs } from "./script_args.mjs";

const { args, require } = scriptArgs();
const { McapStreamReader } = require("@mcap/core");
const { loadDecompressHandlers } = require("@mcap/support");
const Ajv = require("ajv/dist/2020");
const foxgloveSchemas = require("@foxglove/schemas/jsonschema");

const crcHex = (data) => (zlib.crc32(data) >>> 0).toString(16).padStart(8, "0");
const failures = [];
const bytes = fs.readFileSync(args.file);
const stream = new McapStreamReader({ decompressHandlers: await loadDecompressHandlers(), validateCrcs: true });
stream.append(bytes);
const schemas = new Map();
const channels = new Map();
const validators = new Map();
const counts = {};
const ajv = new Ajv({ strict: false });
let listing = "";
let footer = false;
for (let record; (record = stream.nextRecord()); ) {
  if (record.type === "Schema") schemas.set(record.id, record);
  if (record.type === "Channel") {
    channels.set(record.id, record);
    const schema = schemas.get(record.schemaId);
    if (!schema || schema.encoding !== "jsonschema" || record.messageEncoding !== "json") {
      failures.push(`${record.topic}: not a JSON channel with a JSON Schema`);
      continue;
    }
    const short = schema.name.startsWith("foxglove.") ? schema.name.slice("foxglove.".length) : null;
    validators.set(record.id, ajv.compile(short && foxgloveSchemas[short] ? foxgloveSchemas[short] :
      JSON.parse(new TextDecoder().decode(schema.data))));
  }
  if (record.type === "Footer") footer = true;
  if (record.type !== "Message") continue;
  const channel = channels.get(record.channelId);
  counts[channel.topic] = (counts[channel.topic] ?? 0) + 1;
  listing += `${channel.topic} ${record.sequence} ${record.logTime} ${record.publishTime} ${record.data.byteLength} ${crcHex(record.data)}\n`;
  const validate = validators.get(record.channelId);
  if (validate && !validate(JSON.parse(new TextDecoder().decode(record.data)))) {
    failures.push(`${channel.topic} #${record.sequence}: ${ajv.errorsText(validate.errors)}`);
  }
}
if (!footer) failures.push("no footer: the file was not closed");
const ours = execFileSync(args.tool, ["list", args.file], { encoding: "utf8", maxBuffer: 1 << 30 });
if (ours !== listing) {
  const a = ours.split("\n");
  const b = listing.split("\n");
  const i = a.findIndex((line, k) => line !== b[k]);
  failures.push(`our reader and @mcap/core differ at message ${i}: '${a[i]}' vs '${b[i]}'`);
}
for (const suffix of (args.expect ?? "").split(",").filter(Boolean)) {
  if (!Object.keys(counts).some((t) => t.endsWith(`/${suffix}`))) failures.push(`no message on a */${suffix} topic`);
}
console.log(JSON.stringify({ file: args.file, ok: failures.length === 0, bytes: bytes.length, messages: counts,
  failures: failures.slice(0, 10) }));
process.exit(failures.length === 0 ? 0 : 1);
