#!/usr/bin/env bash
# Fetch the real glTF 2.0 assets that benchmarks.assets.kept_layout measures (Khronos sample models and
# others, as their authors published them, not converted) from the Debian archive's source tarballs,
# each checked against its SHA-256; only the models' own files are unpacked. Licences:
# benchmarks/SOURCES.md. TANGO_DEBIAN_POOL overrides the archive (a local mirror: a folder or URL
# holding the same pool paths).
#
#     bash scripts/fetch_gltf_assets.sh [build/gltf-assets]
set -euo pipefail
out=$(realpath -m "${1:-build/gltf-assets}")
pool=${TANGO_DEBIAN_POOL:-http://deb.debian.org/debian/pool/main}
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
mkdir -p "$out"

fetch() { # pool path, sha256 -> the tarball in $work
  local file="$work/$(basename "$1")"
  if [[ "$pool" == http* ]]; then
    curl -fsSL --retry 3 -o "$file" "$pool/$1"
  else
    cp "$pool/$1" "$file"
  fi
  echo "$2  $file" | sha256sum -c --quiet - >/dev/null 2>&1 || { echo "$(basename "$1"): checksum mismatch (not the tarball this script pins)" >&2; exit 1; }
  echo "$file"
}

unpack() { # tarball, destination folder name, member paths (glob patterns)...
  local tarball=$1 dest=$out/$2
  shift 2
  rm -rf "$dest" && mkdir -p "$dest"
  tar -xf "$tarball" -C "$dest" --wildcards --strip-components="${STRIP:-0}" "$@"
}

draco=$(fetch d/draco/draco_1.5.5+dfsg.orig.tar.xz 0d4ff5b218a2f9d836c6f44202918402591407b5f59a5103ec288c5600ab087f)
d=google-draco-a5b3157/testdata
STRIP=4 unpack "$draco" cesium-man "$d/CesiumMan/glTF/*"
STRIP=4 unpack "$draco" fox "$d/Fox/glTF/*"
STRIP=4 unpack "$draco" milk-truck "$d/CesiumMilkTruck/glTF/*"
STRIP=5 unpack "$draco" duck "$d/KhronosSampleModels/Duck/glTF/*"
STRIP=5 unpack "$draco" morph-cube "$d/KhronosSampleModels/AnimatedMorphCube/glTF/*"
trimesh=$(fetch t/trimesh/trimesh_4.5.1.orig.tar.gz bbfb88ddf4f35acbf9749cb9532270b892c886fc4fcc17b851f9277188ddd046)
STRIP=2 unpack "$trimesh" box-textured trimesh-4.5.1/models/BoxTextured.glb
STRIP=2 unpack "$trimesh" test-scene trimesh-4.5.1/models/TestScene.gltf trimesh-4.5.1/models/TestScene.bin
luanti=$(fetch l/luanti/luanti_5.10.0+dfsg.orig.tar.xz 76f3d212b69c9591f9d7a7b7eeb699d7ec00afe2c2bfb3654081f50d58707937)
STRIP=6 unpack "$luanti" spider luanti-5.10.0/games/devtest/mods/gltf/models/gltf_spider_animated.gltf
tinygltf=$(fetch t/tinygltf/tinygltf_2.7.0+dfsg.orig.tar.xz d55bdecdc258be72041da3d7f5c8fd9faa0a93ad6cb42ff6893c82be713626d2)
STRIP=3 unpack "$tinygltf" sparse-morph "tinygltf-2.7.0/models/SparseMorphTargets-issue280/singleBlendshapeCube_sparse.glb"
find "$out" -name "*.gl[tb]*" | sort
