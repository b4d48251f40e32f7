// Interop check of common/mcap and common/ros2 against the reference npm implementations (@mcap/core with
// @mcap/support's zstd and lz4, @foxglove/rosmsg and @foxglove/rosmsg2-serialization), in both directions:
//
// (a) files our writer makes (mcap_interop_tool write: zstd, lz4 and uncompressed chunks, no chunks, no summary)
//     are read by McapStreamReader and, where indexed, McapIndexedReader, both with CRC validation on; the
//     messages must equal what our reader lists, the data section CRC (which neither npm reader checks) is
//     recomputed here, and every Image and Imu is decoded with the npm CDR reader from the schema text in the file
//     and must equal what our decoder prints;
// (b) files @mcap/core's McapWriter makes (zstd chunks compressed with @foxglove/wasm-zstd, uncompressed chunks, no
//     chunks, no summary or index), holding CDR messages from the npm serializer, are read by our reader and
//     decoded by our decoders, which must give exactly what was written. The npm packages cannot compress LZ4, so
//     LZ4 is checked in (a) only: our compressor, read back by the npm decompressor.
//
//   node interop_test.mjs --tool PATH/mcap_interop_tool [--tools DIR]
//
// DIR holds the npm packages (deploy/install_deploy_tools.sh; default $CVISLAM_DEPLOY_TOOLS, else out/deploy-tools).
// Prints one line per check and exits 1 when any fails.
import { execFileSync } from "node:child_process";
import fs from "node:fs";
import { createRequire } from "node:module";
import os from "node:os";
import path from "node:path";
import { fileURLToPath } from "node:url";
import zlib from "node:zlib";

const args = process.argv.slice(2);
const option = (name) => {
  const i = args.indexOf(name);
  return i >= 0 ? args[i + 1] : undefined;
};
const repo = path.resolve(path.dirname(fileURLToPath(import.meta.url)), "../../..");
const tool = option("--tool");
const toolsDir = option("--tools") ?? process.env.CVISLAM_DEPLOY_TOOLS ?? path.join(repo, "out/deploy-tools");
if (!tool) {
  console.error("usage: node interop_test.mjs --tool PATH/mcap_interop_tool [--tools DIR]");
  process.exit(2);
}
if (!fs.existsSync(path.join(toolsDir, "node_modules/@mcap/core"))) {
  console.error(`interop_test: the npm packages are missing in ${toolsDir}: run deploy/install_deploy_tools.sh`);
  process.exit(1);
}
// The packages live in the tools folder, not beside this script: load them from there.
const require = createRequire(path.join(toolsDir, "package.json"));
const { McapStreamReader, McapIndexedReader, McapWriter } = require("@mcap/core");
const { FileHandleReadable, FileHandleWritable } = require("@mcap/nodejs");
const { loadDecompressHandlers } = require("@mcap/support");
const zstd = require("@foxglove/wasm-zstd");
const { parse: parseMessageDefinition } = require("@foxglove/rosmsg");
const { MessageReader, MessageWriter } = require("@foxglove/rosmsg2-serialization");

let failures = 0;
function check(what, ok, detail = "") {
  console.log(`${ok ? "ok  " : "FAIL"}  ${what}${ok || !detail ? "" : `\n      ${detail}`}`);
  if (!ok) failures++;
}
// Compares two listings line by line and names the first difference.
function sameLines(what, actual, expected) {
  const a = actual.trimEnd().split("\n");
  const e = expected.trimEnd().split("\n");
  const n = Math.max(a.length, e.length);
  for (let i = 0; i < n; i++) {
    if (a[i] !== e[i]) {
      check(what, false, `line ${i + 1}: got '${a[i]}', expected '${e[i]}' (${a.length} vs ${e.length} lines)`);
      return;
    }
  }
  check(`${what} (${a.length} lines)`, true);
}
const runTool = (...toolArgs) =>
  execFileSync(tool, toolArgs, { encoding: "utf8", maxBuffer: 1 << 28, stdio: ["ignore", "pipe", "pipe"] });

// The listing form of sample_bag.hpp: "topic sequence log_time publish_time bytes crc32".
const crcHex = (bytes) => (zlib.crc32(bytes) >>> 0).toString(16).padStart(8, "0");
const messageLine = (topic, m) =>
  `${topic} ${m.sequence} ${m.logTime} ${m.publishTime} ${m.data.byteLength} ${crcHex(m.data)}`;

