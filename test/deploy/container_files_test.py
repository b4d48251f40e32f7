#!/usr/bin/env python3
"""Checks a container file against the binaries it ships (CTest: deploy_container_*).

  container_files_test.py --dockerfile deploy/docker/server.Dockerfile --binary build/.../cvislam_server [...]

- multi-stage: a build stage and a runtime stage, every base image pinned to a Debian 12 point release;
- the runtime stage runs as a numeric non-root USER;
- RUNTIME_PACKAGES (the runtime stage's apt list) is exactly the set of Debian packages that hold the shared
  libraries the binaries name in their ELF NEEDED entries, less the base image's own (libc6, libgcc-s1,
  libstdc++6): a missing package is a container that cannot start, an extra one is weight it does not need.
Standard library only; needs readelf, ldd and dpkg (the build machine is Debian, like the image).
"""
import argparse
import os
import re
import subprocess
import sys

BASE_IMAGE_PACKAGES = {"libc6", "libgcc-s1", "libstdc++6"}  # in debian:12-slim (apt needs them)


def needed_libraries(binary):
    out = subprocess.run(["readelf", "-d", binary], check=True, capture_output=True, text=True).stdout
    return re.findall(r"\(NEEDED\)\s+Shared library: \[([^\]]+)\]", out)


def resolved_paths(binary):
    out = subprocess.run(["ldd", binary], check=True, capture_output=True, text=True).stdout
    paths = {}
    for line in out.splitlines():
        m = re.match(r"\s*(\S+) => (\S+)", line)
        if m:
            paths[m.group(1)] = m.group(2)
    return paths


def package_of(path):
    # usrmerge: dpkg may know the file under /lib or /usr/lib, and by its link name or its target.
    candidates = []
    for p in (path, os.path.realpath(path)):
        candidates += [p, p.replace("/usr/lib/", "/lib/", 1), p.replace("/lib/", "/usr/lib/", 1)]
    for c in dict.fromkeys(candidates):
        r = subprocess.run(["dpkg", "-S", c], capture_output=True, text=True)
        if r.returncode == 0:
            return r.stdout.split(":")[0].strip()
    return None


def parse_dockerfile(path):
    text = open(path, encoding="utf-8").read()
    joined = re.sub(r"\\\n", "", text)  # line continuations
    stages = re.findall(r"^FROM\s+(\S+)(?:\s+AS\s+(\S+))?", joined, flags=re.M | re.I)
    last_stage = joined[[m.start() for m in re.finditer(r"^FROM\s", joined, flags=re.M | re.I)][-1]:]
    users = re.findall(r"^USER\s+(\S+)", last_stage, flags=re.M)
    m = re.search(r'^ARG\s+RUNTIME_PACKAGES="([^"]*)"', last_stage, flags=re.M)
    packages = set(m.group(1).split()) if m else None
    installs_it = "${RUNTIME_PACKAGES}" in last_stage or "$RUNTIME_PACKAGES" in last_stage
    return stages, users, packages, installs_it


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dockerfile", required=True)
    ap.add_argument("--binary", action="append", required=True)
    args = ap.parse_args()

    problems = []
    stages, users, listed, installs_it = parse_dockerfile(args.dockerfile)
    if len(stages) < 2:
        problems.append(f"{len(stages)} FROM stage(s): build in one stage and run in another")
    for image, _ in stages:
        if not re.fullmatch(r"debian:12(\.\d+)?(-slim)?", image):
            problems.append(f"base image '{image}': pin a Debian 12 release (debian:12.N or debian:12.N-slim)")
    if not users:
        problems.append("the runtime stage has no USER: it would run as root")
    elif not re.fullmatch(r"[1-9][0-9]*(:[1-9][0-9]*)?", users[-1]):
        problems.append(f"USER {users[-1]}: use a numeric non-root uid[:gid], so that runAsNonRoot can verify it")
    if listed is None or not installs_it:
        problems.append("the runtime stage must declare ARG RUNTIME_PACKAGES=\"...\" and apt-get install it")
        listed = set()

    needed = {}
    for binary in args.binary:
        paths = resolved_paths(binary)
        for lib in needed_libraries(binary):
            if lib not in paths or paths[lib] == "not":
                problems.append(f"{os.path.basename(binary)} needs {lib}, which ldd cannot resolve")
                continue
            package = package_of(paths[lib])
            if package is None:
                problems.append(f"{os.path.basename(binary)}: no Debian package holds {paths[lib]} ({lib})")
                continue
            needed.setdefault(package, set()).add(f"{os.path.basename(binary)}:{lib}")
    required = set(needed) - BASE_IMAGE_PACKAGES
    for p in sorted(required - listed):
        problems.append(f"RUNTIME_PACKAGES lacks {p} (for {', '.join(sorted(needed[p]))})")
    for p in sorted(listed - required):
        problems.append(f"RUNTIME_PACKAGES lists {p}, which no shipped binary links")

    name = os.path.basename(args.dockerfile)
    print(f"{name}: {len(stages)} stages, USER {users[-1] if users else '-'}, {len(listed)} runtime packages, "
          f"{len(required)} needed by {len(args.binary)} binaries")
    for p in problems:
        print(f"  problem: {p}")
    print(f"{name}: {'ok' if not problems else str(len(problems)) + ' problem(s)'}")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
