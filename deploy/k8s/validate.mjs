// Validates rendered Kubernetes manifests offline: every object against the Kubernetes schemas
// (kubernetes-models), then the project's own rules, which the schemas cannot express. One line per object,
// then "N passed, N failed". Run by deploy/check_deploy.sh, from the tools folder (ESM resolves
// kubernetes-models from the script's own location):
//
//   node out/deploy-tools/validate.mjs [--metrics-source METRICS_ENDPOINT_CPP] RENDERED.yaml [...]
//
// --metrics-source: the server's metrics endpoint (server_cloud/service/metrics_endpoint.cpp), from which the
// names of the metrics the server exports are read (every quoted "cvislam_..." string, as
// deploy/grafana/check_dashboard.py reads them). Without it, an HPA or adapter rule that names a metric fails.
//
// Rules (each names the object and the field):
//   - workloads: pinned images (a tag, never "latest"); CPU and memory requests and a memory limit per
//     container; pod runAsNonRoot; no privilege escalation;
//   - the server: startup, readiness and liveness probes over gRPC, on a port the container declares;
//   - a container with iceoryx (/dev/shm mounted) gets a memory emptyDir of at least 256 MiB there;
//   - every ConfigMap, Secret and key a pod uses exists in the same render; every Service selects a workload
//     and targets a port it declares;
//   - a HorizontalPodAutoscaler (autoscaling/v2) scales a StatefulSet or Deployment of the same render (and
//     namespace) that sets no spec.replicas of its own; 1 <= minReplicas <= maxReplicas; it has metrics, and
//     each Pods metric is one the server exports;
//   - a prometheus-adapter rule (a ConfigMap value holding "rules:" with seriesQuery) names an exported metric
//     when it names a cvislam_ one, and has a metricsQuery.
import { readFileSync } from "node:fs";
import { parse, parseAllDocuments } from "yaml";

const groupOf = (apiVersion) => {
  const parts = apiVersion.split("/");
  return parts.length === 1 ? { group: "", version: parts[0] } : { group: parts[0], version: parts[1] };
};

async function schemaCheck(obj) {
  const { group, version } = groupOf(obj.apiVersion ?? "");
  if (obj.kind === "Secret" || obj.kind === "ConfigMap") {
    // kustomize folds long base64 values over several lines, which YAML reads back joined by spaces; the API
    // server's decoder ignores that whitespace, the schema's "byte" format does not.
    obj = { ...obj, ...(obj.data && obj.kind === "Secret" ? { data: Object.fromEntries(
      Object.entries(obj.data).map(([k, v]) => [k, String(v).replace(/\s+/g, "")])) } : {}),
      ...(obj.binaryData ? { binaryData: Object.fromEntries(
      Object.entries(obj.binaryData).map(([k, v]) => [k, String(v).replace(/\s+/g, "")])) } : {}) };
  }
  const path = `kubernetes-models/${group ? group + "/" : ""}${version}/${obj.kind}`;
  let Model;
  try {
    Model = (await import(path))[obj.kind];
  } catch (e) {
    return [`unknown kind ${obj.apiVersion}/${obj.kind}`];
  }
  try {
    new Model(obj).validate();
    return [];
  } catch (e) {
    return [String(e.message ?? e).split("\n").slice(0, 3).join("; ")];
  }
}

const memBytes = (q) => {
  const m = /^([0-9.]+)(Ki|Mi|Gi|Ti|K|M|G|T)?$/.exec(String(q ?? ""));
  if (!m) return NaN;
  const unit = { Ki: 2 ** 10, Mi: 2 ** 20, Gi: 2 ** 30, Ti: 2 ** 40, K: 1e3, M: 1e6, G: 1e9, T: 1e12 }[m[2]] ?? 1;
  return Number(m[1]) * unit;
};

const podSpecOf = (obj) => {
  if (obj.kind === "Pod") return { spec: obj.spec, labels: obj.metadata?.labels ?? {} };
  if (["Deployment", "StatefulSet", "DaemonSet", "Job"].includes(obj.kind)) {
    return { spec: obj.spec?.template?.spec, labels: obj.spec?.template?.metadata?.labels ?? {} };
  }
  return null;
};

