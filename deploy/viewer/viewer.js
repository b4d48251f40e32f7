// cvislam's live viewer: a small Foxglove WebSocket (v1, JSON) client and a three.js view of one map of a mission.
// The channels and their messages are described in docs/viewer.md. Maps that are not merged have no known relation
// to each other, so one map is drawn at a time (the largest by default); agents on other maps are only listed.
// State for tests is kept in window.cvislamViewer (see expose()).
import * as THREE from "three";

// One colour per agent id (id modulo 10): the same values as agentColour() in server_cloud/viewer, so that the
// keyframe cubes the server colours and the viewer's own drawings agree.
const PALETTE = ["#f2544f", "#459ef5", "#66d15c", "#fac233", "#bd73f2",
                 "#33d9cc", "#fa8c2e", "#f273bf", "#a6cc40", "#8c99ff"];
const colourOf = (agent) => PALETTE[((agent % PALETTE.length) + PALETTE.length) % PALETTE.length];
const BACKGROUND = "#0f1217", POINTS = "#aab3bf", EDGES = "#555d68", GRID = "#232a33";
const MAX_LOG = 200, RETRY_MS = 2000, REBUILD_MS = 200, FOV = 50;
const SUBPROTOCOL = "foxglove.websocket.v1";

const query = new URLSearchParams(location.search);
const token = query.get("token") || "";

const state = {
  mission: query.get("mission") || "", // learnt from the channels when the URL names none
  missions: new Set(),                 // every mission advertised (a server without tokens shows them all)
  connected: false,
  status: "connecting",
  channels: new Map(),      // channel id -> channel as advertised
  subscriptions: new Map(), // subscription id -> channel id
  nextSubscription: 0,
  messages: {},             // topic -> messages received
  agents: new Map(),        // agent id -> {id, pose, poseMap, trajectory, trajMap, stats}
  clouds: new Map(),        // map id -> {positions, count, pose, bounds}
  keyframes: new Map(),     // entity id -> {agent, map, p, q, size, lines}
  stats: null,              // the newest cvislam.MissionStats
  events: [],               // the /M/events messages, oldest first (at most MAX_LOG)
  log: [],                  // what the panel lists: events, server status messages, connection changes
  chosenMap: null,          // null: follow the map with the most keyframes
};

const api = (window.cvislamViewer = { palette: PALETTE });

// ---------------------------------------------------------------------------------------------------------------
// Foxglove WebSocket protocol v1, client side: serverInfo, advertise, unadvertise, status; MessageData frames.

function connect() {
  const params = new URLSearchParams();
  if (query.get("mission")) params.set("mission", query.get("mission"));
  if (token) params.set("token", token);
  const scheme = location.protocol === "https:" ? "wss:" : "ws:";
  const search = params.toString();
  const ws = new WebSocket(`${scheme}//${location.host}/${search ? "?" + search : ""}`, [SUBPROTOCOL]);
  ws.binaryType = "arraybuffer";
  let opened = false;
  ws.onopen = () => {
    opened = true;
    resetScene(); // the server sends the whole scene again to a new connection
    setStatus("connected");
  };
  ws.onmessage = (e) => {
    try {
      typeof e.data === "string" ? onText(ws, JSON.parse(e.data)) : onBinary(e.data);
    } catch (err) {
      console.error("cvislam viewer: bad message:", err);
    }
  };
  ws.onclose = async () => {
    // A browser is not told why an upgrade failed. If the page's own server answers plain HTTP, the upgrade was
    // refused (401: mission or token; the only refusal this client can meet); if not, the server is gone.
    setStatus(opened || !(await serverAnswers()) ? "disconnected" : "refused");
    setTimeout(connect, RETRY_MS);
  };
}

const serverAnswers = () => fetch(location.pathname, { cache: "no-store" }).then((r) => r.ok, () => false);

