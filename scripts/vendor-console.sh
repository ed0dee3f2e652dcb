#!/usr/bin/env bash
# Rebuild console/vendor/viewer.js, the web console's 3D viewer, from registry packages.
#
# Installs the pinned `three` and `esbuild` npm packages into a temporary folder (the npm registry
# is the only network access), bundles console/viewer-entry.js (the three.js classes the avatar
# view uses, GLTFLoader and OrbitControls) into one minified ES module, and writes
# console/vendor/PROVENANCE.md with the package versions, the sha256 of the registry tarballs and
# of the bundle, and the licence. The bundle is committed; the server embeds it at build time.
#
#   scripts/vendor-console.sh
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

THREE_VERSION=0.187.0
ESBUILD_VERSION=0.25.12

tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
root="$PWD"
(
    cd "$tmp"
    npm init -y >/dev/null
    npm install --no-audit --no-fund --save-exact "three@$THREE_VERSION" "esbuild@$ESBUILD_VERSION" >/dev/null
    npm pack --silent "three@$THREE_VERSION" >/dev/null
    cp "$root/console/viewer-entry.js" entry.js
    npx --no-install esbuild entry.js --bundle --minify --format=esm --target=es2020 --legal-comments=none \
        --outfile=viewer.js --log-level=warning
)
mkdir -p console/vendor
{
    echo "/* three.js $THREE_VERSION (https://threejs.org), MIT licence: see console/vendor/LICENSE-three.txt."
    echo "   Bundled by scripts/vendor-console.sh from console/viewer-entry.js with esbuild $ESBUILD_VERSION. */"
    cat "$tmp/viewer.js"
} >console/vendor/viewer.js
cp "$tmp/node_modules/three/LICENSE" console/vendor/LICENSE-three.txt
tarball_sha="$(sha256sum "$tmp/three-$THREE_VERSION.tgz" | cut -d' ' -f1)"
bundle_sha="$(sha256sum console/vendor/viewer.js | cut -d' ' -f1)"
cat >console/vendor/PROVENANCE.md <<MD
# console/vendor

| file | from | licence |
| --- | --- | --- |
| \`viewer.js\` | npm \`three@$THREE_VERSION\` (tarball sha256 \`$tarball_sha\`): \`three\`, \`three/addons/loaders/GLTFLoader.js\`, \`three/addons/controls/OrbitControls.js\` as listed in \`console/viewer-entry.js\`, bundled and minified with npm \`esbuild@$ESBUILD_VERSION\` | MIT (\`LICENSE-three.txt\`) |

\`viewer.js\` sha256: \`$bundle_sha\`. Regenerate with \`scripts/vendor-console.sh\` (needs node, npm and the npm
registry); the server embeds the committed file at build time and loads nothing from the network.
MD
echo "console/vendor/viewer.js: $(wc -c <console/vendor/viewer.js) bytes, sha256 $bundle_sha"
