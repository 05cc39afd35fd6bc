#!/usr/bin/env python3
"""Lists the executables in cargo's `--message-format=json` output (stdin) as "name path" lines.

    cargo bench --no-run --message-format=json | python3 scripts/cargo_executables.py --kind bench
    cargo test --no-run --message-format=json | python3 scripts/cargo_executables.py --name siren_gpu

Used by scripts/gpu-compare.sh and scripts/coop-check.sh to find the binaries they carry.
"""
import argparse
import json
import sys

parser = argparse.ArgumentParser()
parser.add_argument("--kind", help="only targets of these kinds (bench, test, bin, ...; comma-separated)")
parser.add_argument("--name", help="only the target of this name")
args = parser.parse_args()
for line in sys.stdin:
    try:
        m = json.loads(line)
    except ValueError:
        continue
    if m.get("reason") != "compiler-artifact" or not m.get("executable"):
        continue
    target = m["target"]
    if args.kind and not set(args.kind.split(",")) & set(target["kind"]):
        continue
    if args.name and target["name"] != args.name:
        continue
    print(target["name"], m["executable"])
