#!/usr/bin/env python3
"""Checks the Grafana dashboard offline against what the server exports: valid dashboard JSON (uid, title, panels
with unique ids inside the 24-column grid, each with PromQL targets), every query's brackets balanced, and every
metric and label a query names one that the server's metrics endpoint exports (read from its source). With
--self-test it also breaks the dashboard in each of those ways and expects every break to be refused.

    check_dashboard.py DASHBOARD_JSON METRICS_ENDPOINT_CPP [--self-test]
"""
import copy
import json
import re
import sys

# Labels a query may select on: the server's own, the histogram's, and what Prometheus adds to every target.
LABELS = {"mission", "direction", "kind", "le", "instance", "job", "pod", "namespace"}
PANEL_TYPES = {"timeseries", "stat", "gauge", "table", "bargauge"}


def exported_metrics(source):
    names = set(re.findall(r'"(cvislam_[a-z0-9_]+)"', source))
    if not names:
        raise SystemExit(f"check_dashboard: no metric names found in the endpoint's source")
    return names


def balanced(expr):
    pairs, stack = {")": "(", "]": "[", "}": "{"}, []
    for c in re.sub(r'"[^"]*"', '""', expr):  # brackets inside label values do not count
        if c in "([{":
            stack.append(c)
        elif c in pairs:
            if not stack or stack.pop() != pairs[c]:
                return False
    return not stack


def problems(dashboard, exported):
    out = []
    for key in ("uid", "title", "panels", "schemaVersion"):
        if key not in dashboard:
            out.append(f"no '{key}'")
    ids = set()
    for p in dashboard.get("panels", []):
        where = f"panel {p.get('id')} '{p.get('title')}'"
        if p.get("id") in ids:
            out.append(f"{where}: id used twice")
        ids.add(p.get("id"))
        if p.get("type") not in PANEL_TYPES:
            out.append(f"{where}: type {p.get('type')!r}")
        g = p.get("gridPos", {})
        if not all(isinstance(g.get(k), int) for k in "xywh") or g["x"] < 0 or g["x"] + g["w"] > 24:
            out.append(f"{where}: gridPos {g} outside the 24-column grid")
        targets = p.get("targets") or []
        if not targets:
            out.append(f"{where}: no targets")
        for t in targets:
            expr = t.get("expr", "")
            if not expr or not t.get("refId"):
                out.append(f"{where}: a target without expr or refId")
                continue
            if not balanced(expr):
                out.append(f"{where}: unbalanced brackets in {expr!r}")
            for name in re.findall(r"\b(cvislam_[a-z0-9_]+)", expr):
                base = re.sub(r"_(bucket|sum|count)$", "", name)
                if name not in exported and base not in exported:
                    out.append(f"{where}: {name} is not a metric the server exports")
            for selector in re.findall(r"\{([^}]*)\}", expr):
                for label in re.findall(r"([a-zA-Z_][a-zA-Z0-9_]*)\s*(?:=~|!~|!=|=)", selector):
                    if label not in LABELS:
                        out.append(f"{where}: label {label!r} is not one the server's metrics carry")
            for label in re.findall(r"\bby\s*\(([^)]*)\)", expr):
                for name in (s.strip() for s in label.split(",")):
                    if name and name not in LABELS:
                        out.append(f"{where}: grouping by {name!r}, a label the server's metrics do not carry")
    return out


def self_test(dashboard, exported):
    """Each way of breaking the dashboard must be refused."""
    breaks = {
        "an unknown metric": lambda d: d["panels"][0]["targets"][0].update(
            expr=d["panels"][0]["targets"][0]["expr"].replace("cvislam_", "cvislam_nonexistent_", 1)),
        "unbalanced brackets": lambda d: d["panels"][0]["targets"][0].update(
            expr=d["panels"][0]["targets"][0]["expr"] + ")"),
        "an unknown label": lambda d: d["panels"][0]["targets"][0].update(expr='cvislam_missions{agent="1"}'),
        "a duplicate panel id": lambda d: d["panels"][1].update(id=d["panels"][0]["id"]),
        "a panel outside the grid": lambda d: d["panels"][0]["gridPos"].update(x=20, w=12),
        "no uid": lambda d: d.pop("uid"),
    }
    failed = 0
    for what, do in breaks.items():
        broken = copy.deepcopy(dashboard)
        do(broken)
        if not problems(broken, exported):
            print(f"check_dashboard: self-test: {what} was not refused")
            failed += 1
    print(f"check_dashboard: self-test: {len(breaks) - failed} of {len(breaks)} broken dashboards refused")
    return failed == 0


def main():
    with open(sys.argv[1]) as f:
        try:
            dashboard = json.load(f)
        except ValueError as e:
            raise SystemExit(f"check_dashboard: {sys.argv[1]}: not JSON ({e})")
    with open(sys.argv[2]) as f:
        exported = exported_metrics(f.read())
    found = problems(dashboard, exported)
    for p in found:
        print(f"FAIL  {p}")
    queries = sum(len(p.get("targets", [])) for p in dashboard.get("panels", []))
    print(f"check_dashboard: {len(dashboard.get('panels', []))} panels, {queries} queries, {len(found)} problems")
    ok = not found
    if "--self-test" in sys.argv:
        ok = self_test(dashboard, exported) and ok
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    main()