function onText(ws, msg) {
  if (msg.op === "serverInfo") {
    const m = msg.metadata?.mission;
    if (!state.mission && m && m !== "*") state.mission = m;
  } else if (msg.op === "advertise") {
    for (const ch of msg.channels ?? []) {
      state.channels.set(ch.id, ch);
      const mission = missionOf(ch.topic);
      if (mission !== null) state.missions.add(mission);
    }
    // One mission at a time: the server catches a late subscriber up on one mission only. Without a mission in
    // the URL, take the one with the most channels.
    if (!state.mission) {
      const count = {};
      for (const ch of state.channels.values()) count[missionOf(ch.topic)] = (count[missionOf(ch.topic)] ?? 0) + 1;
      state.mission = Object.keys(count).filter((m) => m !== "null").sort((a, b) => count[b] - count[a])[0] ?? "";
    }
    const subscribed = new Set(state.subscriptions.values());
    const subscriptions = [];
    for (const ch of state.channels.values()) {
      if (subscribed.has(ch.id) || missionOf(ch.topic) !== state.mission || ch.encoding !== "json") continue;
      const id = state.nextSubscription++;
      state.subscriptions.set(id, ch.id);
      subscriptions.push({ id, channelId: ch.id });
    }
    if (subscriptions.length) ws.send(JSON.stringify({ op: "subscribe", subscriptions }));
  } else if (msg.op === "unadvertise") {
    for (const id of msg.channelIds ?? []) {
      const ch = state.channels.get(id);
      state.channels.delete(id);
      for (const [sub, c] of state.subscriptions) if (c === id) state.subscriptions.delete(sub);
      if (ch) forgetTopic(ch.topic);
    }
  } else if (msg.op === "status") {
    addLog(Date.now() / 1000, msg.level === 2 ? 4 : msg.level === 1 ? 3 : 2, `server: ${msg.message}`);
  }
  expose();
}

function onBinary(buffer) {
  const view = new DataView(buffer);
  if (view.getUint8(0) !== 0x01) return; // only MessageData; Time (0x02) and others are not used here
  const ch = state.channels.get(state.subscriptions.get(view.getUint32(1, true)));
  if (!ch) return; // a subscription to a channel that has since gone
  state.messages[ch.topic] = (state.messages[ch.topic] ?? 0) + 1;
  const msg = JSON.parse(new TextDecoder().decode(new Uint8Array(buffer, 13)));
  const handler = HANDLERS[ch.schemaName];
  if (handler) handler(msg, ch.topic);
  expose();
}

// "/M/events" -> "M", "/M/map3/points" -> "M", "/M/agent1/pose" -> "M"; null for a topic of no mission.
function missionOf(topic) {
  const m = /^\/(.+?)\/(?:events|stats|keyframes|tf|map\d+\/points|agent\d+\/(?:pose|trajectory))$/.exec(topic);
  return m ? m[1] : null;
}
const mapOfFrame = (frame) => { const m = /\/map(\d+)$/.exec(frame ?? ""); return m ? Number(m[1]) : null; };
const agentOfTopic = (topic) => Number(/\/agent(\d+)\/[a-z]+$/.exec(topic)[1]); // pose and trajectory topics

function forgetTopic(topic) {
  const map = /\/map(\d+)\/points$/.exec(topic), agent = /\/agent(\d+)\/(pose|trajectory)$/.exec(topic);
  if (map) state.clouds.delete(Number(map[1]));
  const a = agent && state.agents.get(Number(agent[1]));
  if (a && agent[2] === "pose") a.pose = a.poseMap = null;
  if (a && agent[2] === "trajectory") a.trajectory = a.trajMap = null;
  changed("all");
}

// ---------------------------------------------------------------------------------------------------------------
// Messages -> state.

function agentState(id) {
  if (!state.agents.has(id)) state.agents.set(id, { id, pose: null, poseMap: null, trajectory: null, trajMap: null });
  return state.agents.get(id);
}

const vec = (v) => [v?.x ?? 0, v?.y ?? 0, v?.z ?? 0];
const quat = (q) => [q?.x ?? 0, q?.y ?? 0, q?.z ?? 0, q?.w ?? 1];

