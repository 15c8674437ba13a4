#!/usr/bin/env bash
# Rebuilds three_bundle.js (committed: the package ships it, nothing is built at
# install and the pages it goes into open offline). Needs node and npm.
set -euo pipefail
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
WORK="$(mktemp -d)"
trap 'rm -rf "$WORK"' EXIT
cd "$WORK"
npm init -y > /dev/null
npm install --no-audit --no-fund three@0.170.0 esbuild@0.28 > /dev/null
cp "$HERE/bundle_entry.js" entry.js
npx esbuild entry.js --bundle --minify --format=iife --outfile=bundle.js
{
  printf '/* three.js r170 (three, GLTFLoader, OrbitControls, RoomEnvironment), MIT License,\n'
  printf '   Copyright 2010-2024 three.js authors: https://github.com/mrdoob/three.js/blob/r170/LICENSE\n'
  printf '   Bundled by pipeline/viewer/build_bundle.sh; the pipeline loads it as window.THREE_VIEWER. */\n'
  cat bundle.js
} > "$HERE/three_bundle.js"
