"""Loads an hwsdf model file the way a PyTorch user would, and evaluates it with numpy.

    python scripts/load_model.py MODEL.safetensors [x y z ...]

Needs `pip install safetensors numpy` (`safetensors.torch.load_file` gives the same tensors as
torch tensors). Prints the metadata and tensor shapes, then the signed distance at the given
points (mesh coordinates), computed here from the tensors alone: a check that the file is
self-describing.
"""
import json
import sys

import numpy as np
from safetensors import safe_open
from safetensors.numpy import load_file


def siren(t, cfg, x):
    w0 = cfg["omega0"]
    h = x
    for i in range(cfg["hidden_layers"]):
        h = np.sin(w0 * (h @ t[f"net.{i}.weight"].T + t[f"net.{i}.bias"]))
    i = cfg["hidden_layers"]
    return (h @ t[f"net.{i}.weight"].T + t[f"net.{i}.bias"])[:, 0]


def grid_features(t, cfg, x, level, r):
    """The trilinearly interpolated features of one level at the points x (in [-1, 1]^3)."""
    g = t[f"grids.{level}"]
    n_features = g.shape[-1]
    # The configuration decides how a level is stored, as in the Rust loader (a stray tensor
    # does not): hashed where a hash grid's level has more vertices than its table, sparse for
    # NGLOD's last `sparse_levels` levels, dense otherwise.
    encoding = cfg.get("encoding", {})
    hashed = encoding.get("kind") == "hashed" and (r + 1) ** 3 > 2 ** encoding["log2_table_size"]
    sparse = not hashed and level >= len(cfg["resolutions"]) - cfg.get("sparse_levels", 0)
    if sparse:
        # An NGLOD sparse level: [n, F] for the band's vertices, whose linear indices
        # (ix·(r+1) + iy)·(r+1) + iz are listed; every other vertex has zero features.
        dense = np.zeros(((r + 1) ** 3, n_features), dtype=g.dtype)
        dense[t[f"grids.{level}.vertices"].astype(np.int64)] = g
        g = dense.reshape(r + 1, r + 1, r + 1, n_features)
    # The cell coordinate in f64, as the Rust reference computes it (f32 would be off by up to
    # 1e-4 cells at a level of 4096).
    u = (x.astype(np.float64) + 1.0) * 0.5 * r
    i0 = np.clip(np.floor(u).astype(np.int64), 0, r - 1)
    f = u - i0
    z = 0.0
    for c in range(8):
        d = np.array([(c >> 2) & 1, (c >> 1) & 1, c & 1])
        w = np.prod(np.where(d == 1, f, 1.0 - f), axis=1)
        i = (i0 + d).astype(np.uint64)
        if hashed:
            # A hash grid's level with more vertices than its table of T entries ([T, F]):
            # instant-ngp's spatial hash, in wrapping 32-bit arithmetic.
            m = np.uint64(0xFFFFFFFF)
            h = i[:, 0] ^ ((i[:, 1] * np.uint64(2654435761)) & m) ^ ((i[:, 2] * np.uint64(805459861)) & m)
            rows = g[(h & np.uint64(g.shape[0] - 1)).astype(np.int64)]
        else:
            # A dense level: [r+1, r+1, r+1, F], indexed [ix, iy, iz, f].
            i = i.astype(np.int64)
            rows = g[i[:, 0], i[:, 1], i[:, 2]]
        z = z + w[:, None] * rows
    return z


def nglod(t, cfg, x):
    """NGLOD sums its levels' features; a hash grid concatenates them."""
    x = np.clip(x, -1.0, 1.0)
    levels = [grid_features(t, cfg, x, level, r) for level, r in enumerate(cfg["resolutions"])]
    if cfg.get("encoding", {}).get("kind") == "hashed":
        z = np.concatenate(levels, axis=1)
    else:
        z = sum(levels)
    h = np.maximum(z @ t["mlp.0.weight"].T + t["mlp.0.bias"], 0.0)
    return (h @ t["mlp.2.weight"].T + t["mlp.2.bias"])[:, 0]


def normalized(pts, norm):
    """Mesh coordinates (float32) to the model's box, as the Rust loader maps them: in float32
    where the centre is a float32 (a mesh near the origin), else in float64 (a mesh far from
    the origin, whose centre the file keeps in float64: float32 would shift every point)."""
    center = np.array(norm["center"], dtype=np.float64)
    scale = np.float32(norm["scale"])
    with np.errstate(over="ignore", invalid="ignore"):
        wide = ((pts.astype(np.float64) - center) * np.float64(scale)).astype(np.float32)
        if not np.array_equal(center.astype(np.float32).astype(np.float64), center):
            return wide
        local = (pts - center.astype(np.float32)) * scale
    # A point whose float32 map overflows on the way (and is finite) is mapped in float64.
    narrow = np.isfinite(local).all(axis=1) | ~np.isfinite(pts).all(axis=1)
    return np.where(narrow[:, None], local, wide)


def main():
    path = sys.argv[1]
    with safe_open(path, "np") as f:
        meta = f.metadata()
    tensors = load_file(path)
    print("metadata:", json.dumps(meta, indent=1))
    for name, value in sorted(tensors.items()):
        print(f"{name:16s} {value.dtype} {list(value.shape)}")
    cfg = json.loads(meta["config"])
    norm = json.loads(meta["normalization"])
    pts = np.array([float(v) for v in sys.argv[2:]] or [0.0, 0.0, 0.0], dtype=np.float32)
    pts = pts.reshape(-1, 3)
    local = normalized(pts, norm)
    inside = np.clip(local, -1.0, 1.0)
    # "nglod" and "hashgrid" share one grid lookup and MLP.
    net = siren if meta["architecture"] == "siren" else nglod
    d = net(tensors, cfg, inside) + np.linalg.norm(local - inside, axis=1)
    for p, v in zip(pts, d / np.float32(norm["scale"])):
        print(f"sdf({p[0]:g}, {p[1]:g}, {p[2]:g}) = {v:.6f}")


if __name__ == "__main__":
    main()