const HANDLERS = {
  "foxglove.Log"(msg) {
    state.events.push(msg.message);
    if (state.events.length > MAX_LOG) state.events.shift();
    addLog((msg.timestamp?.sec ?? 0) + (msg.timestamp?.nsec ?? 0) * 1e-9, msg.level ?? 2, msg.message ?? "");
  },
  "cvislam.MissionStats"(msg) {
    state.stats = msg;
    for (const a of msg.agents ?? []) agentState(a.agent).stats = a;
    changed("stats"); // the figures only; rebuild() notices when the largest map changed
  },
  "foxglove.SceneUpdate"(msg) {
    for (const d of msg.deletions ?? []) {
      if (d.type === 1) state.keyframes.clear(); // ALL
      else state.keyframes.delete(d.id);
    }
    for (const e of msg.entities ?? []) {
      const meta = Object.fromEntries((e.metadata ?? []).map((kv) => [kv.key, kv.value]));
      const cube = e.cubes?.[0];
      const lines = (e.lines ?? []).flatMap((l) => (l.points ?? []).flatMap(vec)); // LINE_LIST, identity pose
      state.keyframes.set(e.id, {
        agent: Number(meta.agent ?? e.id.split("/")[1]),
        map: mapOfFrame(e.frame_id) ?? Number(meta.map),
        p: vec(cube?.pose?.position), q: quat(cube?.pose?.orientation),
        size: cube?.size?.x ?? 0.05,
        lines: lines.length ? new Float32Array(lines) : null,
      });
    }
    changed("keyframes");
  },
  "foxglove.PointCloud"(msg, topic) {
    const map = mapOfFrame(msg.frame_id) ?? Number(/\/map(\d+)\/points$/.exec(topic)?.[1]);
    const text = atob(msg.data ?? ""), bytes = new Uint8Array(text.length);
    for (let i = 0; i < text.length; ++i) bytes[i] = text.charCodeAt(i);
    const data = new DataView(bytes.buffer);
    const offset = {};
    for (const f of msg.fields ?? []) if (f.type === 7) offset[f.name] = f.offset; // FLOAT32 only
    const stride = msg.point_stride || 12;
    const count = offset.x === undefined ? 0 : Math.floor(bytes.length / stride);
    const positions = new Float32Array(count * 3);
    ["x", "y", "z"].forEach((name, k) => {
      for (let i = 0; offset[name] !== undefined && i < count; ++i) {
        positions[3 * i + k] = data.getFloat32(i * stride + offset[name], true);
      }
    });
    state.clouds.set(map, { positions, count, pose: msg.pose, bounds: robustBounds(positions) });
    changed("cloud");
  },
  "foxglove.PoseInFrame"(msg, topic) {
    const agent = agentState(agentOfTopic(topic));
    agent.pose = { p: vec(msg.pose?.position), q: quat(msg.pose?.orientation) };
    agent.poseMap = mapOfFrame(msg.frame_id);
    changed("agents");
  },
  "foxglove.PosesInFrame"(msg, topic) {
    const agent = agentState(agentOfTopic(topic));
    agent.trajectory = new Float32Array((msg.poses ?? []).flatMap((p) => vec(p.position)));
    agent.trajMap = mapOfFrame(msg.frame_id);
    changed("agents");
  },
  // foxglove.FrameTransform (/M/tf): the agents' own world frames, not needed to draw the server maps.
};

// A map's bounds without its farthest few points (a single stray point would otherwise fill the view).
function robustBounds(positions) {
  const n = positions.length / 3;
  const box = new THREE.Box3();
  if (n === 0) return box;
  const axis = new Float32Array(n);
  for (let k = 0; k < 3; ++k) {
    for (let i = 0; i < n; ++i) axis[i] = positions[3 * i + k];
    axis.sort();
    box.min.setComponent(k, axis[Math.floor(0.02 * (n - 1))]);
    box.max.setComponent(k, axis[Math.ceil(0.98 * (n - 1))]);
  }
  return box;
}

const agentMap = (a) => a.poseMap ?? a.trajMap ?? a.stats?.map ?? null;

// The maps to choose from: the server's figures when it sent some, else what has been drawn so far.
function mapList() {
  if (state.stats) return [...(state.stats.maps ?? [])].sort((a, b) => a.map - b.map);
  const maps = new Map();
  const get = (id) => maps.get(id) ?? maps.set(id, { map: id, keyframes: 0, points: 0, agents: [] }).get(id);
  for (const kf of state.keyframes.values()) get(kf.map).keyframes++;
  for (const [id, c] of state.clouds) get(id).points = c.count;
  for (const a of state.agents.values()) if (agentMap(a) !== null) get(agentMap(a)).agents.push(a.id);
  return [...maps.values()].sort((a, b) => a.map - b.map);
}

function shownMap() {
  const maps = mapList();
  if (maps.some((m) => m.map === state.chosenMap)) return state.chosenMap;
  let best = null;
  for (const m of maps) {
    if (!best || m.keyframes > best.keyframes || (m.keyframes === best.keyframes && m.points > best.points)) best = m;
  }
  return best ? best.map : null;
}

