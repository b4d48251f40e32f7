#!/usr/bin/env python3
"""Checks the traces of a real mission (deploy/run_mission.sh --trace): every file is Chrome Trace Event JSON whose
spans close on named threads, the ids join up across processes, cvislam_trace aligns each agent's clock to the
server's (one machine: an offset of 0 within the stated bound), and recovers an offset injected into one agent's
trace.

    check_mission_trace.py TRACE_DIR CVISLAM_TRACE_BINARY
"""
import json
import pathlib
import subprocess
import sys
import tempfile

INJECTED_MS = 250.0


def fail(message):
    print(f"check_mission_trace: {message}", file=sys.stderr)
    sys.exit(1)


def load(path):
    try:
        doc = json.loads(path.read_text())
    except ValueError as e:
        fail(f"{path}: not JSON ({e})")
    if "traceEvents" not in doc or "otherData" not in doc:
        fail(f"{path}: no traceEvents or otherData")
    return doc


def check_events(path, doc, want_threads):
    names = {}
    for e in doc["traceEvents"]:
        if e["ph"] == "M" and e["name"] == "thread_name":
            names[e["tid"]] = e["args"]["name"]
    spans = 0
    for e in doc["traceEvents"]:
        if e["ph"] == "M":
            continue
        if e["ph"] not in ("X", "i"):
            fail(f"{path}: an event of phase {e['ph']}")
        if e["tid"] not in names:
            fail(f"{path}: event '{e['name']}' on thread {e['tid']}, which has no name")
        if e["ph"] == "X":
            spans += 1
            if not (isinstance(e["dur"], (int, float)) and e["dur"] >= 0):
                fail(f"{path}: span '{e['name']}' does not close (dur {e.get('dur')})")
    missing = want_threads - set(names.values())
    if missing:
        fail(f"{path}: no events from thread(s) {sorted(missing)}; threads: {sorted(set(names.values()))}")
    if spans == 0:
        fail(f"{path}: no spans")
    if doc["otherData"]["overwritten"] != 0:
        fail(f"{path}: {doc['otherData']['overwritten']} events overwritten in a short mission")


def events(doc, name):
    return [e for e in doc["traceEvents"] if e["name"] == name and e["ph"] != "M"]


def merge(binary, files, out_json):
    run = subprocess.run([binary, "merge", "--json", str(out_json), *map(str, files)], capture_output=True, text=True)
    if run.returncode != 0:
        fail(f"cvislam_trace merge failed: {run.stderr.strip()}")
    return json.loads(out_json.read_text()), run.stdout


def main():
    trace_dir = pathlib.Path(sys.argv[1])
    binary = sys.argv[2]
    server_file = trace_dir / "server.json"
    agent_files = sorted(trace_dir.glob("agent*.json"))
    if len(agent_files) < 2:
        fail(f"{trace_dir}: {len(agent_files)} agent traces; the mission has two agents")
    server = load(server_file)
    check_events(server_file, server, {"recognition", "backend", "global BA"})
    key = None
    for f in agent_files:
        agent = load(f)
        check_events(f, agent, {"tracking", "mapping", "link", "loader"})
        # Every keyframe the agent sent reached the server in the batch the agent says it went in.
        key = agent["otherData"]["mission_key"]
        me = agent["otherData"]["agent"]
        ingested = {e["args"]["batch"] for e in events(server, "ingest")
                    if e["args"]["agent"] == me and e["args"]["mission"] == key}
        sent = events(agent, "keyframe_sent")
        decided = {e["args"]["keyframe"] for e in events(agent, "keyframe_write")}
        if not sent or not decided:
            fail(f"{f}: no keyframes decided or sent")
        lost = [e["args"] for e in sent if e["args"]["batch"] not in ingested]
        if lost:
            fail(f"{f}: {len(lost)} keyframes sent in batches the server has no ingest of, e.g. {lost[0]}")
        if not decided <= {e["args"]["keyframe"] for e in sent}:
            fail(f"{f}: keyframes decided but never sent: {sorted(decided - {e['args']['keyframe'] for e in sent})[:5]}")

    with tempfile.TemporaryDirectory() as tmp:
        tmp = pathlib.Path(tmp)
        summary, text = merge(binary, [server_file, *agent_files], tmp / "chain.json")
        for c in summary["clocks"]:
            if abs(c["offset_ms"]) > c["uncertainty_ms"] + 0.01 or c["uncertainty_ms"] > 20.0:
                fail(f"agent {c['agent']}: offset {c['offset_ms']} +- {c['uncertainty_ms']} ms on one machine")
        links = {l["link"]: l for l in summary["links"]}
        stored = links["keyframe decided -> stored on the server"]
        if stored["n"] != summary["keyframes"] or stored["n"] == 0:
            fail(f"{stored['n']} of {summary['keyframes']} keyframes followed to the server")

        # The first agent's clock 250 ms ahead: its offset comes out as -250 ms, and the way is the same.
        shifted = load(agent_files[0])
        for e in shifted["traceEvents"]:
            if e["ph"] != "M":
                e["ts"] += INJECTED_MS * 1000.0
        shifted_file = tmp / agent_files[0].name
        shifted_file.write_text(json.dumps(shifted))
        moved, _ = merge(binary, [server_file, shifted_file, *agent_files[1:]], tmp / "shifted.json")
        agent_id = shifted["otherData"]["agent"]
        c = next(c for c in moved["clocks"] if c["agent"] == agent_id)
        if abs(c["offset_ms"] + INJECTED_MS) > c["uncertainty_ms"] + 0.01:
            fail(f"injected {INJECTED_MS} ms into agent {agent_id}: recovered {c['offset_ms']} +- {c['uncertainty_ms']} ms")
        before = links["keyframe decided -> stored on the server"]["p50_ms"]
        after = {l["link"]: l for l in moved["links"]}["keyframe decided -> stored on the server"]["p50_ms"]
        if abs(before - after) > 2 * c["uncertainty_ms"] + 0.01:
            fail(f"the way changed with the clock: decided -> stored p50 {before} ms, {after} ms after the shift")
    print(text, end="")
    print(f"check_mission_trace: {len(agent_files)} agents and the server: spans closed, ids joined, clocks aligned; "
          f"{INJECTED_MS} ms injected, {c['offset_ms']:.3f} +- {c['uncertainty_ms']:.3f} ms recovered")


if __name__ == "__main__":
    main()
