#!/usr/bin/env python3
"""Lists pairs of modules of a crate that import each other (`use crate::…`, `super::…`,
`crate::…` paths in code). A module is a file's module path; test-only modules are skipped.
Usage: scripts/module-cycles.py crates/sdf-nn/src [more crate src dirs]; exits 1 if any pair."""
import os, re, sys

def module_of(root, path):
    rel = os.path.relpath(path, root)[:-3].split(os.sep)
    if rel[-1] in ("mod", "lib", "main"):
        rel = rel[:-1]
    return tuple(rel)

def refs(text, me):
    out = set()
    text = re.sub(r"#\[cfg\(test\)\]\s*mod tests\s*\{.*", "", text, flags=re.S)
    text = re.sub(r"//[^\n]*", "", text)
    for m in re.finditer(r"\b((?:crate|super)(?:::[a-z_][a-z0-9_]*)+)", text):
        parts = m.group(1).split("::")
        base = list(me)
        if parts[0] == "super":
            while parts and parts[0] == "super":
                base = base[:-1]
                parts = parts[1:]
            target = tuple(base) + tuple(parts)
        else:
            target = tuple(parts[1:])
        out.add(target)
    for m in re.finditer(r"use\s+crate::\{([^;]*)\}", text):
        for item in re.split(r",\s*", m.group(1)):
            item = item.strip().split("::")[0]
            if re.match(r"^[a-z_][a-z0-9_]*$", item):
                out.add((item,))
    return out

bad = 0
for root in sys.argv[1:]:
    mods = {}
    for d, _, files in os.walk(root):
        for f in files:
            if f.endswith(".rs"):
                p = os.path.join(d, f)
                mods[module_of(root, p)] = p
    names = set(mods)
    deps = {}
    for m, p in mods.items():
        if m and m[-1] == "tests":
            continue
        ds = set()
        for t in refs(open(p).read(), m):
            # the longest known module that prefixes the path
            for k in range(len(t), 0, -1):
                if t[:k] in names:
                    if t[:k] != m and not m[:k] == t[:k]:
                        ds.add(t[:k])
                    break
        deps[m] = ds
    for a in deps:
        for b in deps[a]:
            if a < b and a in deps.get(b, ()):
                print(f"{root}: {'::'.join(a)} <-> {'::'.join(b)}")
                bad += 1
sys.exit(1 if bad else 0)