function addLog(t, level, text) {
  state.log.push({ t, level, text });
  // In time order: a new connection's catch-up brings events older than the "connected" line.
  if (state.log.length > 1 && t < state.log.at(-2).t) state.log.sort((a, b) => a.t - b.t);
  if (state.log.length > MAX_LOG) state.log.shift();
  ui.logDirty = true;
}

const statusText = (s) => (s === "refused" ? "refused: check the mission and token in the URL" : s);
function setStatus(status) {
  if (status !== state.status) {
    addLog(Date.now() / 1000, status === "connected" ? 2 : 3, statusText(status));
  }
  state.status = status;
  state.connected = status === "connected";
  ui.panelDirty = true;
  expose();
}

function resetScene() {
  for (const m of [state.channels, state.subscriptions, state.agents, state.clouds, state.keyframes]) m.clear();
  state.stats = null;
  changed("all");
}

// Keeps window.cvislamViewer (read by test/viewer/browser_test.mjs) and the page title up to date.
function expose() {
  const agents = {};
  for (const a of state.agents.values()) {
    agents[a.id] = { pose: a.pose ? [...a.pose.p] : null, trajectoryLength: a.trajectory ? a.trajectory.length / 3 : 0,
                     map: agentMap(a), connected: a.stats?.connected ?? null, colour: colourOf(a.id) };
  }
  Object.assign(api, {
    connected: state.connected, status: state.status, mission: state.mission,
    channels: [...state.channels.values()].map((c) => c.topic), messages: { ...state.messages },
    agents, shownMap: shownMap(), events: [...state.events], keyframes: state.keyframes.size,
    pointClouds: Object.fromEntries([...state.clouds].map(([m, c]) => [m, c.count])),
  });
  document.title = `cvislam viewer: ${state.mission || "?"} (${state.agents.size} agents)`;
}

// ---------------------------------------------------------------------------------------------------------------
// The scene: z is up in the maps (gravity-aligned). Everything drawn belongs to the shown map.

const viewEl = document.getElementById("view");
// Multisampling doubles the cost of every frame in a software renderer (SwiftShader: headless tests, machines
// without a GPU), where the page would otherwise take most of a core: smooth lines only with a GPU.
const probe = document.createElement("canvas").getContext("webgl2");
const info = probe?.getExtension("WEBGL_debug_renderer_info");
const software = /swiftshader|llvmpipe|software/i.test(info ? probe.getParameter(info.UNMASKED_RENDERER_WEBGL) : "");
probe?.getExtension("WEBGL_lose_context")?.loseContext();
const renderer = new THREE.WebGLRenderer({ antialias: !software, preserveDrawingBuffer: true });
renderer.setPixelRatio(window.devicePixelRatio);
viewEl.prepend(renderer.domElement);
const scene = new THREE.Scene();
scene.background = new THREE.Color(BACKGROUND);

const perspective = new THREE.PerspectiveCamera(FOV, 1, 0.01, 1000);
perspective.up.set(0, 0, 1);
const top = new THREE.OrthographicCamera(-1, 1, 1, -1, 0.01, 1000);
top.up.set(0, 1, 0); // north (+y) up on the screen

const emptyGeometry = () => new THREE.BufferGeometry();
const grid = new THREE.LineSegments(emptyGeometry(), new THREE.LineBasicMaterial({ color: GRID }));
const cloud = new THREE.Points(emptyGeometry(),
  new THREE.PointsMaterial({ color: POINTS, size: 2, sizeAttenuation: false })); // 2 pixels whatever the zoom
const edges = new THREE.LineSegments(emptyGeometry(), new THREE.LineBasicMaterial({ color: EDGES }));
const cubeGeometry = new THREE.BoxGeometry(1, 1, 1);
const cubeMaterial = new THREE.MeshBasicMaterial(); // white: the instance colours show as they are
let cubes = null; // an InstancedMesh, grown as needed
scene.add(grid, cloud, edges);

