#!/usr/bin/env bash
# The capacity benchmark in a short form, as CTest runs it: CPU budgets and agent copies work. Two cvislam_agent
# processes fly the real EuRoC V1_01 excerpt into a recording server; then test/scaleout/capacity_bench.sh runs one
# step: two replicas, each in a cgroup of 0.25 cores, and two missions of four agents (the two recorded agents and
# a copy of each under new ids, --copies 2). Checks: every batch acknowledged; the copies flew as agents 2 and 3
# and the replicas served agents 0-3 in each mission; each replica's cgroup counted its periods, throttled some of
# them, and the replicas used no more CPU than their budgets allowed.
#
#   test/scaleout/capacity_budget_test.sh BIN_DIR      (CTest: scaleout_capacity_budget)
set -euo pipefail
bin=${1:?usage: $0 BIN_DIR}
repo=$(cd "$(dirname "$0")/../.." && pwd)
if [ "$(id -u)" != 0 ]; then echo "SKIPPED: CPU budgets need root (cgroups)"; exit 77; fi
source "$repo/test/scaleout/lib.sh"
v101_excerpt  # sets seq, or skips
# A machine without a usable cgroup cpu controller cannot run budgets at all: say so and skip, rather than fail.
if ! (cgroup_init "cvislam-probe-$$" && rmdir "$cgroup_dir"); then
  echo "SKIPPED: no cgroup cpu controller to run CPU budgets in (see above)"
  exit 77
fi
scaleout_work capacity-budget
fail() { echo "FAILED: $*" >&2; keep=1; exit 1; }

record_agents "$seq" || fail "making the recording"
"$repo/test/scaleout/capacity_bench.sh" "$bin" "$work/recording.db" --replicas 2 --agents 8 --copies 2 \
  --replica-cpus 0.25 --keep-going --out "$work/capacity.json" | tee "$work/bench.log" ||
  fail "capacity_bench.sh failed (see above)"
python3 - "$work/capacity.json" <<'PY' || fail "the step's figures (above)"
import json, sys
j = json.load(open(sys.argv[1]))
(step,) = j["steps"]
problems = []
if not step["finished"] or step["acked"] != step["batches"] or step["batches"] == 0:
    problems.append(f"{step['acked']} of {step['batches']} batches acknowledged")
if step["agent_ids"] != [0, 1, 2, 3]:
    problems.append(f"the replay clients flew agents {step['agent_ids']}, not 0-3 (copies under new ids)")
if step["served_agents"] != {"m0": [0, 1, 2, 3], "m1": [0, 1, 2, 3]}:
    problems.append(f"the replicas served {step['served_agents']}, not agents 0-3 in m0 and m1")
if not step["periods"] > 0:
    problems.append("the replicas' cgroups counted no periods: no quota was applied")
if not step["throttled_periods"] > 0:
    problems.append("no period was throttled at 0.25 cores: the quota was not enforced")
# The CPU a replica used can exceed its quota by at most a period's worth, read at the step's end.
if not step["budget_used"] <= 1.02:
    problems.append(f"the replicas used {step['budget_used']} of their budget: more CPU than allowed")
print(f"2 replicas at 0.25 cores: {step['acked']}/{step['batches']} batches acknowledged, agents {step['agent_ids']}, "
      f"served {step['served_agents']}, throttled {step['throttled_periods']} of {step['periods']} periods, "
      f"{step['budget_used']} of the budget used, ingest p99 worst agent {step['ingest_ms_p99_worst']:.0f} ms, "
      f"pooled {step['ingest_ms_p99_pooled']:.0f} ms over {step['ingest_samples']} batches")
if problems:
    print("\n".join(problems))
    sys.exit(1)
PY
echo "PASSED: CPU budgets applied and observed, copies flown under new ids"
