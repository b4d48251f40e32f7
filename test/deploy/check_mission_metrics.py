#!/usr/bin/env python3
"""Checks the server's Prometheus metrics of a real mission: every scrape taken while it ran parses with the
Prometheus project's own text-format parser (python3-prometheus-client), counters never go back, and the scrape
taken after the agents ended matches what the server wrote into stats.json at shutdown.

    check_mission_metrics.py SCRAPES_DIR FINAL_SCRAPE STATS_JSON MISSION
"""
import json
import pathlib
import sys

from prometheus_client.parser import text_string_to_metric_families


def fail(message):
    print(f"check_mission_metrics: {message}", file=sys.stderr)
    sys.exit(1)


def samples(path):
    """{(sample name, sorted labels): value} of one scrape; fails on anything the parser refuses."""
    out = {}
    try:
        for family in text_string_to_metric_families(path.read_text()):
            for s in family.samples:
                out[(s.name, tuple(sorted(s.labels.items())))] = s.value
    except Exception as e:  # the parser raises ValueError and others on malformed text
        fail(f"{path}: not Prometheus text format ({e})")
    return out


def value(scrape, name, **labels):
    return scrape.get((name, tuple(sorted(labels.items()))))


def main():
    scrapes_dir, final_file, stats_file, mission = pathlib.Path(sys.argv[1]), pathlib.Path(sys.argv[2]), \
        pathlib.Path(sys.argv[3]), sys.argv[4]
    during = sorted(scrapes_dir.glob("*.txt"))
    if len(during) < 2:
        fail(f"{len(during)} scrapes taken during the mission; want at least 2")
    previous = {}
    for f in during:
        now = samples(f)
        for key, v in now.items():
            if key[0].endswith("_total") and key in previous and v < previous[key]:
                fail(f"{f}: counter {key} went back from {previous[key]} to {v}")
        previous = now
    final = samples(final_file)
    stats = json.loads(stats_file.read_text())
    agents = [a for a in stats["agents"] if a["mission"] == mission]
    if not agents:
        fail(f"stats.json has no agent of mission {mission}")

    def total(direction, kind, field):
        return sum(int(a[direction].get(kind, {}).get(field, 0)) for a in agents)

    # The link's counters are final once the agents have ended: they must equal what stats.json says.
    checked = 0
    for direction in ("up", "down"):
        kinds = {k for a in agents for k in a[direction]}
        for kind in kinds:
            for field, name in (("messages", "cvislam_link_messages_total"), ("bytes", "cvislam_link_bytes_total")):
                got = value(final, name, direction=direction, kind=kind, mission=mission)
                want = total(direction, kind, field)
                if got is None or int(got) != want:
                    fail(f"{name}{{direction={direction}, kind={kind}}} = {got}, stats.json says {want}")
                checked += 1
    if value(final, "cvislam_agents", mission=mission) != len(agents):
        fail(f"cvislam_agents = {value(final, 'cvislam_agents', mission=mission)}, stats.json has {len(agents)}")
    batches = total("up", "batch", "messages")
    ingested = value(final, "cvislam_ingest_seconds_count")
    duplicates = sum(int(a.get("duplicate_batches", 0)) for a in agents)
    if ingested is None or int(ingested) != batches - duplicates:
        fail(f"cvislam_ingest_seconds_count = {ingested}; stats.json: {batches} batches, {duplicates} duplicates")
    if value(final, "cvislam_merges_total", mission=mission) is None:
        fail("no cvislam_merges_total for the mission")
    print(f"check_mission_metrics: {len(during)} scrapes during the mission parsed, counters monotonic; "
          f"{checked} link counters and {int(ingested)} ingested batches match stats.json")


if __name__ == "__main__":
    main()