function workloadRules(obj, names) {
  const errors = [];
  const { spec } = podSpecOf(obj);
  if (!spec) return ["no pod spec"];
  if (spec.securityContext?.runAsNonRoot !== true) errors.push("spec.securityContext.runAsNonRoot must be true");
  const volumes = Object.fromEntries((spec.volumes ?? []).map((v) => [v.name, v]));
  for (const t of obj.spec?.volumeClaimTemplates ?? []) volumes[t.metadata?.name] = { persistentVolumeClaim: {} };
  for (const v of spec.volumes ?? []) {
    if (v.configMap && !names.has(`ConfigMap/${v.configMap.name}`)) {
      errors.push(`volume ${v.name}: ConfigMap ${v.configMap.name} is not in this render`);
    }
    if (v.secret && !names.has(`Secret/${v.secret.secretName}`)) {
      errors.push(`volume ${v.name}: Secret ${v.secret.secretName} is not in this render`);
    }
  }
  for (const c of [...(spec.initContainers ?? []), ...(spec.containers ?? [])]) {
    const where = `container ${c.name}`;
    const image = String(c.image ?? "");
    const tag = image.includes("@") ? "digest" : image.split("/").pop().split(":")[1];
    if (!tag || tag === "latest") errors.push(`${where}: image '${image}' needs a pinned tag (not latest)`);
    const r = c.resources ?? {};
    if (!r.requests?.cpu || !r.requests?.memory) errors.push(`${where}: resources.requests needs cpu and memory`);
    if (!r.limits?.memory) errors.push(`${where}: resources.limits.memory is missing`);
    if (c.securityContext?.allowPrivilegeEscalation !== false) {
      errors.push(`${where}: securityContext.allowPrivilegeEscalation must be false`);
    }
    for (const e of c.env ?? []) {
      const ref = e.valueFrom?.secretKeyRef;
      if (ref && !names.has(`Secret/${ref.name}`)) errors.push(`${where}: env ${e.name}: Secret ${ref.name} is not in this render`);
      if (ref && names.has(`Secret/${ref.name}`) && !names.get(`Secret/${ref.name}`).has(ref.key)) {
        errors.push(`${where}: env ${e.name}: Secret ${ref.name} has no key '${ref.key}'`);
      }
    }
    for (const m of c.volumeMounts ?? []) {
      if (!volumes[m.name]) errors.push(`${where}: volumeMount ${m.name} has no volume`);
      if (m.mountPath === "/dev/shm") {
        const v = volumes[m.name]?.emptyDir;
        if (!v || v.medium !== "Memory") errors.push(`${where}: /dev/shm (iceoryx) must be an emptyDir with medium Memory`);
        else if (!(memBytes(v.sizeLimit) >= 256 * 2 ** 20)) errors.push(`${where}: /dev/shm sizeLimit must be >= 256Mi (RouDi's pools)`);
      }
    }
    if (obj.metadata?.name === "cvislam-server" || /cvislam-server$/.test(obj.metadata?.name ?? "")) {
      const ports = new Set((c.ports ?? []).flatMap((p) => [p.containerPort, p.name]));
      for (const probe of ["startupProbe", "readinessProbe", "livenessProbe"]) {
        const g = c[probe]?.grpc;
        if (!g) errors.push(`${where}: ${probe} must be a gRPC probe`);
        else if (!ports.has(g.port)) errors.push(`${where}: ${probe} probes port ${g.port}, which the container does not declare`);
      }
    }
  }
  return errors;
}

function serviceRules(obj, workloads) {
  const errors = [];
  const selector = obj.spec?.selector ?? {};
  const matching = workloads.filter(({ labels }) => Object.entries(selector).every(([k, v]) => labels[k] === v));
  if (Object.keys(selector).length === 0 || matching.length === 0) {
    errors.push("spec.selector selects no workload in this render");
    return errors;
  }
  for (const p of obj.spec?.ports ?? []) {
    const target = p.targetPort ?? p.port;
    const declared = matching.some(({ spec }) =>
      (spec.containers ?? []).some((c) => (c.ports ?? []).some((cp) => cp.name === target || cp.containerPort === target)));
    if (!declared) errors.push(`port ${p.name ?? p.port}: targetPort ${target} is not a port of the selected pods`);
  }
  return errors;
}

// The metric names the server exports, read from its metrics endpoint's source.
function exportedMetrics(source) {
  const names = new Set([...readFileSync(source, "utf8").matchAll(/"(cvislam_[a-z0-9_]+)"/g)].map((m) => m[1]));
  if (names.size === 0) throw new Error(`validate: no metric names found in ${source}`);
  return names;
}

function metricExported(name, exported) {
  if (!exported) return `metric ${name}: cannot check it against the server's metrics (give --metrics-source)`;
  return exported.has(name) ? null : `metric ${name} is not one the server exports (server_cloud/service/metrics_endpoint.cpp)`;
}

const SCALABLE = new Set(["StatefulSet", "Deployment"]);