// The agent's marker: a cone along its body x axis, kept about the same size on screen, drawn over everything with
// a white rim (a larger white cone drawn first): its own keyframes, in the same colour, would otherwise hide it.
const coneGeometry = new THREE.ConeGeometry(0.3, 1, 20).rotateZ(-Math.PI / 2);
const rimMaterial = new THREE.MeshBasicMaterial({ color: "#ffffff", depthTest: false, side: THREE.DoubleSide });
const agentDrawings = new Map(); // agent id -> {marker, path, label}

function setPositions(geometry, positions) {
  geometry.dispose(); // frees the old GPU buffer; the geometry uploads its new one on the next render
  geometry.setAttribute("position", new THREE.BufferAttribute(positions, 3));
  geometry.computeBoundingSphere();
}

const ui = { view: "3d", userMoved: false, dirty: new Set(["all"]), needsRender: true, panelDirty: true,
             logDirty: true, lastPanel: 0, lastRebuild: 0, shownKeyframes: [], cubePx: 0, bounds: new THREE.Box3(),
             fitted: null, shown: undefined };
const orbit = { target: new THREE.Vector3(), distance: 10, azimuth: -Math.PI / 2, elevation: 0.7 };

function changed(what) {
  ui.dirty.add(what);
  ui.panelDirty = true;
}

// Rebuilds what changed for the shown map, and the bounds the camera fits.
function rebuild() {
  const map = shownMap();
  const all = ui.dirty.has("all") || map !== ui.shown;
  if (map !== ui.shown) ui.userMoved = false; // another map: fit it
  ui.shown = map;
  if (all || ui.dirty.has("cloud")) {
    const c = state.clouds.get(map);
    setPositions(cloud.geometry, c ? c.positions : new Float32Array(0));
    cloud.position.set(...vec(c?.pose?.position));
    cloud.quaternion.set(...quat(c?.pose?.orientation));
  }
  if (all || ui.dirty.has("keyframes")) {
    ui.shownKeyframes = [...state.keyframes.values()].filter((k) => k.map === map);
    const segments = ui.shownKeyframes.filter((k) => k.lines).map((k) => k.lines);
    const joined = new Float32Array(segments.reduce((n, s) => n + s.length, 0));
    segments.reduce((at, s) => (joined.set(s, at), at + s.length), 0);
    setPositions(edges.geometry, joined);
    ui.cubePx = 0; // lay the cubes out again
  }
  if (all || ui.dirty.has("agents")) {
    for (const a of state.agents.values()) drawAgent(a, map);
  }
  ui.dirty.clear();

  const box = new THREE.Box3();
  const c = state.clouds.get(map);
  if (c && !c.bounds.isEmpty()) box.union(c.bounds);
  for (const k of ui.shownKeyframes) box.expandByPoint(new THREE.Vector3(...k.p));
  for (const d of agentDrawings.values()) {
    if (d.marker.visible) box.expandByPoint(d.marker.position);
    if (d.path.visible && d.path.geometry.boundingSphere) {
      box.union(new THREE.Box3().setFromBufferAttribute(d.path.geometry.attributes.position));
    }
  }
  if (box.isEmpty()) box.set(new THREE.Vector3(-1, -1, 0), new THREE.Vector3(1, 1, 0));
  ui.bounds = box;
  buildGrid(box);
}

function drawAgent(a, map) {
  let d = agentDrawings.get(a.id);
  if (!d) {
    const material = new THREE.MeshBasicMaterial({ color: colourOf(a.id), depthTest: false });
    d = { marker: new THREE.Mesh(coneGeometry, material),
          path: new THREE.Line(emptyGeometry(), new THREE.LineBasicMaterial({ color: colourOf(a.id) })),
          label: Object.assign(document.createElement("div"), { className: "label", textContent: `agent ${a.id}` }) };
    d.label.style.color = colourOf(a.id);
    const rim = new THREE.Mesh(coneGeometry, rimMaterial);
    rim.scale.setScalar(1.2);
    rim.renderOrder = 1; // after the scene, before the cone
    d.marker.renderOrder = 2;
    d.marker.add(rim);
    document.getElementById("labels").append(d.label);
    scene.add(d.marker, d.path);
    agentDrawings.set(a.id, d);
  }
  d.marker.visible = !!a.pose && a.poseMap === map;
  if (a.pose) d.marker.position.set(...a.pose.p), d.marker.quaternion.set(...a.pose.q);
  d.path.visible = !!a.trajectory && a.trajectory.length >= 6 && a.trajMap === map;
  if (a.trajectory) setPositions(d.path.geometry, a.trajectory);
}

