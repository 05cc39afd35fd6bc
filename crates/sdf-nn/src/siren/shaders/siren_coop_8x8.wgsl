// The 8 × 8 tiles of `siren_coop.wgsl` (f16 × f16 → f32; Mesa's lavapipe from Mesa 25.1 on;
// Apple GPUs too once the host runs these kernels on a range of subgroup sizes).
// Workgroup memory: 16.5 KiB of activations (32 rows of width ≤ 256) and 4 KiB of scratch.
enable f16;
enable wgpu_cooperative_matrix;

alias CA = coop_mat8x8<f16, A>;
alias CB = coop_mat8x8<f16, B>;
alias CC = coop_mat8x8<f32, C>;
// Side of a tile.
const T: u32 = 8u;
// f16 activations: 32 rows of width 256 (rows padded by 8).
const ACT: u32 = 8448u;
// Subgroups per workgroup at most: two column tiles each, 256 columns.
const SLOTS: u32 = 16u;
