#!/usr/bin/env bash
# Node tools the tests use: the Khronos glTF validator (npm package gltf-validator), put in
# tools/node/ (git-ignored). Does nothing when that version is already there.
set -euo pipefail
cd "$(dirname "$0")"
version="2.0.0-dev.3.10"
installed="node/node_modules/gltf-validator/package.json"
if [ -f "$installed" ] && grep -q "\"version\": \"$version\"" "$installed"; then
  exit 0
fi
command -v npm >/dev/null || { echo "npm is missing: install Node.js 18 or later (with npm)" >&2; exit 1; }
echo "installing gltf-validator@$version into tools/node/"
npm install --silent --no-audit --no-fund --no-save --prefix node "gltf-validator@$version" >/dev/null
