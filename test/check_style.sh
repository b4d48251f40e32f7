#!/usr/bin/env bash
# The house style, checked: every tracked C++ file formatted as .clang-format says, and, with --tidy, clang-tidy
# (.clang-tidy) on the C++ files a change touches.
#
#   test/check_style.sh                 # formatting of every tracked .cpp/.hpp/.h (a few seconds)
#   test/check_style.sh --fix           # reformat them in place
#   test/check_style.sh --tidy [BASE]   # also clang-tidy on the .cpp files changed since BASE (default origin/main,
#                                       # else main), with build/default/compile_commands.json
#
# Exits 1 and names each file that fails. test/run_tests.sh runs the formatting check, so CI fails on it.
set -euo pipefail
repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$repo"
fix=0
tidy=0
base=
while [ $# -gt 0 ]; do
  case "$1" in
    --fix) fix=1; shift ;;
    --tidy)
      tidy=1; shift
      if [ $# -gt 0 ] && [ "${1#-}" = "$1" ]; then base=$1; shift; fi ;;
    -h|--help) sed -n '2,10p' "$0"; exit 0 ;;
    *) echo "check_style: unknown argument '$1' (see --help)" >&2; exit 2 ;;
  esac
done
for tool in clang-format clang-tidy; do
  command -v "$tool" >/dev/null || { echo "check_style: $tool is missing; run deploy/install_deps.sh" >&2; exit 2; }
done

mapfile -t files < <(git ls-files '*.cpp' '*.hpp' '*.h')
if [ "$fix" = 1 ]; then
  clang-format -i "${files[@]}"
  echo "check_style: reformatted ${#files[@]} files"
  exit 0
fi
status=0
mapfile -t unformatted < <(for f in "${files[@]}"; do
  clang-format --dry-run --Werror "$f" >/dev/null 2>&1 || echo "$f"
done)
if [ "${#unformatted[@]}" -gt 0 ]; then
  echo "check_style: ${#unformatted[@]} of ${#files[@]} files are not formatted (fix: test/check_style.sh --fix):" >&2
  printf '  %s\n' "${unformatted[@]}" >&2
  status=1
else
  echo "check_style: all ${#files[@]} C++ files formatted"
fi

if [ "$tidy" = 1 ]; then
  if [ -z "$base" ]; then
    base=main
    git rev-parse -q --verify origin/main >/dev/null && base=origin/main
  fi
  db=build/default/compile_commands.json
  [ -f "$db" ] || { echo "check_style: $db is missing; configure the default preset first" >&2; exit 2; }
  mapfile -t changed < <(git diff --name-only --diff-filter=d "$base" -- '*.cpp' | grep -v '^test/fuzz/' || true)
  if [ "${#changed[@]}" -eq 0 ]; then
    echo "check_style: no .cpp file changed since $base"
  else
    echo "check_style: clang-tidy on ${#changed[@]} file(s) changed since $base"
    for f in "${changed[@]}"; do
      clang-tidy -p build/default --quiet --extra-arg=-Wno-unknown-warning-option "$f" 2>/dev/null || { echo "  clang-tidy: $f has findings" >&2; status=1; }
    done
  fi
fi
exit "$status"
