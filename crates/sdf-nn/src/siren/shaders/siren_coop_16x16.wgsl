// The 16 × 16 tiles of `siren_coop.wgsl` (f16 × f16 → f32; NVIDIA tensor cores; AMD's drivers
// report a range of subgroup sizes, which the host does not run these kernels on yet).
// Workgroup memory: 33 KiB of activations (64 rows of width ≤ 256) and 8 KiB of scratch (41 KiB).
enable f16;
enable wgpu_cooperative_matrix;

alias CA = coop_mat16x16<f16, A>;
alias CB = coop_mat16x16<f16, B>;
alias CC = coop_mat16x16<f32, C>;
// Side of a tile.
const T: u32 = 16u;
// f16 activations: 64 rows of width 256 (rows padded by 8).
const ACT: u32 = 16896u;
// Subgroups per workgroup at most: two column tiles each, 256 columns.
const SLOTS: u32 = 8u;
