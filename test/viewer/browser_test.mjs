// The browser viewer (deploy/viewer) in headless Chromium against a running viewer endpoint: the page connects,
// receives every agent's pose, keyframes and a point cloud, and draws them: each agent shown on the displayed map
// has pixels of its palette colour in the WebGL canvas, and the canvas is not one flat colour.
//
//   node browser_test.mjs --url http://127.0.0.1:PORT/?mission=M[&token=T] --agents N --screenshot OUT.png
//                         [--timeout S] [--tools DIR] [--chromium PATH]
//
// Prints one JSON line of what it found; exits 0 when everything above held, 1 (saying what was missing) otherwise.
// A page error (an uncaught exception in the page) is a failure; console errors are printed.
import { scriptArgs } from "./script_args.mjs";

const { args, tools, require } = scriptArgs();
const puppeteer = require("puppeteer-core");
const { PNG } = require("pngjs");

const url = args.url;
const wantAgents = Number(args.agents ?? 1);
const timeoutS = Number(args.timeout ?? 60);
const screenshot = args.screenshot;
const MIN_PIXELS = 20;
const COLOUR_TOLERANCE = 40; // Euclidean distance in RGB: antialiased edges blend, the insides are exact
if (!url) {
  console.error("usage: node browser_test.mjs --url URL --agents N --screenshot OUT.png [--timeout S] [--tools DIR]");
  process.exit(2);
}

const failures = [];
const pageErrors = [];
const browser = await puppeteer.launch({
  executablePath: args.chromium ?? process.env.CHROMIUM ?? "/usr/bin/chromium",
  headless: true,
  defaultViewport: { width: 1280, height: 800 },
  args: ["--no-sandbox", "--enable-unsafe-swiftshader", "--hide-scrollbars", "--window-size=1280,800"],
});
let state = null;
let pixels = {};
let title = null;
try {
  const page = await browser.newPage();
  page.on("console", (m) => {
    if (m.type() === "error") console.error(`[page console.error] ${m.text()}`);
  });
  page.on("response", (r) => {
    if (r.status() >= 400) console.error(`[page request] ${r.url()}: HTTP ${r.status()}`);
  });
  page.on("pageerror", (e) => {
    console.error(`[page error] ${e.message}`);
    pageErrors.push(e.message);
  });
  page.on("requestfailed", (r) => console.error(`[page request failed] ${r.url()}: ${r.failure()?.errorText}`));
  await page.goto(url, { waitUntil: "load", timeout: timeoutS * 1000 });

  // What the page has so far, and what is still missing from it.
  const readState = () => page.evaluate(() => JSON.parse(JSON.stringify(window.cvislamViewer ?? null)));
  const missing = (s) => {
    if (!s) return ["window.cvislamViewer is not set (did viewer.js load?)"];
    const out = [];
    const known = Object.keys(s.agents ?? {});
    const posed = known.filter((id) => s.agents[id].pose);
    if (!s.connected) out.push(`not connected (status: ${s.status})`);
    if (posed.length < wantAgents) {
      out.push(`${posed.length} of ${wantAgents} agents with a pose (with a pose: [${posed}], known: [${known}])`);
    }
    if (!(s.keyframes > 0)) out.push("no keyframe entity");
    if (!Object.keys(s.pointClouds ?? {}).length) out.push("no point cloud");
    return out;
  };
  const deadline = Date.now() + timeoutS * 1000;
  while (true) {
    state = await readState();
    if (missing(state).length === 0 || pageErrors.length || Date.now() > deadline) break;
    await new Promise((r) => setTimeout(r, 250));
  }
  if (missing(state).length) {
    failures.push(`after ${timeoutS} s: ${missing(state).join("; ")}`);
  } else {
    await new Promise((r) => setTimeout(r, 1000)); // a few more frames
    state = await readState();
  }
  title = await page.title();
  if (screenshot) await page.screenshot({ path: screenshot });

  // The WebGL canvas as the page drew it (preserveDrawingBuffer keeps the last frame readable).
  const dataUrl = await page.evaluate(() => document.querySelector("#view canvas")?.toDataURL("image/png") ?? null);
  if (!dataUrl) {
    failures.push("no canvas in #view");
  } else {
    const png = PNG.sync.read(Buffer.from(dataUrl.split(",")[1], "base64"));
    const rgb = (hex) => [1, 3, 5].map((i) => parseInt(hex.slice(i, i + 2), 16));
    const shown = Object.entries(state?.agents ?? {}).filter(([, a]) => a.pose && a.map === state.shownMap);
    const targets = shown.map(([id]) => [id, rgb(state.palette[Number(id) % state.palette.length])]);
    pixels = Object.fromEntries(targets.map(([id]) => [id, 0]));
    const colours = new Map();
    for (let i = 0; i < png.data.length; i += 4) {
      const [r, g, b] = [png.data[i], png.data[i + 1], png.data[i + 2]];
      const key = (r << 16) | (g << 8) | b;
      colours.set(key, (colours.get(key) ?? 0) + 1);
    }
    // Count per distinct colour (far fewer than pixels).
    for (const [key, n] of colours) {
      const c = [key >> 16, (key >> 8) & 255, key & 255];
      for (const [id, t] of targets) {
        if (Math.hypot(c[0] - t[0], c[1] - t[1], c[2] - t[2]) <= COLOUR_TOLERANCE) pixels[id] += n;
      }
    }
    if (colours.size <= 1) failures.push("the canvas is one flat colour: nothing was drawn");
    if (state && state.shownMap === null) failures.push("no map shown");
    for (const [id, n] of Object.entries(pixels)) {
      if (n < MIN_PIXELS) failures.push(`agent ${id} (shown on map ${state.shownMap}) has ${n} pixels of its colour, < ${MIN_PIXELS}`);
    }
    if (!failures.length && shown.length === 0) failures.push(`no agent is on the shown map ${state?.shownMap}`);
  }
} catch (e) {
  failures.push(`browser: ${e.message}`);
} finally {
  await browser.close();
}
for (const e of pageErrors) failures.push(`page error: ${e}`);

const agents = Object.fromEntries(Object.entries(state?.agents ?? {}).map(([id, a]) => [id, { map: a.map, pose: a.pose,
  trajectory: a.trajectoryLength, pixels: pixels[id] ?? null }]));
console.log(JSON.stringify({ ok: failures.length === 0, url, mission: state?.mission, title,
  shownMap: state?.shownMap, agents, keyframes: state?.keyframes, pointClouds: state?.pointClouds,
  events: state?.events?.length, messages: state?.messages, screenshot, failures }));
process.exit(failures.length ? 1 : 0);