// Keyframe cubes: their own size, but never smaller than a few pixels, so that a large map still shows them.
function layoutKeyframes(pixel) {
  const list = ui.shownKeyframes;
  if (!cubes || cubes.instanceMatrix.count < list.length) {
    if (cubes) { scene.remove(cubes); cubes.dispose(); }
    cubes = new THREE.InstancedMesh(cubeGeometry, cubeMaterial, Math.max(64, 2 * list.length));
    cubes.frustumCulled = false; // its bounding sphere would go stale as instances move
    scene.add(cubes);
  }
  const m = new THREE.Matrix4(), p = new THREE.Vector3(), q = new THREE.Quaternion(), s = new THREE.Vector3();
  const colour = new THREE.Color();
  list.forEach((k, i) => {
    s.setScalar(Math.max(k.size, 4 * pixel));
    cubes.setMatrixAt(i, m.compose(p.set(...k.p), q.set(...k.q), s));
    cubes.setColorAt(i, colour.set(colourOf(k.agent)));
  });
  cubes.count = list.length;
  cubes.instanceMatrix.needsUpdate = true;
  if (cubes.instanceColor) cubes.instanceColor.needsUpdate = true;
  ui.cubePx = pixel;
}

// A square grid on the floor of the map (its lowest z), spaced by a power of ten: 4 to 40 cells across the map.
function buildGrid(box) {
  const size = box.getSize(new THREE.Vector3());
  const extent = Math.max(size.x, size.y, 1e-3);
  const step = 10 ** Math.floor(Math.log10(extent / 4));
  const x0 = Math.floor(box.min.x / step) - 2, x1 = Math.ceil(box.max.x / step) + 2;
  const y0 = Math.floor(box.min.y / step) - 2, y1 = Math.ceil(box.max.y / step) + 2;
  if ((x1 - x0) * (y1 - y0) > 40000) return; // degenerate bounds: keep the old grid
  const z = box.min.z, out = [];
  for (let x = x0; x <= x1; ++x) out.push(x * step, y0 * step, z, x * step, y1 * step, z);
  for (let y = y0; y <= y1; ++y) out.push(x0 * step, y * step, z, x1 * step, y * step, z);
  setPositions(grid.geometry, new Float32Array(out));
}

// ---------------------------------------------------------------------------------------------------------------
// Cameras: an orbit around a target for the 3-D view, the same target seen from above for the top view. Both
// share the distance, so that switching keeps the scale.

const camera = () => (ui.view === "top" ? top : perspective);
const tanHalf = Math.tan(THREE.MathUtils.degToRad(FOV / 2));
const worldPerPixel = () => (2 * orbit.distance * tanHalf) / Math.max(1, viewEl.clientHeight);

function fit() {
  const box = ui.bounds, size = box.getSize(new THREE.Vector3()), centre = box.getCenter(new THREE.Vector3());
  const aspect = perspective.aspect;
  // Refit only when the bounds changed noticeably: moving agents would otherwise make the view twitch.
  const radius = Math.max(size.length() / 2, 0.5);
  const f = ui.fitted;
  const same = f && f.view === ui.view && centre.distanceTo(f.centre) < 0.05 * f.radius;
  if (same && Math.abs(radius / f.radius - 1) < 0.05) return;
  ui.fitted = { view: ui.view, centre, radius };
  orbit.target.copy(centre);
  if (ui.view === "top") {
    orbit.distance = (Math.max(size.y / 2, size.x / 2 / aspect, 0.5) * 1.15) / tanHalf;
  } else {
    const halfAngle = Math.min(Math.atan(tanHalf), Math.atan(tanHalf * aspect));
    orbit.distance = (radius * 0.85) / Math.sin(halfAngle); // the box's corners are rarely all in view
  }
  ui.needsRender = true;
}

function placeCameras() {
  const { target, distance, azimuth, elevation } = orbit;
  perspective.position.set(Math.cos(elevation) * Math.cos(azimuth), Math.cos(elevation) * Math.sin(azimuth),
    Math.sin(elevation)).multiplyScalar(distance).add(target);
  perspective.near = distance / 500;
  perspective.far = distance * 100;
  perspective.lookAt(target);
  perspective.updateProjectionMatrix();
  const halfH = distance * tanHalf, depth = distance + ui.bounds.getSize(new THREE.Vector3()).length() + 10;
  Object.assign(top, { left: -halfH * perspective.aspect, right: halfH * perspective.aspect, top: halfH,
                       bottom: -halfH, near: 0.01, far: 2 * depth });
  top.position.set(target.x, target.y, target.z + depth);
  top.lookAt(target);
  top.updateProjectionMatrix();
}

