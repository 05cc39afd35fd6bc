#!/usr/bin/env bash
# Runs the tests of the one-point- and one-row-per-subgroup kernels at subgroup widths other
# than lavapipe's 8: 4 and 16 lanes.
#
# Those kernels split one point's (or one training row's) work by the subgroup's width: lanes
# 8g..8g+7 take the corners of the levels l with l % (width / 8) == g, a width under 8 loops
# over the corners, each lane takes every width-th hidden unit. GPUs run 32 or 64 lanes (4 or 8
# groups of levels), lavapipe runs 8 (one group), so the split across groups never ran before a
# GPU did. lavapipe's LP_NATIVE_VECTOR_WIDTH sets its width: 128 bits give 4 lanes, 512 give
# 16 (two groups: levels alternate, and a 5-level grid has more levels than groups, as a
# 16-level hash grid has on a 32-lane GPU). Wider settings are no use: Mesa 22.3 and 26.1 both
# report 32 or 64 lanes for 1024 or 2048 bits but run 16 to a subgroup, so a kernel that
# trusts `subgroup_size` skips half its work (a probe summed lane + 1 to 136 with 32 reported).
#
# The tests are those whose names say they run the subgroup kernels: `subgroup` or
# `both_kernels` in the name (keep that convention when adding one). CI runs this after
# `cargo test --workspace`, whose build it reuses (`--workspace`: the same features).
#
#   scripts/subgroup-widths.sh
set -euo pipefail
cd "$(dirname "$0")/.."
bin="${CARGO_TARGET_DIR:-$PWD/target}/debug"
# lavapipe even where a GPU is the default adapter: only lavapipe reads the variable.
export HWSDF_ADAPTER=${HWSDF_ADAPTER:-llvmpipe}
# The tests that pin the subgroup kernels, as counted on 2026-11-28: one in sdf-nn's library,
# four in `scene`, one in `nglod`. Fewer means a filter or a name drifted.
expected=6
log=$(mktemp)
trap 'rm -f "$log"' EXIT
for bits in 128 512; do
    lanes=$((bits / 32))
    echo "== subgroups of $lanes lanes (LP_NATIVE_VECTOR_WIDTH=$bits)"
    # A driver that ignores the variable would test nothing new.
    info=$(LP_NATIVE_VECTOR_WIDTH=$bits "$bin/gpu-info" 2>&1) \
        || { echo "gpu-info failed (HWSDF_ADAPTER=$HWSDF_ADAPTER): $info" >&2; exit 1; }
    if ! grep -q "subgroup size: $lanes\.\.$lanes," <<<"$info"; then
        echo "the adapter does not run subgroups of $lanes lanes with LP_NATIVE_VECTOR_WIDTH=$bits:" >&2
        grep -i "adapter\|subgroup" <<<"$info" >&2 || echo "$info" >&2
        exit 1
    fi
    LP_NATIVE_VECTOR_WIDTH=$bits cargo test -q --workspace --lib --test scene --test nglod \
        -- subgroup both_kernels 2>&1 | tee "$log"
    ran=$(grep -E '^test result: ok\.' "$log" | awk '{ n += $4 } END { print n + 0 }')
    if [ "$ran" -lt "$expected" ]; then
        echo "only $ran subgroup-kernel tests ran at $lanes lanes (expected $expected)" >&2
        exit 1
    fi
done
