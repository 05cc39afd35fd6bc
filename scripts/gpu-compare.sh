#!/usr/bin/env bash
# One table of our kernels against PyTorch on a GPU host that has no Rust toolchain.
#
#   scripts/gpu-compare.sh pack [DIR]   # here, with cargo: release benches + binaries into DIR
#   scripts/gpu-compare.sh run  [DIR]   # on the GPU host, with python3 (+ torch for the peer)
#
# DIR defaults to out/gpu-pack (ignored by git). `pack` builds the criterion bench executables
# (`cargo bench --no-run`) and the release binaries, strips them, and copies those the stages
# of GPU_COMPARE_STAGES use (all by default: set it at pack time to stay under a lent machine's
# 64 MiB) with tests/data (the benches open tests/data/spot.obj by a relative path), the PyTorch scripts and
# this script, and archives the folder as DIR.tar.gz. With GPU_COMPARE_DEBS=1 it also downloads
# Debian's amd64 Vulkan loader and glvnd packages into DIR/debs, for a host without them (`run`
# unpacks them as root). Copy DIR (or
# the archive) to the host, then `bash DIR/gpu-compare.sh run DIR`.
#
# `run` finds the Vulkan loader (or unpacks DIR/debs/*.deb as root, or says how to get one),
# prints the adapter, first runs every packed kernel test binary against its CPU and f64
# references on it (the `checks` stage: the table says whether they passed), runs our benches (siren, nglod, and any other packed bench whose name
# starts with `query`) with criterion's results under DIR/results/criterion, runs the PyTorch
# scripts for both presets, and prints one Markdown table of ours against PyTorch eager (and
# torch.compile where it works) with the ratios. The table is also written to
# DIR/results/table.md, next to every raw log (and, at its end, issue 37's and 38's targets
# beside the scene bench, the ground truth and the step profiles). It then times whole fits with `train` on
# tests/data/spot.obj (issue 14's "100 epochs of NGLOD `default`", issue 12's "a default SIREN
# fit", whose model `eval` then scores and times on the f32 kernels and on cooperative matrices)
# and, when the pack holds meshes, runs `corpus` over them (issue 14's F1 averages), and
# appends both to the table. Where the adapter has f16 cooperative matrices (`gpu-info` says
# so), the `coop` stage runs their test against the f64 reference (the packed siren_gpu test
# binary, HWSDF_REQUIRE_COOP=1) and the SIREN eval bench on them (SIREN_BENCH_KERNELS=coop,
# criterion's results under DIR/results/criterion-coop), and adds their rows; it also times SIREN
# queries through NeuralSdf on them (the query bench, QUERY_BENCH_SIREN_KERNELS=coop, at 10, 3000
# and 50 000 points; DIR/results/query-coop.txt). The `blocks` stage
# runs the SIREN `default` bench on the tiled kernels once per forced register block of the
# tiled GEMM (SIREN_BENCH_TILED_BLOCK; results under DIR/results/criterion-block-*), the figures
# that set `TiledBlock::Auto`'s rule on GPUs, and the eval bench with the fused kernel's 2 and
# 3 register blocks of rows per invocation (SIREN_BENCH_FUSED_ROW_BLOCKS; criterion-rows-*),
# which decide its default, and adds their rows. The `split` stage runs the
# query bench interleaved (QUERY_BENCH_INTERLEAVED): a query's wall time split into the empty
# round trip, the upload, one launch and the kernel, for NGLOD and SIREN `small` and `default`
# (issue 13: what SIREN's wall path adds to its kernel time); its log is
# DIR/results/query-split.txt. The `phases` stage times one mapped query phase by phase
# (QUERY_BENCH_PHASES: map, write, encode, submit, wait, read; a blocking wait; a command buffer
# encoded during the previous wait; the GPU span on mapped and device-local buffers), NGLOD and
# SIREN `default` at 10, 3000 and 50 000 points; DIR/results/query-phases.txt. The `profile` stage prints where a SIREN `default` training step's
# time goes, launch by launch, from GPU timestamps (SIREN_BENCH_PROFILE; issue 12's ≤ 2 ms per
# step); its log is DIR/results/siren-profile.txt. It then does the same for NGLOD and the
# hash grid's `default` (NGLOD_BENCH_PROFILE: each launch of a step, and of the GPU draw, with
# one row per invocation and per subgroup, beside the measured epoch; issue 38's ≤ 15 ms per
# epoch), DIR/results/nglod-profile.txt. Environment:
#   GPU_COMPARE_PRESETS=small,default   presets to run (both by default)
#   GPU_COMPARE_STAGES=checks,bench,kernels,coop,blocks,split,phases,profile,torch,fit,scene,groundtruth,hashgrid,corpus
#                                       what to run (default all; split a session's runs with it).
#                                       `kernels` runs the query bench's NGLOD and hash-grid
#                                       rows once per query kernel (HWSDF_QUERY_KERNEL=invocation
#                                       and subgroup, 10, 3000, 50 000 and 10^6 points;
#                                       DIR/results/query-kernel-*.txt), which decides the
#                                       GPU default (issue 39's ≤ 60 µs per 3000);
#                                       `scene` runs benches/scene (issue 37's targets, with the
#                                       fit stage's NGLOD model when it ran; both query kernels
#                                       side by side); `groundtruth` the
#                                       ground_truth_bench example: GPU against CPU labels on
#                                       spot and on armadillo split to 1.4 M triangles (needs
#                                       GPU_COMPARE_MESHES at pack time; else spot twice);
#                                       `hashgrid` the grid_sweep example: hash-grid candidates
#                                       for its default beside NGLOD, each for the same seconds
#                                       (GPU_COMPARE_SWEEP_SECONDS=1; GPU_COMPARE_SWEEP= the
#                                       specs, see crates/sdf-eval/examples/grid_sweep.rs), on
#                                       spot and the packed CAD-like meshes
#   GPU_COMPARE_BLOCKS=                 register blocks of the tiled GEMM the `blocks` stage
#                                       forces (e.g. 4x4,8x8; none by default: session 13's
#                                       H100 run set TiledBlock::Auto's rule)
#   GPU_COMPARE_ROW_BLOCKS=2,3          the fused kernel's row blocks it forces too
#   GPU_COMPARE_SPLIT_ROUNDS=500        rounds of the `split` and `phases` stages' query benches
#   GPU_COMPARE_CHECK_TIMEOUT=300       seconds each kernel test binary may take (`checks`)
#   GPU_COMPARE_CHECKS=                 (pack) the `checks` stage's test binaries, comma-separated
#                                       (default all twelve; see GPU_CHECKS below)
#   GPU_COMPARE_FITS=nglod,nglod-fresh,nglod-invocation,nglod-batch4096,hashgrid,hashgrid-small,siren,siren-design-loss,siren-constant-lr
#                                       which fits the `fit` stage times (default all nine:
#                                       NGLOD about 10 s on an H100 (nglod-fresh with
#                                       --pool 1,1, fresh points every epoch, the GPU source
#                                       before session 32's pool; nglod-invocation with
#                                       HWSDF_TRAIN_KERNEL=invocation, nglod-batch4096 with
#                                       --batch 4096 --lr 0.0014), the hash grid's presets
#                                       (issue 39: ≤ 1 s of training), SIREN about 30 s each;
#                                       siren-design-loss is SIREN with --sign-weight 0, the
#                                       design document's four loss terms alone,
#                                       siren-constant-lr SIREN with --plateau-patience 0, a
#                                       constant learning rate)
#   GPU_COMPARE_MESHES=DIR              (pack) copy DIR's meshes into the pack for `corpus`
#   GPU_COMPARE_CORPUS_ARGS="..."       extra `corpus` arguments (default: --model nglod); each
#                                       set keeps its own results (e.g. add --band-cells 0)
#   GPU_COMPARE_TIMEOUT=240             seconds each fit and the corpus run may take (a lent
#                                       machine's calls are limited; corpus resumes where a
#                                       run stopped, so a second call finishes it)
#   GPU_COMPARE_RESULTS=DIR             where the logs, criterion's results and the table go
#                                       (default DIR/results, cleared first; a folder named
#                                       here must be new or empty). Point it at the
#                                       folder a lent machine sends back, so that a call cut
#                                       off by its time limit still returns what it measured
#   GPU_COMPARE_ALLOW_CPU=1             run even if the adapter is a CPU (lavapipe): a dry run
#   GPU_COMPARE_SKIP_TORCH=1            only our side (same as leaving `torch` out of the stages)
#   any variable the benches read (SIREN_BENCH_*, NGLOD_BENCH_EPOCHS, WGPU_ADAPTER_NAME, ...)
#
# A lent machine has minutes, not hours: pick the stages (they run in the order of ALL_STAGES
# below), stop the run before the call's limit, and pack the results into one file of the
# folder that comes back (at most 8 files come back; the models stay):
#   GPU_COMPARE_RESULTS=/tmp/res GPU_COMPARE_STAGES=checks,groundtruth,scene,profile,fit \
#       timeout 540 bash gpu-compare.sh run .; tar czf $OUT/results.tgz --exclude='*.safetensors' -C /tmp res
# and leave `corpus` (about 3 minutes on an H100) for a call of its own. On a GPU the SIREN
# bench samples 3 s per figure (20 s on lavapipe).
set -euo pipefail