function resize() {
  const w = Math.max(1, viewEl.clientWidth), h = Math.max(1, viewEl.clientHeight);
  renderer.setSize(w, h, false);
  perspective.aspect = w / h;
  ui.fitted = null;
  ui.needsRender = true;
}
new ResizeObserver(resize).observe(viewEl);

// Mouse: left-drag rotates (pans in the top view), right- or shift-drag pans, the wheel zooms, a double-click fits.
const canvas = renderer.domElement;
let drag = null;
canvas.addEventListener("contextmenu", (e) => e.preventDefault());
canvas.addEventListener("pointerdown", (e) => {
  drag = { x: e.clientX, y: e.clientY, pan: e.button !== 0 || e.shiftKey || ui.view === "top" };
  canvas.setPointerCapture(e.pointerId);
});
canvas.addEventListener("pointerup", () => (drag = null));
canvas.addEventListener("pointermove", (e) => {
  if (!drag) return;
  const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
  Object.assign(drag, { x: e.clientX, y: e.clientY });
  if (drag.pan) {
    const px = worldPerPixel(), m = camera().matrixWorld;
    orbit.target.addScaledVector(new THREE.Vector3().setFromMatrixColumn(m, 0), -dx * px);
    orbit.target.addScaledVector(new THREE.Vector3().setFromMatrixColumn(m, 1), dy * px);
  } else {
    orbit.azimuth -= dx * 0.006;
    orbit.elevation = THREE.MathUtils.clamp(orbit.elevation + dy * 0.006, -1.5, 1.5);
  }
  userMoved();
});
canvas.addEventListener("wheel", (e) => {
  e.preventDefault();
  orbit.distance *= Math.exp(THREE.MathUtils.clamp(e.deltaY, -200, 200) * 0.0015);
  userMoved();
}, { passive: false });
canvas.addEventListener("dblclick", () => refit());

const userMoved = () => Object.assign(ui, { userMoved: true, needsRender: true });
const refit = () => Object.assign(ui, { userMoved: false, fitted: null, needsRender: true });

// ---------------------------------------------------------------------------------------------------------------
// Frame loop: the scene is rebuilt when data changed, at most every REBUILD_MS (poses of several agents come at
// 5 Hz each, unsynchronised: drawing each one costs a software renderer dearly), and drawn when anything changed;
// the camera follows the mouse at the full frame rate. Between draws the last frame stays in the canvas
// (preserveDrawingBuffer, which also lets tests read it).

function frame(now) {
  requestAnimationFrame(frame);
  if (ui.dirty.size && now - ui.lastRebuild >= REBUILD_MS) {
    rebuild();
    ui.lastRebuild = now;
    ui.needsRender = true;
  }
  if (!ui.userMoved) fit();
  if (ui.needsRender) {
    placeCameras();
    const px = worldPerPixel();
    if (Math.abs(px / ui.cubePx - 1) > 0.1 || !Number.isFinite(px / ui.cubePx)) layoutKeyframes(px);
    for (const d of agentDrawings.values()) d.marker.scale.setScalar(28 * px);
    renderer.render(scene, camera());
    placeLabels();
    ui.needsRender = false;
  }
  if (ui.panelDirty && performance.now() - ui.lastPanel > 250) updatePanel();
}

function placeLabels() {
  const w = viewEl.clientWidth, h = viewEl.clientHeight, p = new THREE.Vector3();
  for (const d of agentDrawings.values()) {
    p.copy(d.marker.position).project(camera());
    const show = d.marker.visible && Math.abs(p.x) <= 1 && Math.abs(p.y) <= 1 && Math.abs(p.z) <= 1;
    d.label.style.display = show ? "" : "none";
    if (show) d.label.style.left = `${((p.x + 1) / 2) * w + 12}px`, d.label.style.top = `${((1 - p.y) / 2) * h}px`;
  }
}

// ---------------------------------------------------------------------------------------------------------------
// The side panel.

