#!/usr/bin/env bash
# Runs the cooperative-matrix tests (`LayerKernels::CoopF16`) against the f64 reference on a
# CPU: Mesa's lavapipe has f16 cooperative matrices (8 × 8 tiles) from Mesa 25.1 on, and
# Debian 12's Mesa 22.3 has none. This builds the SIREN GPU test binary here, installs a
# Debian 13 root with the Mesa of trixie-backports (once; about 300 MB under DIR, default
# target/coop-root, ignored by git), and runs the tests whose names contain `coop` inside it,
# with HWSDF_REQUIRE_COOP=1 so that a driver without cooperative matrices fails instead of
# skipping; then the GEMM's wide-layer test (`wide_layers`), which this newer driver computes
# right and Mesa 22.3 wrong, and the tiled GEMM's register blocks (`tiled_register_blocks`:
# their workgroup tiles are sized by pipeline overrides, a second compiler checks them). CI runs
# it after `cargo test`. Needs root (or sudo) and Debian's mirror.
#
#   scripts/coop-check.sh [DIR]
set -euo pipefail
cd "$(dirname "$0")/.."
root=${1:-target/coop-root}
mirror=http://deb.debian.org/debian
SUDO=""
[ "$(id -u)" -ne 0 ] && SUDO="sudo"

if [ ! -e "$root/.ready" ]; then
    if ! command -v debootstrap >/dev/null; then
        echo "== installing debootstrap"
        $SUDO apt-get update -qq
        DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq debootstrap >/dev/null
    fi
    echo "== a Debian 13 root with trixie-backports' Mesa in $root"
    $SUDO rm -rf "$root"
    mkdir -p "$(dirname "$root")"
    $SUDO debootstrap --variant=minbase trixie "$root" "$mirror" >"$root.log" 2>&1 \
        || { tail -20 "$root.log" >&2; exit 1; }
    echo "deb $mirror trixie-backports main" | $SUDO tee "$root/etc/apt/sources.list.d/backports.list" >/dev/null
    # apt's "Can not write log (Is /dev/pts mounted?)" is harmless here: into the log with the rest.
    { $SUDO chroot "$root" apt-get update -qq \
        && $SUDO chroot "$root" env DEBIAN_FRONTEND=noninteractive \
            apt-get install -y -qq -t trixie-backports mesa-vulkan-drivers libvulkan1; } \
        >>"$root.log" 2>&1 || { tail -20 "$root.log" >&2; exit 1; }
    $SUDO touch "$root/.ready"
fi

echo "== building the SIREN GPU tests"
# `--workspace`, not `-p sdf-nn`: the features then unify as in `cargo test --workspace`, whose
# binary CI has just built and this reuses; `-p sdf-nn` resolves other features and rebuilds
# sdf-nn and its dependencies (3.5 minutes of a CI run).
exe=$(cargo test -q --workspace --test siren_gpu --no-run --message-format=json 2>/dev/null \
    | python3 scripts/cargo_executables.py --name siren_gpu | cut -d' ' -f2-)
[ -n "$exe" ] || { echo "the siren_gpu test binary was not built" >&2; exit 1; }
$SUDO cp "$exe" "$root/tmp/siren_gpu"
$SUDO rm -rf "$root/tmp/data"
$SUDO cp -r tests/data "$root/tmp/data"
echo "== driver: $($SUDO chroot "$root" dpkg-query -W -f '${Package} ${Version}' mesa-vulkan-drivers)"
# The tests print the adapter at every step; the driver line above names it.
$SUDO chroot "$root" env HWSDF_REQUIRE_COOP=1 HWSDF_TEST_DATA=/tmp/data /tmp/siren_gpu coop --nocapture 2>&1 \
    | grep -v 'XDG_RUNTIME_DIR\|^adapter: '
# The GEMM's wide layers: Debian 12's Mesa 22.3 computes them wrong (the test expects the typed
# refusal there), Mesa 26.1 right (the test expects them to match the f64 reference here).
$SUDO chroot "$root" env HWSDF_TEST_DATA=/tmp/data /tmp/siren_gpu wide_layers 2>&1 \
    | grep -v 'XDG_RUNTIME_DIR\|^adapter: '
# Every register block of the tiled GEMM against the f64 reference on the newer compiler.
$SUDO chroot "$root" env HWSDF_TEST_DATA=/tmp/data /tmp/siren_gpu tiled_register_blocks 2>&1 \
    | grep -v 'XDG_RUNTIME_DIR\|^adapter: '
