"""The PyTorch side of the SIREN benchmark: the same network, batch sizes and training step as
`cargo bench --bench siren`, in PyTorch eager and (where it works) `torch.compile`.

    python scripts/siren_torch_bench.py [--preset small|default] [--device cuda|cpu]
                                        [--threads N] [--compile] [--model FILE.safetensors]

Measures, like benches/siren.rs:
- inference per point at a batch of 50 000, and the latency of a batch of 3000;
- one training step of 10^4 points (5000 surface points with normals + 5000 uniform box
  points): forward with the input gradient (autograd, create_graph), the 4-term loss of
  crates/sdf-nn/src/siren/cpu.rs, backward through Φ and ∇Φ (double backprop), Adam.

Every figure is the median of `--reps` timed repetitions after warm-up, with the device
synchronised around each one. `--json` prints one JSON object with the figures in seconds
(what scripts/gpu-compare.sh reads). `--model` loads the weights from an hwsdf model file (the same
tensor names, `net.{i}.weight` / `net.{i}.bias`), so both sides run the very same network; the
timing does not depend on the values otherwise. Needs `pip install torch numpy` (plus
`safetensors` for `--model`).
"""
import argparse
import json
import math
import statistics
import time

import torch

PRESETS = {"small": (64, 3, 10.0), "default": (256, 4, 30.0)}  # width, sine layers, ω0


class Siren(torch.nn.Module):
    """sin(ω0 (W x + b)) layers and a linear head, initialised as `Siren::new` does."""

    def __init__(self, width, layers, omega0):
        super().__init__()
        dims = [3] + [width] * layers + [1]
        self.omega0 = omega0
        self.net = torch.nn.ModuleList(torch.nn.Linear(a, b) for a, b in zip(dims, dims[1:]))
        with torch.no_grad():
            for i, lin in enumerate(self.net):
                n = lin.in_features
                bound = 1.0 / n if i == 0 else math.sqrt(6.0 / n) / omega0
                lin.weight.uniform_(-bound, bound)
                lin.bias.uniform_(-1.0 / math.sqrt(n), 1.0 / math.sqrt(n))
            self.net[-1].bias.fill_(0.5)  # sdf_nn::siren::OUTPUT_BIAS_INIT

    def forward(self, x):
        for lin in self.net[:-1]:
            x = torch.sin(self.omega0 * lin(x))
        return self.net[-1](x)


def loss_fn(model, pts, normals, n_surface, w=(3000.0, 100.0, 100.0, 5.0), alpha=100.0):
    """The mean-over-all-points loss of crates/sdf-nn/src/siren/cpu.rs."""
    pts = pts.requires_grad_(True)
    phi = model(pts)[:, 0]
    (grad,) = torch.autograd.grad(phi.sum(), pts, create_graph=True)
    n = pts.shape[0]
    gn = grad.norm(dim=1)
    cos = (grad[:n_surface] * normals).sum(dim=1) / gn[:n_surface].clamp_min(1e-12)
    return (
        w[0] * phi[:n_surface].abs().sum()
        + w[2] * (1.0 - cos).sum()
        + w[1] * torch.exp(-alpha * phi[n_surface:].abs()).sum()
        + w[3] * (gn - 1.0).abs().sum()
    ) / n


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
    ap.add_argument("--compile", action="store_true", help="also time torch.compile")
    ap.add_argument("--model", help="take the weights from an hwsdf .safetensors file")
    ap.add_argument("--reps", type=int, default=20)
    ap.add_argument("--json", action="store_true", help="print the figures as one JSON object")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    torch.manual_seed(1)
    model = Siren(*PRESETS[args.preset]).to(device)
    if args.model:
        from safetensors import safe_open
        from safetensors.torch import load_file

        with safe_open(args.model, "pt") as f:
            cfg = json.loads(f.metadata()["config"])
        model = Siren(cfg["width"], cfg["hidden_layers"], cfg["omega0"]).to(device)
        model.load_state_dict({k: v.to(device) for k, v in load_file(args.model).items()})

    params = sum(p.numel() for p in model.parameters())
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
    header = (f"torch {torch.__version__}, device {name}, threads {torch.get_num_threads()}, "
              f"preset {args.preset}, {params} parameters")
    if not args.json:
        print(header)
    results = {"torch": torch.__version__, "device": name, "preset": args.preset, "params": params}

    gen = torch.Generator(device="cpu").manual_seed(42)
    box = lambda n: (torch.rand(n, 3, generator=gen) * 2 - 1).to(device)  # noqa: E731
    x50k, x3k = box(50_000), box(3000)
    surf = box(5000)
    normals = torch.nn.functional.normalize(surf, dim=1)
    batch = torch.cat([surf, box(5000)])
    opt = torch.optim.Adam(model.parameters(), lr=1e-4)

    def variants():
        yield "eager", model
        if args.compile:
            # Double backward (create_graph) cannot reuse donated buffers.
            torch._functorch.config.donated_buffer = False
            yield "compile", torch.compile(model)

    def step(m):
        opt.zero_grad(set_to_none=True)
        loss_fn(m, batch.detach().clone(), normals, 5000).backward()
        opt.step()

    for label, m in variants():
        figures = []
        results[label] = {}
        for what, key, fn, reps in [
            ("eval 50k", "eval_50000_s", lambda: m(x50k), args.reps),
            ("eval 3000", "eval_3000_s", lambda: m(x3k), args.reps),
            ("train step 10^4", "train_step_s", lambda: step(m), max(3, args.reps // 2)),
        ]:
            try:
                with torch.set_grad_enabled(what.startswith("train")):
                    t = timed(fn, device, reps)
            except Exception as e:  # torch.compile may not take every case
                figures.append(f"{what} failed ({type(e).__name__}: {str(e).splitlines()[0][:120]})")
                results[label][key] = None
                continue
            results[label][key] = t
            extra = f" ({t / 50_000 * 1e9:.1f} ns/pt)" if what == "eval 50k" else ""
            figures.append(f"{what} {t * 1e3:.3f} ms{extra}")
        if not args.json:
            print(f"{label}: " + ", ".join(figures))
    if args.json:
        print(json.dumps(results))

if __name__ == "__main__":
    main()
