"""The PyTorch side of the NGLOD benchmark: the same model, batch sizes and training epoch as
`cargo bench --bench nglod`, in PyTorch eager.

    python scripts/nglod_torch_bench.py [--preset small|default] [--device cuda|cpu]
                                        [--threads N] [--reps N] [--json]

The model is crates/sdf-nn/src/nglod: K dense feature grids over [-1, 1]^3 (grid l has
(r_l + 1)^3 vertices of F features, vertex i at -1 + 2 i / r_l, so `grid_sample` with
align_corners=True), trilinearly interpolated, summed over the levels, decoded by
W1 relu(W0 z + b0) + b1. Measures:
- inference per point at a batch of 50 000, and the latency of a batch of 3000;
- one training epoch of the design document's 5e5 points in batches of 2048 (245 steps of the
  full-model MSE and Adam), points and targets already on the device, as our epoch's GPU loop.

Every figure is the median of `--reps` timed repetitions after warm-up, with the device
synchronised around each one. `--json` prints one JSON object with the figures in seconds
(what scripts/gpu-compare.sh reads). Needs `pip install torch`.
"""
import argparse
import json
import statistics
import time

import torch
import torch.nn.functional as F

PRESETS = {"small": ([4, 8, 16], 4, 32), "default": ([6, 12, 24], 8, 128)}  # resolutions, F, H


class Nglod(torch.nn.Module):
    def __init__(self, resolutions, features, hidden):
        super().__init__()
        self.grids = torch.nn.ParameterList(
            torch.nn.Parameter(0.01 * torch.randn(1, features, r + 1, r + 1, r + 1))
            for r in resolutions
        )
        self.mlp = torch.nn.Sequential(
            torch.nn.Linear(features, hidden), torch.nn.ReLU(), torch.nn.Linear(hidden, 1)
        )

    def forward(self, x):
        g = x.view(1, -1, 1, 1, 3)
        z = sum(F.grid_sample(grid, g, mode="bilinear", align_corners=True) for grid in self.grids)
        return self.mlp(z.view(z.shape[1], -1).t())[:, 0]


def timed(fn, device, reps, warmup=3):
    for _ in range(warmup):
        fn()
    if device.type == "cuda":
        torch.cuda.synchronize()
    out = []
    for _ in range(reps):
        t = time.perf_counter()
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize()
        out.append(time.perf_counter() - t)
    return statistics.median(out)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--preset", choices=PRESETS, default="default")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--threads", type=int, help="torch.set_num_threads (CPU)")
    ap.add_argument("--reps", type=int, default=20)
    ap.add_argument("--json", action="store_true", help="print the figures as one JSON object")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    torch.manual_seed(1)
    model = Nglod(*PRESETS[args.preset]).to(device)
    params = sum(p.numel() for p in model.parameters())
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"

    gen = torch.Generator(device="cpu").manual_seed(42)
    box = lambda n: (torch.rand(n, 3, generator=gen) * 2 - 1).to(device)  # noqa: E731
    x50k, x3k = box(50_000), box(3000)
    epoch_pts = box(500_000)
    epoch_d = epoch_pts.norm(dim=1) - 0.5  # any target: the timing does not depend on it
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    batch = 2048

    def epoch():
        perm = torch.randperm(epoch_pts.shape[0], device=device)
        for i in range(0, perm.shape[0] - batch + 1, batch):
            idx = perm[i : i + batch]
            opt.zero_grad(set_to_none=True)
            F.mse_loss(model(epoch_pts[idx]), epoch_d[idx]).backward()
            opt.step()

    with torch.no_grad():
        t50k = timed(lambda: model(x50k), device, args.reps)
        t3k = timed(lambda: model(x3k), device, args.reps)
    tep = timed(epoch, device, max(3, args.reps // 5), warmup=1)
    figures = {
        "torch": torch.__version__,
        "device": name,
        "preset": args.preset,
        "params": params,
        "eager": {"eval_50000_s": t50k, "eval_3000_s": t3k, "epoch_s": tep},
    }
    if args.json:
        print(json.dumps(figures))
    else:
        print(f"torch {torch.__version__}, device {name}, threads {torch.get_num_threads()}, "
              f"preset {args.preset}, {params} parameters")
        print(f"eager: eval 50k {t50k * 1e3:.3f} ms ({t50k / 50_000 * 1e9:.1f} ns/pt), "
              f"eval 3000 {t3k * 1e3:.3f} ms, epoch (245 steps of 2048) {tep:.3f} s")


if __name__ == "__main__":
    main()