function hpaRules(obj, docs, exported) {
  if (obj.apiVersion !== "autoscaling/v2") return [`apiVersion ${obj.apiVersion}: use autoscaling/v2`];
  const errors = [];
  const spec = obj.spec ?? {};
  const ref = spec.scaleTargetRef ?? {};
  const namespace = obj.metadata?.namespace;
  if (!SCALABLE.has(ref.kind)) {
    errors.push(`spec.scaleTargetRef.kind ${ref.kind}: must be a StatefulSet or Deployment`);
  } else {
    const target = docs.find((o) => o.kind === ref.kind && o.metadata?.name === ref.name &&
      o.metadata?.namespace === namespace);
    if (!target) {
      errors.push(`spec.scaleTargetRef: ${ref.kind} ${ref.name} is not in this render${namespace ? ` (namespace ${namespace})` : ""}`);
    } else {
      if (ref.apiVersion !== target.apiVersion) {
        errors.push(`spec.scaleTargetRef.apiVersion ${ref.apiVersion}: the ${ref.kind} is ${target.apiVersion}`);
      }
      if (target.spec?.replicas !== undefined) {
        errors.push(`spec.scaleTargetRef: ${ref.kind} ${ref.name} sets spec.replicas, which every apply resets under the HPA`);
      }
    }
  }
  const min = spec.minReplicas ?? 1;
  if (!(Number.isInteger(min) && min >= 1)) errors.push(`spec.minReplicas ${min}: must be at least 1`);
  if (!(Number.isInteger(spec.maxReplicas) && spec.maxReplicas >= min)) {
    errors.push(`spec.maxReplicas ${spec.maxReplicas}: must be at least minReplicas (${min})`);
  }
  const metrics = spec.metrics ?? [];
  if (metrics.length === 0) errors.push("spec.metrics: none");
  for (const [i, m] of metrics.entries()) {
    if (m.type !== "Pods") continue;
    const problem = metricExported(m.pods?.metric?.name, exported);
    if (problem) errors.push(`spec.metrics[${i}]: ${problem}`);
  }
  return errors;
}

// The rules of a prometheus-adapter config held in a ConfigMap value, or null when the value is not one.
function adapterRulesOf(text) {
  if (!/^rules:/m.test(String(text))) return null;
  let config;
  try {
    config = parse(String(text));
  } catch (e) {
    return null;
  }
  const rules = config?.rules;
  return Array.isArray(rules) && rules.some((r) => r?.seriesQuery) ? rules : null;
}

function adapterRules(obj, exported) {
  const errors = [];
  for (const [key, text] of Object.entries(obj.data ?? {})) {
    for (const [i, rule] of (adapterRulesOf(text) ?? []).entries()) {
      const where = `data.${key} rules[${i}]`;
      if (!rule.metricsQuery) errors.push(`${where}: no metricsQuery`);
      for (const name of String(rule.seriesQuery ?? "").match(/cvislam_[a-z0-9_]+/g) ?? []) {
        const problem = metricExported(name, exported);
        if (problem) errors.push(`${where}: seriesQuery: ${problem}`);
      }
    }
  }
  return errors;
}

const args = process.argv.slice(2);
let exported = null;
const at = args.indexOf("--metrics-source");
if (at >= 0) {
  exported = exportedMetrics(args[at + 1]);
  args.splice(at, 2);
}

let passed = 0;
let failed = 0;
for (const file of args) {
  const docs = parseAllDocuments(readFileSync(file, "utf8")).map((d) => d.toJS()).filter(Boolean);
  // names: "Kind/name" -> set of data keys (ConfigMaps and Secrets), for reference checks
  const names = new Map(docs.map((o) => [`${o.kind}/${o.metadata?.name}`,
    new Set([...Object.keys(o.data ?? {}), ...Object.keys(o.stringData ?? {})])]));
  const workloads = docs.map(podSpecOf).filter((w) => w && w.spec);
  for (const obj of docs) {
    const id = `${file.split("/").pop()}: ${obj.kind}/${obj.metadata?.name}`;
    const errors = await schemaCheck(obj);
    if (podSpecOf(obj)) errors.push(...workloadRules(obj, names));
    if (obj.kind === "Service") errors.push(...serviceRules(obj, workloads));
    if (obj.kind === "HorizontalPodAutoscaler") errors.push(...hpaRules(obj, docs, exported));
    if (obj.kind === "ConfigMap") errors.push(...adapterRules(obj, exported));
    if (errors.length === 0) {
      passed += 1;
      console.log(`ok    ${id}`);
    } else {
      failed += 1;
      console.log(`FAIL  ${id}\n        ${errors.join("\n        ")}`);
    }
  }
}
console.log(`${passed} passed, ${failed} failed`);
process.exit(failed === 0 && passed > 0 ? 0 : 1);