# The `checks` stage's test binaries (target names), all by default; GPU_COMPARE_CHECKS (a
# comma-separated subset, at pack time) packs fewer: each is 6-9 MB, 2-3 MB compressed.
GPU_CHECKS="siren_gpu|nglod|adam|embed|render|gpu_timer|neural_sdf|serve_queries|scene|ground_truth|ground_truth_sample|nglod_gpu_points"
if [ -n "${GPU_COMPARE_CHECKS:-}" ]; then
    GPU_CHECKS=${GPU_COMPARE_CHECKS//,/|}
fi
# Every stage, in the order `run` runs them: the default of GPU_COMPARE_STAGES.
ALL_STAGES=checks,bench,kernels,coop,blocks,split,phases,profile,torch,fit,scene,groundtruth,hashgrid,corpus

usage() {
    awk 'NR > 1 && !/^#/ { exit } NR > 1 { sub(/^# ?/, ""); print }' "$0"
    exit 2
}

cmd=${1:-}
[ -n "$cmd" ] || usage
dir=${2:-}

pack() {
    local root
    root=$(cd "$(dirname "$0")/.." && pwd)
    dir=${dir:-$root/out/gpu-pack}
    mkdir -p "$dir"
    dir=$(cd "$dir" && pwd)
    cd "$root"
    command -v cargo >/dev/null || { echo "pack needs cargo (run it where the project builds)" >&2; exit 1; }
    echo "== building release binaries and bench executables"
    cargo build --release --bins
    cargo build --release -p sdf-nn --example ground_truth_bench --example nglod_sample_source
    cargo build --release -p sdf-eval --example grid_sweep
    cargo bench --no-run
    # The test binaries that run kernels against their CPU and f64 references (the `checks`
    # stage): sdf-nn's GPU tests, the query API's and the serving example's.
    local checks
    checks=$({
        cargo test --release -p sdf-nn --tests --no-run --message-format=json 2>/dev/null
        cargo test --release -p hwsdf --test neural_sdf --example serve_queries --no-run \
            --message-format=json 2>/dev/null
    } | python3 scripts/cargo_executables.py --kind test,example | grep -E "^($GPU_CHECKS) ")
    [ "$(wc -l <<<"$checks")" = "$(wc -w <<<"${GPU_CHECKS//|/ }")" ] \
        || { echo "not every kernel test binary was built ($GPU_CHECKS): $checks" >&2; exit 1; }
    local benches
    benches=$(cargo bench --no-run --message-format=json 2>/dev/null \
        | python3 scripts/cargo_executables.py --kind bench)
    [ -n "$benches" ] || { echo "no bench executables were built" >&2; exit 1; }
    rm -rf "$dir/bin" "$dir/benches" "$dir/tests" "$dir/scripts" "$dir/checks" "$dir/examples"
    mkdir -p "$dir/bin" "$dir/benches" "$dir/tests" "$dir/scripts" "$dir/checks" "$dir/examples"
    # Only what the stages to run (GPU_COMPARE_STAGES, as `run` reads it) use: a lent machine
    # carries at most 64 MiB, and everything packed is about 74 MiB compressed.
    local stages=",${GPU_COMPARE_STAGES:-$ALL_STAGES},"
    want() {
        local s
        for s in "$@"; do [[ $stages == *,$s,* ]] && return 0; done
        return 1
    }
    if want groundtruth; then
        cp target/release/examples/ground_truth_bench target/release/examples/nglod_sample_source \
            "$dir/examples/"
    fi
    if want hashgrid; then cp target/release/examples/grid_sweep "$dir/examples/"; fi
    local name path
    if want checks; then
        while read -r name path; do cp "$path" "$dir/checks/$name"; done <<<"$checks"
        # The example's trained models, which the scene and embed checks load (beside
        # tests/data, as HWSDF_TEST_DATA/../../examples/scene).
        mkdir -p "$dir/examples/scene"
        cp examples/scene/*.safetensors "$dir/examples/scene/"
    fi
    local exe exes=(gpu-info)
    if want fit; then exes+=(train eval); fi
    if want corpus; then exes+=(corpus); fi
    for exe in "${exes[@]}"; do
        cp "target/release/$exe" "$dir/bin/"
    done
    while read -r name path; do
        local keep=0
        case "$name" in
            siren) if want bench coop blocks profile; then keep=1; fi ;;
            nglod) if want bench profile; then keep=1; fi ;;
            query*) if want bench kernels coop split phases; then keep=1; fi ;;
            scene) if want scene; then keep=1; fi ;;
        esac
        if [ "$keep" = 1 ]; then cp "$path" "$dir/benches/$name"; fi
    done <<<"$benches"
    strip "$dir"/bin/* "$dir"/benches/* "$dir"/checks/* "$dir"/examples/* 2>/dev/null || true
    cp -r tests/data "$dir/tests/"
    # load_model.py for the neural_sdf check (beside tests/data, as HWSDF_TEST_DATA/../../scripts).
    cp scripts/siren_torch_bench.py scripts/nglod_torch_bench.py scripts/load_model.py "$dir/scripts/"
    cp scripts/gpu-compare.sh "$dir/"
    git rev-parse --short HEAD >"$dir/COMMIT" 2>/dev/null || echo unknown >"$dir/COMMIT"
    rm -rf "$dir/meshes"
    if [ -n "${GPU_COMPARE_MESHES:-}" ]; then
        echo "== copying the meshes of $GPU_COMPARE_MESHES"
        mkdir -p "$dir/meshes"
        find "$GPU_COMPARE_MESHES" -maxdepth 1 -type f \
            \( -name '*.obj' -o -name '*.gltf' -o -name '*.glb' -o -name '*.bin' -o -name '*.tsv' \) \
            -exec cp {} "$dir/meshes/" \;
    fi
    if [ "${GPU_COMPARE_DEBS:-0}" = 1 ]; then
        echo "== downloading Debian's amd64 Vulkan loader packages into $dir/debs"
        local o=(-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/gpu-compare-apt)
        mkdir -p /tmp/gpu-compare-apt/partial "$dir/debs"
        apt-get "${o[@]}" update -qq
        # The loader, and the glvnd libraries NVIDIA's Vulkan driver loads through (without them
        # the loader finds the driver's manifest but wgpu sees no adapter: session 19's H100).
        (cd "$dir/debs" && apt-get "${o[@]}" download libvulkan1 libegl1 libglvnd0 libopengl0 \
            libgl1 libglx0 libgles2)
    fi
    # One compressed file to carry (the folder is ~70 MB, the archive about a third of that).
    tar -C "$(dirname "$dir")" -czf "$dir.tar.gz" "$(basename "$dir")"
    echo "== packed $(du -sh "$dir" | cut -f1) into $dir, $(du -sh "$dir.tar.gz" | cut -f1) as $dir.tar.gz (commit $(cat "$dir/COMMIT"))"
    echo "   stages: ${GPU_COMPARE_STAGES:-$ALL_STAGES}; bin: $(ls "$dir/bin" | tr '\n' ' ')"
    echo "   benches: $(ls "$dir/benches" | tr '\n' ' '); checks: $(ls "$dir/checks" | tr '\n' ' ')"
    # A lent GPU machine takes at most 64 MiB in all: the archive and the repository's tracked
    # files travel together.
    local tree archive
    tree=$(git ls-files -z | xargs -0 du -cb 2>/dev/null | tail -1 | cut -f1)
    archive=$(stat -c %s "$dir.tar.gz")
    echo "   with the tracked files ($((tree / 1024 / 1024)) MiB): $(((archive + tree) / 1024 / 1024)) MiB to carry"
    if [ $((archive + tree)) -gt $((62 * 1024 * 1024)) ]; then
        echo "   warning: over 62 MiB with the tracked files; a lent machine carries at most 64 MiB in all:" \
            "pack fewer stages, or fewer check binaries (GPU_COMPARE_CHECKS)" >&2
    fi
    echo "   on the GPU host: tar xzf $(basename "$dir").tar.gz && bash $(basename "$dir")/gpu-compare.sh run $(basename "$dir")"
}

find_vulkan() {
    local debs=("$dir"/debs/*.deb "$dir"/../.gl/*.deb)
    local found=0 f
    for f in "${debs[@]}"; do [ -e "$f" ] && found=1; done
    # Whenever the pack has them (and we are root): a host may have the loader but not the
    # glvnd libraries the NVIDIA driver needs. `dpkg -x` only adds files.
    if [ "$found" = 1 ] && [ "$(id -u)" = 0 ]; then
        echo "== unpacking the packed Debian packages (Vulkan loader, glvnd)"
        for f in "${debs[@]}"; do [ -e "$f" ] && dpkg -x "$f" /; done
        ldconfig
    fi
    if ldconfig -p 2>/dev/null | grep 'libvulkan\.so\.1' >/dev/null; then
        return 0
    fi
    cat >&2 <<'EOF'
No Vulkan loader (libvulkan.so.1) on this host. Either install it
(apt-get install libvulkan1), or on the build machine run
`GPU_COMPARE_DEBS=1 scripts/gpu-compare.sh pack` and run this again as root, which unpacks
DIR/debs/*.deb into / (dpkg -x) and runs ldconfig.
EOF
    exit 1
}

find_icd() {
    # The NVIDIA container runtime mounts the driver (and its manifest) under /usr/local/nvidia,
    # which may be outside the loader's search path: name it where it exists (what session 19's
    # H100 and H200 runs needed, with the glvnd libraries).
    local icd
    for icd in /usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json /usr/local/nvidia/icd.d/nvidia_icd.json; do
        if [ -e "$icd" ]; then
            export VK_DRIVER_FILES=${VK_DRIVER_FILES:-$icd}
            # Loaders before 1.3.207 read only the older name.
            export VK_ICD_FILENAMES=${VK_ICD_FILENAMES:-$VK_DRIVER_FILES}
            echo "== using the Vulkan driver manifest $VK_DRIVER_FILES"
            return 0
        fi
    done
}

run() {
    dir=${dir:-$(dirname "$0")}
    dir=$(cd "$dir" && pwd)
    cd "$dir"
    [ -x bin/gpu-info ] || { echo "$dir holds no pack (run 'gpu-compare.sh pack' first)" >&2; exit 1; }
    find_vulkan
    find_icd
    local res
    if [ -n "${GPU_COMPARE_RESULTS:-}" ]; then
        # The caller's folder is never cleared: it must be new or empty.
        res=$GPU_COMPARE_RESULTS
        mkdir -p "$res"
        [ -z "$(ls -A "$res")" ] || { echo "GPU_COMPARE_RESULTS=$res is not empty" >&2; exit 1; }
    else
        res="$dir/results"
        rm -rf "$res"
        mkdir -p "$res"
    fi
    res=$(cd "$res" && pwd)
    echo "== adapter (commit $(cat COMMIT 2>/dev/null || echo unknown))"
    bin/gpu-info | tee "$res/gpu-info.txt"
    if grep -qi 'llvmpipe\|(Cpu,' "$res/gpu-info.txt" && [ "${GPU_COMPARE_ALLOW_CPU:-0}" != 1 ]; then
        echo "the selected adapter is a CPU; set WGPU_ADAPTER_NAME, or GPU_COMPARE_ALLOW_CPU=1 for a dry run" >&2
        exit 1
    fi
    export CRITERION_HOME="$res/criterion"
    export SIREN_BENCH_PRESETS=${GPU_COMPARE_PRESETS:-small,default}
    local stages=",${GPU_COMPARE_STAGES:-$ALL_STAGES},"
    if [[ $stages == *,checks,* ]]; then
        # Kernels designed on lavapipe meet a real GPU here: other subgroup sizes, real
        # parallelism within a workgroup, other limits. Figures from kernels that fail their
        # references are worth nothing, so these run first, and the table says how they went.
        echo "== checks: every kernel test binary against its CPU / f64 references on this adapter"
        local t name rc
        : >"$res/checks.txt"
        for t in checks/*; do
            name=$(basename "$t")
            rc=0
            HWSDF_TEST_DATA="$dir/tests/data" timeout "${GPU_COMPARE_CHECK_TIMEOUT:-300}" "$t" \
                >"$res/check-$name.txt" 2>&1 || rc=$?
            {
                printf '%s: %s; %s\n' "$name" "$([ $rc = 0 ] && echo passed || echo "FAILED (exit $rc)")" \
                    "$(grep -E '^test result:' "$res/check-$name.txt" | tail -1 | cut -c14-)"
                grep -E '^test .* FAILED$' "$res/check-$name.txt" | sed 's/^/    /' || true
            } | tee -a "$res/checks.txt"
        done
    fi
    local b
    for b in benches/*; do
        [[ $stages == *,bench,* ]] || break
        local name
        name=$(basename "$b")
        case "$name" in
            siren | nglod | query*) ;;
            *) continue ;;
        esac
        echo "== bench $name"
        "$b" --bench 2>&1 | tee "$res/bench-$name.txt"
    done
    if [[ $stages == *,kernels,* ]] && [ -x benches/query ]; then
        # One point per invocation against one per subgroup (the default on GPUs, chosen on
        # paper: a 3000-point query leaves one long chain of loads per invocation).
        local k
        for k in invocation subgroup; do
            echo "== NGLOD and hash-grid queries, HWSDF_QUERY_KERNEL=$k"
            HWSDF_QUERY_KERNEL=$k QUERY_BENCH_PRESETS=default,hashgrid_small,hashgrid_default \
                QUERY_BENCH_POINTS=10,3000,50000,1000000 CRITERION_HOME="$res/criterion-kernel-$k" \
                benches/query --bench neural_sdf --measurement-time 2 --warm-up-time 1 2>&1 \
                | grep -v XDG_RUNTIME_DIR | tee "$res/query-kernel-$k.txt" || echo "(failed)"
        done
    fi
    if [[ $stages == *,coop,* ]]; then
        if grep -q 'cooperative matrices (f32 accumulators): none' "$res/gpu-info.txt"; then
            echo "== no f16 cooperative matrices on this adapter: coop stage skipped" | tee "$res/coop-missing.txt"
        else
            echo "== cooperative matrices: f16 inference against the f64 reference"
            HWSDF_REQUIRE_COOP=1 HWSDF_TEST_DATA="$dir/tests/data" checks/siren_gpu coop --nocapture 2>&1 \
                | grep -v XDG_RUNTIME_DIR \
                | tee "$res/coop-check.txt" || echo "(failed)"
            echo "== bench siren on cooperative matrices (SIREN_BENCH_KERNELS=coop)"
            CRITERION_HOME="$res/criterion-coop" SIREN_BENCH_KERNELS=coop benches/siren --bench eval 2>&1 \
                | tee "$res/bench-siren-coop.txt" || echo "(failed)"
            if [ -x benches/query ]; then
                echo "== SIREN queries through NeuralSdf on cooperative matrices (one dispatch)"
                QUERY_BENCH_INTERLEAVED="${GPU_COMPARE_SPLIT_ROUNDS:-500}" QUERY_BENCH_PRESETS=small \
                    QUERY_BENCH_SIREN_KERNELS=coop QUERY_BENCH_SIREN_PRESETS=small,default \
                    QUERY_BENCH_POINTS=10,3000,50000 benches/query 2>&1 \
                    | tee "$res/query-coop.txt" || echo "(failed)"
            fi
        fi
    fi
    if [[ $stages == *,split,* ]] && [ -x benches/query ]; then
        echo "== the query path split into its parts (QUERY_BENCH_INTERLEAVED=${GPU_COMPARE_SPLIT_ROUNDS:-500})"
        QUERY_BENCH_INTERLEAVED="${GPU_COMPARE_SPLIT_ROUNDS:-500}" QUERY_BENCH_SIREN_PRESETS=small,default \
            benches/query 2>&1 | tee "$res/query-split.txt" || echo "(failed)"
    fi
    if [[ $stages == *,phases,* ]] && [ -x benches/query ]; then
        echo "== one mapped query phase by phase (QUERY_BENCH_PHASES=${GPU_COMPARE_SPLIT_ROUNDS:-500})"
        QUERY_BENCH_PHASES="${GPU_COMPARE_SPLIT_ROUNDS:-500}" \
            QUERY_BENCH_PRESETS="${QUERY_BENCH_PRESETS:-default}" \
            QUERY_BENCH_SIREN_PRESETS="${QUERY_BENCH_SIREN_PRESETS:-default}" \
            QUERY_BENCH_POINTS="${QUERY_BENCH_POINTS:-10,3000,50000}" \
            benches/query 2>&1 | tee "$res/query-phases.txt" || echo "(failed)"
    fi
    if [[ $stages == *,profile,* ]]; then
        echo "== a SIREN default training step, launch by launch (SIREN_BENCH_PROFILE=20)"
        SIREN_BENCH_PROFILE=20 SIREN_BENCH_PRESETS=default benches/siren 2>&1 \
            | tee "$res/siren-profile.txt" || echo "(failed)"
        echo "== NGLOD and hash-grid default training steps, launch by launch, per kernel and point source (NGLOD_BENCH_PROFILE=20)"
        NGLOD_BENCH_PROFILE=20 benches/nglod 2>&1 \
            | tee "$res/nglod-profile.txt" || echo "(failed)"
    fi
    if [[ $stages == *,blocks,* ]]; then
        local blk
        for blk in $(echo "${GPU_COMPARE_BLOCKS:-}" | tr ',' ' '); do
            [ -n "$blk" ] || continue
            echo "== bench siren default, tiled kernels, register blocks $blk (SIREN_BENCH_TILED_BLOCK=$blk)"
            CRITERION_HOME="$res/criterion-block-$blk" SIREN_BENCH_PRESETS=default SIREN_BENCH_KERNELS=tiled \
                SIREN_BENCH_TILED_BLOCK="$blk" benches/siren --bench 2>&1 \
                | tee "$res/bench-siren-block-$blk.txt" || echo "(failed)"
        done
        local rb
        for rb in $(echo "${GPU_COMPARE_ROW_BLOCKS:-2,3}" | tr ',' ' '); do
            [ -n "$rb" ] || continue
            echo "== bench siren eval, fused kernel with $rb row blocks per invocation (SIREN_BENCH_FUSED_ROW_BLOCKS=$rb)"
            CRITERION_HOME="$res/criterion-rows-$rb" SIREN_BENCH_KERNELS=tiled \
                SIREN_BENCH_FUSED_ROW_BLOCKS="$rb" benches/siren --bench eval 2>&1 \
                | tee "$res/bench-siren-rows-$rb.txt" || echo "(failed)"
        done
    fi
    local presets=${GPU_COMPARE_PRESETS:-small,default}
    if [ "${GPU_COMPARE_SKIP_TORCH:-0}" != 1 ] && [[ $stages == *,torch,* ]]; then
        if python3 -c 'import torch' 2>/dev/null; then
            local p
            for p in ${presets//,/ }; do
                echo "== PyTorch SIREN $p"
                python3 scripts/siren_torch_bench.py --preset "$p" --compile --json \
                    | tee "$res/torch-siren-$p.json" || echo "(failed)"
                echo "== PyTorch NGLOD $p"
                python3 scripts/nglod_torch_bench.py --preset "$p" --json \
                    | tee "$res/torch-nglod-$p.json" || echo "(failed)"
            done
        else
            echo "== no PyTorch here (python3 -c 'import torch' failed): our side only" | tee "$res/torch-missing.txt"
        fi
    fi
    python3 - "$res" "$presets" <<'PY' | tee "$res/table.md"
import glob, json, os, re, sys

res, presets = sys.argv[1], sys.argv[2].split(",")

def criterion(group, fn, param, home="criterion"):
    path = os.path.join(res, home, group, fn, str(param), "new", "estimates.json")
    try:
        with open(path) as f:
            return json.load(f)["median"]["point_estimate"] * 1e-9
    except (OSError, KeyError, ValueError):
        return None

def torch_json(model, preset):
    try:
        with open(os.path.join(res, f"torch-{model}-{preset}.json")) as f:
            lines = [l for l in f.read().splitlines() if l.startswith("{")]
            return json.loads(lines[-1]) if lines else {}
    except (OSError, ValueError):
        return {}

def epoch_gpu_seconds():
    # benches/nglod.rs prints "total X s: GPU Y s, sampling Z s, stalls W s".
    try:
        text = open(os.path.join(res, "bench-nglod.txt")).read()
    except OSError:
        return None, None
    # The bench prints an epoch split per model ("<name> epoch split on ..."): NGLOD's alone.
    m = re.search(r"^nglod_default epoch split.*?(?=^\S|\Z)", text, re.M | re.S)
    text = m.group(0) if m else ""
    totals = re.findall(r"total ([\d.]+) s: GPU ([\d.]+) s", text)
    epochs = re.findall(r"epoch \d+: (\d+) steps, GPU loop ([\d.]+) s", text)
    if not epochs:
        return None, None
    loops = sorted(float(g) for _, g in epochs)
    return loops[len(loops) // 2], float(totals[-1][0]) if totals else None

def fmt(t, per=None):
    if t is None:
        return "—"
    s = f"{t * 1e6:.0f} µs" if t < 1e-2 else f"{t * 1e3:.2f} ms" if t < 10 else f"{t:.1f} s"
    if per:
        s += f" ({t / per * 1e9:.1f} ns/pt)"
    return s

def ratio(ours, theirs):
    if ours is None or theirs is None or ours <= 0:
        return "—"
    return f"{theirs / ours:.2f}×"

gpu = open(os.path.join(res, "gpu-info.txt")).read().strip().splitlines()
print(f"Adapter: {gpu[0] if gpu else 'unknown'}\n")
try:
    checks = open(os.path.join(res, "checks.txt")).read().rstrip()
    failed = "FAILED" in checks
    print(("**Some kernels FAILED their references on this adapter: the figures below are not "
           "to be trusted.**" if failed else "Kernel checks on this adapter (all passed):")
          + "\n\n" + "\n".join("    " + l for l in checks.splitlines()) + "\n")
except OSError:
    print("Kernel checks: not run (the `checks` stage).\n")
print("| model | preset | measure | ours | PyTorch eager | eager / ours | torch.compile | compile / ours |")
print("| --- | --- | --- | --- | --- | --- | --- | --- |")
rows = []
for p in presets:
    t = torch_json("siren", p)
    eager, comp = t.get("eager", {}), t.get("compile", {})
    for label, fn, param, key, per in [
        ("eval, batch 50 000", "eval", 50000, "eval_50000_s", 50000),
        # Points and values on the GPU, as PyTorch's figure is taken (a device tensor in and
        # out, synchronised); the served network, whose Auto runs large batches on
        # cooperative matrices where the GPU has them.
        ("eval, batch 50 000, served, on the GPU (as PyTorch)", "eval_resident", 50000, "eval_50000_s", 50000),
        ("eval, batch 3000", "eval", 3000, "eval_3000_s", None),
        ("eval, batch 3000, served, on the GPU (as PyTorch)", "eval_resident", 3000, "eval_3000_s", None),
        ("training step, 10⁴ points", "train_step", 10000, "train_step_s", None),
    ]:
        ours = criterion(f"siren_{p}", fn, param)
        rows.append(("SIREN", p, label, ours, eager.get(key), comp.get(key), per))
        coop = criterion(f"siren_{p}", fn, param, "criterion-coop") if fn.startswith("eval") else None
        if coop is not None:
            rows.append(("SIREN", p, label + ", f16 cooperative matrices", coop, eager.get(key),
                         comp.get(key), per))
        # The `blocks` stage's forced register blocks of the tiled GEMM and of the fused kernel.
        for prefix, what in [("criterion-block-", "tiled, {} register blocks"),
                             ("criterion-rows-", "fused kernel, {} row blocks")]:
            for home in sorted(glob.glob(os.path.join(res, prefix + "*"))):
                forced = criterion(f"siren_{p}", fn, param, os.path.basename(home))
                if forced is not None:
                    rows.append(("SIREN", p, f"{label}, " + what.format(os.path.basename(home)[len(prefix):]),
                                 forced, eager.get(key), comp.get(key), per))
    t = torch_json("nglod", p)
    eager = t.get("eager", {})
    for label, param, key, per in [
        ("eval, batch 50 000", 50000, "eval_50000_s", 50000),
        ("eval, batch 3000", 3000, "eval_3000_s", None),
    ]:
        # PyTorch's `default` is the design document's dense model: our `design` group.
        ours = criterion("nglod_design" if p == "default" else f"nglod_{p}", "eval", param)
        rows.append(("NGLOD", p, label, ours, eager.get(key), None, per))
        if p == "default":
            rows.append(("NGLOD", p, label + ", with the sparse 48 level (our default)",
                         criterion("nglod_default", "eval", param), None, None, per))
    if p == "default":
        loop, _ = epoch_gpu_seconds()
        rows.append(("NGLOD", p, "epoch GPU loop, 5·10⁵ points", loop, eager.get("epoch_s"), None, None))
for model, p, label, ours, eager, comp, per in rows:
    print(f"| {model} | {p} | {label} | {fmt(ours, per)} | {fmt(eager, per)} | {ratio(ours, eager)} "
          f"| {fmt(comp, per)} | {ratio(ours, comp)} |")
print("\nRatios above 1× mean ours is faster. Every criterion result of the run:\n")
for est in sorted(glob.glob(os.path.join(res, "criterion*", "**", "new", "estimates.json"), recursive=True)):
    name = os.path.relpath(os.path.dirname(os.path.dirname(est)), res)
    try:
        print(f"- {name}: {fmt(json.load(open(est))['median']['point_estimate'] * 1e-9)}")
    except (OSError, KeyError, ValueError):
        pass
PY
    if [[ $stages == *,fit,* ]]; then
        local m
        for m in $(echo "${GPU_COMPARE_FITS:-nglod,nglod-fresh,nglod-invocation,nglod-batch4096,hashgrid,hashgrid-small,siren,siren-design-loss,siren-constant-lr}" | tr ',' ' '); do
            local fit_args kernel=""
            case "$m" in
                nglod | siren | hashgrid) fit_args=(--model "$m") ;;
                # The training rows one per invocation, beside the GPUs' default of one per
                # subgroup (session 26): the whole fit's answer to which is faster.
                nglod-invocation) fit_args=(--model nglod); kernel=invocation ;;
                # The GPU ground truth's points labelled fresh every epoch, as before its pool
                # (session 32): what the pool saves on a GPU, and that F1 stays.
                nglod-fresh) fit_args=(--model nglod --pool 1,1) ;;
                # Half the steps of twice the rows (session 28, lavapipe, 100 epochs: F1 kept
                # on spot, 0.01 lower near the surface on octagonal-pocket): what it saves on a
                # GPU, whose step of 2048 rows leaves most of it idle.
                nglod-batch4096) fit_args=(--model nglod --batch 4096 --lr 0.0014) ;;
                hashgrid-small) fit_args=(--model hashgrid --preset small) ;;
                # The SIREN reference code's schedule beside ours (the design document's divide
                # by 10 on plateaus): the H100's default fit had reached the floor by step 5125.
                siren-constant-lr) fit_args=(--model siren --plateau-patience 0) ;;
                # Without the sign term: the design document's loss beside ours.
                siren-design-loss) fit_args=(--model siren --sign-weight 0) ;;
                *) echo "unknown fit $m (nglod, nglod-fresh, nglod-invocation, nglod-batch4096, hashgrid, hashgrid-small, siren, siren-design-loss or siren-constant-lr)" >&2; continue ;;
            esac
            echo "== fit: $m on tests/data/spot.obj (the GPU default run; ${fit_args[*]})"
            local t0 t1
            t0=$(date +%s.%N)
            # SIGTERM at the limit: train writes its checkpoint and stops cleanly.
            HWSDF_TRAIN_KERNEL="$kernel" timeout "${GPU_COMPARE_TIMEOUT:-240}" \
                bin/train tests/data/spot.obj "${fit_args[@]}" --out "$res/fit-$m.safetensors" \
                --report "$res/fit-$m.json" 2>&1 | tee "$res/fit-$m.txt" || echo "(failed)"
            t1=$(date +%s.%N)
            echo "wall $(python3 -c "print(f'{$t1 - $t0:.1f}')") s" | tee -a "$res/fit-$m.txt"
            # The fitted SIREN through the report's path on the f32 kernels and, where the
            # adapter has them, on f16 cooperative matrices: F1 and latency side by side.
            if [ "$m" = siren ] && [ -e "$res/fit-siren.safetensors" ]; then
                local k
                for k in auto coop; do
                    if [ "$k" = coop ] && grep -q 'cooperative matrices (f32 accumulators): none' "$res/gpu-info.txt"; then
                        continue
                    fi
                    echo "== eval of the SIREN fit, --siren-kernels $k"
                    bin/eval "$res/fit-siren.safetensors" tests/data/spot.obj --json --siren-kernels "$k" \
                        >"$res/eval-siren-$k.json" 2>"$res/eval-siren-$k.txt" || echo "(failed)"
                done
            fi
        done
    fi
    if [[ $stages == *,scene,* ]] && [ -x benches/scene ]; then
        # Issue 37's targets: 8 NGLOD `default` models and 4 primitives; the fit stage's NGLOD
        # model when there is one (trained weights give real sphere-tracing step counts).
        echo "== bench scene (8 models, 4 primitives: distances, rays, 1920x1080 render)"
        # Without a fit (the stage alone, or the fit cut off), the bench's own untrained models.
        local model=()
        [ -e "$res/fit-nglod.safetensors" ] && model=(SCENE_BENCH_MODEL="$res/fit-nglod.safetensors")
        env ${model[@]+"${model[@]}"} SCENE_BENCH_SECONDS="${SCENE_BENCH_SECONDS:-2}" \
            CRITERION_HOME="$res/criterion-scene" benches/scene --bench 2>&1 \
            | grep -v XDG_RUNTIME_DIR | tee "$res/bench-scene.txt" || echo "(failed)"
    fi
    if [[ $stages == *,groundtruth,* ]] && [ -x examples/ground_truth_bench ]; then
        # Issue 38: GPU against CPU labels on every core, spot and a 1.4 M-triangle scan
        # (armadillo split twice into four), 10^7 points.
        echo "== ground truth: GPU against the CPU's $(nproc) cores"
        local scan=tests/data/spot.obj
        [ -e meshes/armadillo.obj ] && scan=meshes/armadillo.obj
        examples/ground_truth_bench tests/data/spot.obj --points "${GT_BENCH_POINTS:-1000000}" --reps 2 2>&1 \
            | grep -v XDG_RUNTIME_DIR | tee "$res/ground-truth.txt" || echo "(failed)"
        examples/ground_truth_bench "$scan" --subdivide 2 --points "${GT_BENCH_SCAN_POINTS:-10000000}" --reps 1 2>&1 \
            | grep -v XDG_RUNTIME_DIR | tee -a "$res/ground-truth.txt" || echo "(failed)"
    fi
    if [[ $stages == *,groundtruth,* ]] && [ -x examples/nglod_sample_source ]; then
        # Issue 38: NGLOD `default` epochs of spot with points from the CPU pool against points
        # drawn and labelled on the GPU.
        echo "== NGLOD default epochs: CPU pool against GPU draws"
        examples/nglod_sample_source tests/data/spot.obj --points 500000 \
            --epochs "${GT_EPOCHS:-20}" --preset default --batch 2048 2>&1 \
            | grep -v XDG_RUNTIME_DIR | tee "$res/sample-source.txt" || echo "(failed)"
        # The GPU draws labelled fresh every epoch, as before the GPU pool (session 32).
        echo "== NGLOD default epochs: GPU draws, pool 1,1"
        examples/nglod_sample_source tests/data/spot.obj --points 500000 \
            --epochs "${GT_EPOCHS:-20}" --preset default --batch 2048 --sources gpu --pool 1,1 2>&1 \
            | grep -v XDG_RUNTIME_DIR | sed 's/^gpu: mean/gpu (pool 1,1): mean/' \
            | tee -a "$res/sample-source.txt" || echo "(failed)"
    fi
    if [[ $stages == *,hashgrid,* ]] && [ -x examples/grid_sweep ]; then
        # Issue 39: the hash grid's default chosen by F1 per second of training on a GPU.
        # Candidates beside NGLOD, each with the same budget (planned from its first epoch),
        # on spot and the CAD-like meshes when packed (thin parts, where the hash grid should
        # beat NGLOD).
        local sweep_meshes=tests/data/spot.obj m s
        for m in idler-riser octagonal-pocket adis16480; do
            [ -e "meshes/$m.obj" ] && sweep_meshes="$sweep_meshes meshes/$m.obj"
        done
        for s in $(echo "${GPU_COMPARE_SWEEP_SECONDS:-1}" | tr ',' ' '); do
            for m in $sweep_meshes; do
                echo "== hash grid sweep: $m, $s s of training each"
                # shellcheck disable=SC2086 # the candidates are words
                # Larger batches take fewer steps (fewer launches and Adam passes) per epoch.
                # `lazy`: Adam leaves the table entries a step did not touch (a tenth of
                # `default`'s 5.8 M per step of 2048 points), instant-ngp's way.
                examples/grid_sweep "$m" "$s" ${GPU_COMPARE_SWEEP:-nglod hashgrid hashgrid-small \
                    hashgrid@0.0025,2048,lazy hashgrid@0.005,8192,lazy \
                    hashgrid@0.005,8192 hashgrid@0.01,16384 hashgrid-small@0.005,8192 \
                    hash:16,16,512,2,17,64 hash:12,16,512,2,18,64} 2>&1 \
                    | grep -v XDG_RUNTIME_DIR | tee -a "$res/hashgrid-sweep.txt" || echo "(failed)"
            done
        done
    fi
    if [[ $stages == *,corpus,* ]] && [ -d meshes ]; then
        echo "== corpus over the packed meshes"
        local t0 t1
        t0=$(date +%s.%N)
        # Outside results/ (which each run clears), so that a run stopped by the timeout
        # resumes there, and one folder per set of arguments: corpus refuses to mix settings
        # in one results folder, and each set resumes in its own.
        local cargs=${GPU_COMPARE_CORPUS_ARGS:---model nglod} cdir
        cdir="$dir/corpus/$(printf '%s' "$cargs" | tr -c 'A-Za-z0-9.,=-' '_' | sed 's/^[-_]*//')"
        mkdir -p "$cdir"
        echo "corpus arguments: $cargs (results in $cdir)" | tee "$res/corpus.txt"
        # shellcheck disable=SC2086 # word splitting of the extra arguments is intended
        timeout "${GPU_COMPARE_TIMEOUT:-240}" \
            bin/corpus meshes $cargs --out "$cdir/corpus.md" 2>&1 \
            | tee -a "$res/corpus.txt" || echo "(failed)"
        t1=$(date +%s.%N)
        echo "wall $(python3 -c "print(f'{$t1 - $t0:.1f}')") s" | tee -a "$res/corpus.txt"
        [ -e "$cdir/corpus.md" ] && cp "$cdir/corpus.md" "$res/corpus.md"
    fi
    python3 - "$res" <<'PY' | tee -a "$res/table.md"
import glob, json, os, re, sys

res = sys.argv[1]


def reports(pattern):
    """(path, report) for the JSON reports matching `pattern`; unreadable ones are skipped."""
    for path in sorted(glob.glob(os.path.join(res, pattern))):
        try:
            yield path, json.load(open(path))
        except (OSError, ValueError):
            continue


fits = list(reports("fit-*.json"))
if fits:
    print("\n| fit on tests/data/spot.obj | preset | trained | final lr | training | wall in all | F1 box / near "
          "| box sign errors > 0.05 from the surface: false inside / false outside |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
for path, r in fits:
    wall = "—"
    try:
        lines = open(path[:-5] + ".txt").read().splitlines()
        wall = next(l.split()[1] + " s" for l in reversed(lines) if l.startswith("wall "))
    except (OSError, StopIteration, IndexError):
        pass
    f1 = lambda k: "n/a" if r.get(k) is None else f"{r[k]:.4f}"
    unit = "steps" if r.get("model") == "siren" else "epochs"
    far = "—"
    e = r.get("sign_errors_bbox")
    if e:
        # Far errors are regions of the wrong sign: spurious surfaces (false inside) or an
        # inside never carved (false outside); the near ones are the surface a little off.
        beyond = lambda b: b["within_0_2"] + b["beyond_0_2"]
        far = f"{beyond(e['false_inside'])} / {beyond(e['false_outside'])}"
    name = os.path.basename(path)[len("fit-"):-len(".json")]
    lr = r.get("final_lr")
    print(f"| {name} | {r.get('preset')} | {r.get('trained')} {unit} | {'—' if lr is None else f'{lr:.0e}'} | "
          f"{r.get('train_seconds', 0):.1f} s | {wall} | {f1('f1_bbox')} / {f1('f1_near_surface')} | {far} |")
evals = list(reports("eval-siren-*.json"))
if evals:
    print("\n| SIREN fit through `eval` | kernels | F1 box / near | wall per point | wall per 3000 | GPU per point | GPU per 3000 |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
for _, r in evals:
    g = lambda k, f: "—" if r.get(k) is None else f.format(r[k])
    print(f"| spot | {r.get('siren_kernels')} | {g('f1_bbox', '{:.4f}')} / {g('f1_near_surface', '{:.4f}')} | "
          f"{g('per_point_ns', '{:.1f} ns')} | {g('batch3000_us', '{:.0f} µs')} | "
          f"{g('gpu_per_point_ns', '{:.2f} ns')} | {g('gpu_batch3000_us', '{:.0f} µs')} |")
corpus = os.path.join(res, "corpus.md")
if os.path.exists(corpus):
    print("\nCorpus over the packed meshes (results/corpus.md):\n")
    print(open(corpus).read())


def table(head, rows):
    """A Markdown table of `head` (column names) and `rows` (tuples of strings), if any rows."""
    if rows:
        print("\n| " + " | ".join(head) + " |\n|" + " --- |" * len(head))
        for r in rows:
            print("| " + " | ".join(r) + " |")


def read(name):
    """The text of results/`name`, or "" where the stage did not run."""
    try:
        return open(os.path.join(res, name)).read()
    except OSError:
        return ""


def median_s(path):
    try:
        return json.load(open(path))["median"]["point_estimate"] * 1e-9
    except (OSError, KeyError, ValueError):
        return None


def fmt_s(t):
    if t is None:
        return "—"
    return f"{t * 1e6:.0f} µs" if t < 1e-2 else f"{t * 1e3:.2f} ms" if t < 10 else f"{t:.1f} s"


# Issue 37's targets from the scene bench (criterion's medians), each kernel the bench ran.
scene = os.path.join(res, "criterion-scene", "scene")
targets = {"distance": ("3000 distances", "≤ 150 µs"), "rays": ("3000 rays", "≤ 1 ms"),
           "render": ("1920×1080 render", "≤ 30 ms"), "eight_models": ("the 8 single-model queries", "—"),
           "rays_plain": ("3000 rays, plain steps", "—")}
rows = []
for est in sorted(glob.glob(os.path.join(scene, "*", "*", "new", "estimates.json"))):
    name = os.path.basename(os.path.dirname(os.path.dirname(os.path.dirname(est))))
    # `distance_per_subgroup`: the `distance` figure with one point per subgroup.
    base, _, kernel = name.partition("_per_")
    label, target = targets.get(base, (name, "—"))
    rows.append((label + (f", one per {kernel}" if kernel else ""), fmt_s(median_s(est)), target))
table(("scene bench (issue 37)", "ours", "target"), rows)

# Issue 38: labels per second, GPU against the CPU's cores, and each kernel's GPU time.
text = read("ground-truth.txt")
mesh = None
gt_rows = []
for line in text.splitlines():
    m = re.match(r"(\S+): (\d+) triangles", line)
    if m:
        mesh = f"{os.path.basename(m.group(1))} ({int(m.group(2)):,} triangles)"
    m = re.match(r"\s+(signed|closest)\s+GPU\s+(\d+) labels/s .*GPU/CPU ([\d.]+)", line)
    if m and mesh:
        gt_rows.append((mesh, m.group(1), f"{int(m.group(2)):,}/s", f"{m.group(3)}×"))
    m = re.match(r"\s+(\w+): (closest|winding|signed_distance)\s+([\d.]+) ms", line)
    if m and mesh and m.group(1) == m.group(2):
        gt_rows.append((mesh, f"{m.group(1)} kernel, GPU time of one part", f"{m.group(3)} ms", ""))
table(("ground truth (issue 38: sdf ≥ 20× the CPU's cores on the 1.4 M-triangle scan)", "query", "GPU",
       "GPU / CPU"), gt_rows)
for line in read("sample-source.txt").splitlines():
    if "mean wall time per epoch" in line:
        print(f"- NGLOD `default` epoch, {line.strip()}")

# Issue 38's "GPU part of an epoch ≤ 15 ms" (and 39's), from the step profiles.
text = read("nglod-profile.txt")
heading = None
prof = []
for line in text.splitlines():
    m = re.match(r"(\w+), points from (\S+), one row per (\w+):", line)
    if m:
        heading = m.groups()
    m = re.match(r"\| (sum once the pool is full, each launch in its own pass|the second epoch's step loop, measured \(wall\)) \| \| ([\d.]+) \|", line)
    if m and heading:
        prof.append((*heading, m.group(1), m.group(2) + " ms"))
table(("epoch's GPU part (issue 38: ≤ 15 ms for NGLOD `default`)", "points from", "one row per", "how", "ms"),
      prof)
PY
    echo "== table written to $res/table.md"
}

case "$cmd" in
    pack) pack ;;
    run) run ;;
    *) usage ;;
esac
