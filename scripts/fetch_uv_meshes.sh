#!/usr/bin/env bash
# Fetch the UV-mapped meshes that benchmarks.assets.kept_layout measures besides ../shared/meshes/spot.obj,
# from Debian's assimp-testmodels package (assimp 5.2.5), converted to GLB with Debian's own assimp
# command-line tool; nothing is installed (the packages are unpacked into the target folder).
# Licences: benchmarks/SOURCES.md.
#
#     bash scripts/fetch_uv_meshes.sh [build/uv-meshes]
set -euo pipefail
out=$(realpath -m "${1:-build/uv-meshes}")
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
mkdir -p "$out"
cd "$work"
apt-get download assimp-testmodels assimp-utils libassimp5 libdraco7 >/dev/null
for deb in *.deb; do dpkg-deb -x "$deb" root; done
export LD_LIBRARY_PATH=$work/root/usr/lib/x86_64-linux-gnu
models=$work/root/usr/share/assimp/models
convert() { # model file, output name
  "$work/root/usr/bin/assimp" export "$models/$1" "$out/$2" -fglb2 >/dev/null
  echo "$out/$2"
}
convert Collada/duck.dae duck.glb
convert glTF/CesiumMilkTruck/CesiumMilkTruck.gltf milktruck.glb
convert MS3D/jeep1.ms3d jeep.glb