const $ = (id) => document.getElementById(id);
const esc = (s) => String(s).replace(/[&<>"']/g, (c) => `&#${c.charCodeAt(0)};`);
function bytes(n) {
  if (!(n >= 0)) return "–";
  let i = 0;
  for (; n >= 1024 && i < 4; ++i) n /= 1024;
  return i === 0 ? `${n} B` : `${n.toFixed(n < 10 ? 2 : 1)} ${["", "KiB", "MiB", "GiB", "TiB"][i]}`;
}
const LEVELS = { 1: "debug", 3: "warn", 4: "error", 5: "error" };

function updatePanel() {
  ui.panelDirty = false;
  ui.lastPanel = performance.now();
  $("status").className = `status ${state.status}`;
  $("status-text").textContent = statusText(state.status);
  $("mission").textContent = state.mission || "–";

  const maps = mapList(), shown = shownMap();
  // Only the map ids in the options: figures there would replace them (and close the dropdown) every second.
  const largest = state.chosenMap === null && shown !== null ? ` (map ${shown})` : "";
  fillSelect($("map-select"), [["", `largest${largest}`], ...maps.map((m) => [String(m.map), `map ${m.map}`])],
    state.chosenMap === null ? "" : String(state.chosenMap));
  const missions = [...state.missions].sort();
  $("mission-select").hidden = missions.length < 2;
  fillSelect($("mission-select"), missions.map((m) => [m, m]), state.mission);
  const view = ui.view === "top" ? "top view" : "3-D view";
  $("viewinfo").textContent = shown === null ? "no map yet" : `map ${shown} · ${view}`;

  const agents = [...state.agents.values()].sort((a, b) => a.id - b.id);
  $("agents").tBodies[0].innerHTML = agents.map((a) => {
    const s = a.stats, map = agentMap(a);
    const link = s ? (s.connected ? "on" : `<span class="off">off</span>`) : "–";
    const here = map === shown;
    return `<tr class="${here ? "shown" : "elsewhere"}" title="${here ? "" : "on another map: not drawn"}">
      <td><span class="swatch" style="background:${colourOf(a.id)}"></span></td><td>${a.id}</td><td>${link}</td>
      <td>${map ?? "–"}</td><td>${s?.keyframes ?? "–"}</td><td>${bytes(s?.up_bytes)}</td>
      <td>${bytes(s?.down_bytes)}</td></tr>`;
  }).join("");
  $("maps").tBodies[0].innerHTML = maps.map((m) => `<tr class="${m.map === shown ? "shown" : "elsewhere"}">
      <td>${m.map}${m.map === shown ? " ◂" : ""}</td><td>${m.keyframes}</td><td>${m.points}</td>
      <td>${(m.agents ?? []).map((id) => `<span style="color:${colourOf(id)}">${id}</span>`).join(" ")}</td>
    </tr>`).join("");

  if (ui.logDirty) {
    ui.logDirty = false;
    const time = (t) => new Date(t * 1000).toTimeString().slice(0, 8);
    $("log").innerHTML = state.log.slice().reverse().map((e) =>
      `<li class="${LEVELS[e.level] ?? ""}"><time>${time(e.t)}</time>${esc(e.text)}</li>`).join("");
  }
}

// Replaces a select's options only when they differ, so that an open dropdown is not closed by an update.
function fillSelect(select, options, value) {
  const key = JSON.stringify(options);
  if (select.dataset.key !== key) {
    select.dataset.key = key;
    select.innerHTML = options.map(([v, text]) => `<option value="${esc(v)}">${esc(text)}</option>`).join("");
  }
  if (document.activeElement !== select) select.value = value;
}

$("map-select").addEventListener("change", (e) => {
  state.chosenMap = e.target.value === "" ? null : Number(e.target.value);
  ui.userMoved = false;
  changed("all");
  expose();
});
$("mission-select").addEventListener("change", (e) => {
  query.set("mission", e.target.value);
  location.search = query.toString(); // a fresh page: one mission per connection
});
$("view-toggle").addEventListener("click", () => {
  ui.view = ui.view === "top" ? "3d" : "top";
  $("view-toggle").textContent = ui.view === "top" ? "3-D view" : "top view";
  ui.fitted = null;
  ui.needsRender = ui.panelDirty = true;
});
$("fit").addEventListener("click", refit);

expose();
resize();
connect();
requestAnimationFrame(frame);