// The decode form of mcap_interop_tool: doubles as the hex of their IEEE-754 bits, so equal text is equal value.
const bits = (v) => {
  const view = new DataView(new ArrayBuffer(8));
  view.setFloat64(0, v, true);
  return view.getBigUint64(0, true).toString(16).padStart(16, "0");
};
function decodeLine(topic, sequence, schemaName, msg) {
  let line = `${topic} ${sequence} ${msg.header.stamp.sec}.${msg.header.stamp.nanosec} ${msg.header.frame_id}`;
  if (schemaName === "sensor_msgs/msg/Image") {
    line += ` ${msg.width}x${msg.height} ${msg.encoding} ${msg.is_bigendian} ${msg.step} ${msg.data.length}`;
    for (let i = 0; i < msg.data.length; i += 97) line += ` ${msg.data[i]}`;
  } else {
    const { orientation: q, angular_velocity: w, linear_acceleration: a } = msg;
    for (const v of [q.x, q.y, q.z, q.w, w.x, w.y, w.z, a.x, a.y, a.z]) line += ` ${bits(v)}`;
    for (const c of [msg.orientation_covariance, msg.angular_velocity_covariance, msg.linear_acceleration_covariance]) {
      for (const v of c) line += ` ${bits(v)}`;
    }
  }
  return line;
}

// The offset of the first top-level record with opcode `op`, walking from the Header; -1 if there is none.
function findRecord(bytes, op) {
  const view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  for (let at = 8; at + 9 <= bytes.length; at += 9 + Number(view.getBigUint64(at + 1, true))) {
    if (bytes[at] === op) return at;
  }
  return -1;
}

// The data section CRC, which neither npm reader checks.
function checkDataSectionCrc(name, bytes) {
  const at = findRecord(bytes, 0x0f);
  const stored = at < 0 ? 0 : new DataView(bytes.buffer, bytes.byteOffset).getUint32(at + 9, true);
  const computed = zlib.crc32(bytes.subarray(0, Math.max(at, 0))) >>> 0;
  check(`${name}: data_section_crc ${stored.toString(16)} recomputed`, at > 0 && stored !== 0 && stored === computed);
}

// Controls, so that a check that cannot fail does not pass unnoticed: a chunk's stored CRC flipped in our file must
// stop McapStreamReader, and a compressed byte flipped in McapWriter's file must stop our reader.
function controls(oursFile, npmFile) {
  const ours = Buffer.from(fs.readFileSync(oursFile));
  ours[findRecord(ours, 0x06) + 9 + 24] ^= 0x01;  // the first chunk's uncompressed_crc
  const stream = new McapStreamReader({ decompressHandlers, validateCrcs: true });
  stream.append(ours);
  let error = "";
  try {
    while (stream.nextRecord()) {}
  } catch (e) {
    error = String(e.message ?? e);
  }
  check(`control: McapStreamReader refuses our file with a flipped chunk CRC ('${error}')`, /CRC/i.test(error));

  const theirs = Buffer.from(fs.readFileSync(npmFile));
  theirs[findRecord(theirs, 0x06) + 80] ^= 0x01;  // inside the first chunk's compressed records
  const broken = path.join(work, "npm-zstd-broken.mcap");
  fs.writeFileSync(broken, theirs);
  let ourError = "";
  try {
    runTool("list", broken);
  } catch (e) {
    ourError = String(e.stderr ?? e).trim();
  }
  check(`control: our reader refuses McapWriter's file with a flipped chunk byte ('${ourError}')`,
    ourError.includes("Chunk at offset"));
}

