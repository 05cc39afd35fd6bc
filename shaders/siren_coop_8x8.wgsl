// The 8 × 8 tiles of `siren_coop.wgsl` (f16 × f16 → f32; Mesa's lavapipe from Mesa 25.1 on;
// Apple GPUs too once the host runs these kernels on a range of subgroup sizes).
// Workgroup memory: 2 × 8.25 KiB of activations and 8 KiB of scratch (24.5 KiB).
enable f16;
enable wgpu_cooperative_matrix;

alias CA = coop_mat8x8<f16, A>;
alias CB = coop_mat8x8<f16, B>;
alias CC = coop_mat8x8<f32, C>;
// Side of a tile.
const T: u32 = 8u;
// f16 activations per buffer: 16 rows of width 256 (rows padded by 8).
const ACT: u32 = 4224u;
// Tiles multiplied at once: one per subgroup of 8 in a workgroup of 256.
const SLOTS: u32 = 32u;
