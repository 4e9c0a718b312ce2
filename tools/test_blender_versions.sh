#!/usr/bin/env bash
# Run the Blender add-on's tests (tests/test_addon_*.py) on other Blender versions: each
# as the bpy module from PyPI, in its own virtual environment outside the repository.
#
#   tools/test_blender_versions.sh [BPY_VERSION ...] [-- PYTEST_ARGS ...]
#   tools/test_blender_versions.sh                    # 4.2.0, the oldest Blender supported
#   tools/test_blender_versions.sh 4.2.0 4.3.0 4.5.15 -- -x
#
# Environments live in $DIFFSHEG_BPY_CACHE (default ~/.cache/diffsheg/bpy), one per version,
# made on first use (a bpy wheel is about 350 MB) and brought up to date on every run.
# They hold bpy, the torch pinned in requirements.txt, the core's dependencies from
# pyproject.toml and pytest; the tests import the add-on and the core from this checkout.
# The bpy wheels are built for CPython 3.11 only: PYTHON names the interpreter (python3.11).
# Exit status: 0 when every version passed.
set -euo pipefail

REPO="$(cd "$(dirname "$0")/.." && pwd)"
CACHE="${DIFFSHEG_BPY_CACHE:-${XDG_CACHE_HOME:-$HOME/.cache}/diffsheg/bpy}"
PYTHON="${PYTHON:-python3.11}"

versions=()
while [ $# -gt 0 ] && [ "$1" != "--" ]; do
  versions+=("$1")
  shift
done
[ "${1:-}" = "--" ] && shift
[ "${#versions[@]}" -eq 0 ] && versions=(4.2.0)

if ! "$PYTHON" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' 2>/dev/null; then
  echo "test_blender_versions: $PYTHON is not CPython 3.11, the only Python the bpy wheels are built for;" \
       "set PYTHON=/path/to/python3.11" >&2
  exit 2
fi

# The core's dependencies (pyproject.toml) with torch as pinned for CI (requirements.txt).
mapfile -t requirements < <("$PYTHON" - "$REPO" <<'EOF'
import re, sys, tomllib
from pathlib import Path

repo = Path(sys.argv[1])
deps = tomllib.loads((repo / "pyproject.toml").read_text())["project"]["dependencies"]
pins = {}
for line in (repo / "requirements.txt").read_text().splitlines():
    m = re.match(r"([A-Za-z0-9_.-]+)==", line.strip())
    if m:
        pins[m.group(1).lower()] = line.strip()
for dep in deps:
    name = re.match(r"[A-Za-z0-9_.-]+", dep).group(0).lower()
    print(pins.get(name, dep))
EOF
)

failed=()
for version in "${versions[@]}"; do
  venv="$CACHE/bpy-$version"
  echo "=== bpy $version ($venv)"
  if [ ! -x "$venv/bin/python" ]; then
    mkdir -p "$CACHE"
    "$PYTHON" -m venv "$venv"
  fi
  # Blender 4.2-5.0 ship numpy 1.26; the 4.2-4.3 wheels do not say so.
  if ! "$venv/bin/python" -m pip install -q --disable-pip-version-check \
      "bpy==$version" "numpy>=1.26,<2" "${requirements[@]}" "pytest>=8"; then
    echo "test_blender_versions: could not install bpy $version (see pip's message above)" >&2
    failed+=("$version (install)")
    continue
  fi
  start=$SECONDS
  if (cd "$REPO" && "$venv/bin/python" -m pytest -q -p no:cacheprovider tests/test_addon_*.py "$@"); then
    echo "=== bpy $version: passed in $((SECONDS - start)) s"
  else
    echo "=== bpy $version: FAILED after $((SECONDS - start)) s"
    failed+=("$version")
  fi
done

if [ "${#failed[@]}" -gt 0 ]; then
  echo "test_blender_versions: failed on bpy ${failed[*]}" >&2
  exit 1
fi
echo "test_blender_versions: passed on bpy ${versions[*]}"