const decompressHandlers = await loadDecompressHandlers();
await zstd.isLoaded;
const work = fs.mkdtempSync(path.join(os.tmpdir(), "mcap-interop-"));
try {
  // (a) Our files, read by @mcap/core.
  const ours = runTool("write", work).trim().split("\n");
  let imuDefinition;
  let imageDefinition;
  for (const name of ours) {
    const file = path.join(work, name);
    const bytes = fs.readFileSync(file);
    const oursListing = runTool("list", file);
    const oursDecoded = runTool("decode", file);

    const stream = new McapStreamReader({ decompressHandlers, validateCrcs: true, includeChunks: true });
    stream.append(bytes);
    const topics = new Map();
    const schemas = new Map();
    const readers = new Map();
    let listing = "";
    let decoded = "";
    let chunks = 0;
    let trailing = 0;
    for (let record; (record = stream.nextRecord()); ) {
      if (record.type === "Schema") schemas.set(record.id, record);
      if (record.type === "Channel") topics.set(record.id, record);
      if (record.type === "Chunk") chunks++;
      if (record.type !== "Message") continue;
      const channel = topics.get(record.channelId);
      listing += messageLine(channel.topic, record) + "\n";
      const schema = schemas.get(channel.schemaId);
      if (!schema) continue;
      if (!readers.has(schema.id)) {
        const text = new TextDecoder().decode(schema.data);
        readers.set(schema.id, new MessageReader(parseMessageDefinition(text, { ros2: true })));
        if (schema.name === "sensor_msgs/msg/Imu") imuDefinition = text;
        if (schema.name === "sensor_msgs/msg/Image") imageDefinition = text;
      }
      const reader = readers.get(schema.id);
      decoded += decodeLine(channel.topic, record.sequence, schema.name, reader.readMessage(record.data)) + "\n";
      if (reader.lastReadHadTrailingBytes()) trailing++;
    }
    check(`${name}: the npm CDR reader found no trailing bytes in any message`, trailing === 0);
    check(`${name}: McapStreamReader with CRCs reached the end (${chunks} chunks)`,
      stream.done() && (chunks > 0) === !name.includes("unchunked"));
    sameLines(`${name}: McapStreamReader's messages = our reader's`, listing, oursListing);
    sameLines(`${name}: npm CDR decoding = ours`, decoded, oursDecoded);
    checkDataSectionCrc(name, bytes);

    if (name.includes("no-summary")) continue;
    const handle = await fs.promises.open(file, "r");
    try {
      const indexed = await McapIndexedReader.Initialize({ readable: new FileHandleReadable(handle), decompressHandlers });
      check(`${name}: McapIndexedReader read the summary (its CRC checked)`, indexed.statistics !== undefined);
      check(`${name}: statistics count ${indexed.statistics.messageCount} messages`,
        Number(indexed.statistics.messageCount) === listing.trimEnd().split("\n").length);
      check(`${name}: DataEnd's CRC as the indexed reader saw it`,
        indexed.dataSectionCrc === (zlib.crc32(bytes.subarray(0, Number(indexed.dataEndOffset))) >>> 0));
      if (indexed.chunkIndexes.length > 0) {
        let byTime = [];
        for await (const m of indexed.readMessages({ validateCrcs: true })) {
          byTime.push(messageLine(indexed.channelsById.get(m.channelId).topic, m));
        }
        // The indexed reader goes by log time and breaks ties its own way: compare as sets of lines.
        sameLines(`${name}: McapIndexedReader's messages (by time, CRCs on) = ours`, byTime.sort().join("\n"),
          listing.trimEnd().split("\n").sort().join("\n"));
      }
    } catch (e) {
      check(`${name}: McapIndexedReader`, false, String(e));
    } finally {
      await handle.close();
    }
  }

  // (b) Files @mcap/core writes, read by ours.
  const imuWriter = new MessageWriter(parseMessageDefinition(imuDefinition, { ros2: true }));
  const imageWriter = new MessageWriter(parseMessageDefinition(imageDefinition, { ros2: true }));
  // [file, McapWriter options, chunked, with a summary]
  const layouts = [
    ["npm-zstd.mcap", { chunkSize: 4096, compressChunk: (d) => ({ compression: "zstd", compressedData: zstd.compress(d, 3) }) }, true, true],
    ["npm-uncompressed-chunks.mcap", { chunkSize: 4096 }, true, true],
    ["npm-unchunked.mcap", { useChunks: false }, false, true],
    ["npm-unindexed.mcap", { useChunks: false, useStatistics: false, useSummaryOffsets: false, useAttachmentIndex: false,
      useMetadataIndex: false, repeatSchemas: false, repeatChannels: false }, false, false],
  ];
  for (const [name, options, chunked, withSummary] of layouts) {
    const file = path.join(work, name);
    const handle = await fs.promises.open(file, "w");
    const writer = new McapWriter({ writable: new FileHandleWritable(handle), ...options });
    await writer.start({ profile: "ros2", library: "@mcap/core interop test" });
    const encoder = new TextEncoder();
    const imuSchema = await writer.registerSchema({ name: "sensor_msgs/msg/Imu", encoding: "ros2msg", data: encoder.encode(imuDefinition) });
    const imageSchema = await writer.registerSchema({ name: "sensor_msgs/msg/Image", encoding: "ros2msg", data: encoder.encode(imageDefinition) });
    const imuChannel = await writer.registerChannel({ schemaId: imuSchema, topic: "/imu0", messageEncoding: "cdr", metadata: new Map() });
    const camChannel = await writer.registerChannel({ schemaId: imageSchema, topic: "/cam0/image_raw", messageEncoding: "cdr",
      metadata: new Map([["offered_qos_profiles", ""]]) });
    await writer.addAttachment({ name: "calib.yaml", logTime: 1n, createTime: 2n, mediaType: "application/yaml", data: encoder.encode("fx: 1\n") });
    await writer.addMetadata({ name: "mission", metadata: new Map([["agent", "7"]]) });
    let expectedListing = "";
    let expectedDecoded = "";
    const start = 1700000000n * 1000000000n;
    for (let i = 0; i < 200; i++) {
      const t = start + BigInt(i) * 5000000n;
      const stamp = { sec: Number(t / 1000000000n), nanosec: Number(t % 1000000000n) };
      const imu = {
        header: { stamp, frame_id: "imu_link" },
        orientation: { x: 0.001 * i, y: -0.5, z: 0.25, w: Math.sqrt(1 - 0.3125 - 1e-6 * i * i) },
        orientation_covariance: Array.from({ length: 9 }, (_, k) => k * 1e-3 + i),
        angular_velocity: { x: Math.sin(i), y: Math.cos(i), z: -1 / (i + 1) },
        angular_velocity_covariance: Array.from({ length: 9 }, (_, k) => (k === 4 ? 2e-4 : 0)),
        linear_acceleration: { x: 9.81 + i / 7, y: -0.1, z: 1e-300 * i },
        linear_acceleration_covariance: Array.from({ length: 9 }, (_, k) => -k),
      };
      const imuData = imuWriter.writeMessage(imu);
      const imuMessage = { channelId: imuChannel, sequence: i, logTime: t, publishTime: t + 1n, data: imuData };
      await writer.addMessage(imuMessage);
      expectedListing += messageLine("/imu0", imuMessage) + "\n";
      expectedDecoded += decodeLine("/imu0", i, "sensor_msgs/msg/Imu", imu) + "\n";
      if (i % 10 === 0) {
        const [width, height, encoding, channels] = i % 20 === 0 ? [24, 10, "mono8", 1] : [7, 5, "rgb8", 3];
        const pixels = new Uint8Array(width * height * channels).map((_, k) => (k * 13 + i) & 0xff);
        const image = { header: { stamp, frame_id: "cam0_optical_frame" }, height, width, encoding, is_bigendian: 0,
          step: width * channels, data: pixels };
        const imageMessage = { channelId: camChannel, sequence: i / 10, logTime: t, publishTime: t, data: imageWriter.writeMessage(image) };
        await writer.addMessage(imageMessage);
        expectedListing += messageLine("/cam0/image_raw", imageMessage) + "\n";
        expectedDecoded += decodeLine("/cam0/image_raw", i / 10, "sensor_msgs/msg/Image", image) + "\n";
      }
    }
    await writer.end();
    await handle.close();
    try {
      // Every CRC McapWriter computed was checked: one per chunk, the data section, the attachment, the summary.
      const [messages, chunks, crcs, summary] = runTool("counts", file).trim().split(" ").map(Number);
      check(`${name}: our reader checked ${crcs} CRCs (${chunks} chunks, summary ${summary ? "read" : "absent"})`,
        messages === 220 && crcs === chunks + 2 + summary && (chunks > 0) === chunked && summary === Number(withSummary));
      sameLines(`${name}: our reader's messages = what McapWriter wrote`, runTool("list", file), expectedListing);
      sameLines(`${name}: our CDR decoding = what MessageWriter encoded`, runTool("decode", file), expectedDecoded);
    } catch (e) {
      check(`${name}: our reader`, false, String(e.stderr ?? e));
    }
  }
  controls(path.join(work, "ours-zstd.mcap"), path.join(work, "npm-zstd.mcap"));
} finally {
  fs.rmSync(work, { recursive: true, force: true });
}
console.log(failures === 0 ? "interop: all checks passed" : `interop: ${failures} check(s) failed`);
process.exit(failures === 0 ? 0 : 1);
