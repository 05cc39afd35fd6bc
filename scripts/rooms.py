#!/usr/bin/env python3
"""Checks the rooms of the library: no source file over 1,000 lines and no function over 150,
unless a comment containing `rooms:` says why: in the file's first 30 lines for the file, in the
function or the 5 lines above it for a function (e.g. `// rooms: one scope owns …`).
Tests (`tests/`, `#[cfg(test)] mod tests`) are not counted. Usage: scripts/rooms.py DIR…;
exits 1 and lists the offenders when any."""
import os, re, sys

MAX_FILE, MAX_FN = 1000, 150
FN = re.compile(r"^(\s*)(?:pub(?:\([^)]*\))?\s+)?(?:const\s+)?(?:async\s+)?(?:unsafe\s+)?fn\s+(\w+)")

def functions(lines):
    """(name, first line, length) of each function, by brace matching from its signature."""
    out = []
    for i, line in enumerate(lines):
        m = FN.match(line)
        if not m:
            continue
        depth, opened = 0, False
        for j in range(i, len(lines)):
            code = re.sub(r'"(?:\\.|[^"\\])*"', '""', lines[j].split("//")[0])
            depth += code.count("{") - code.count("}")
            opened = opened or "{" in code
            if opened and depth <= 0:
                out.append((m.group(2), i + 1, j - i + 1))
                break
            if not opened and code.rstrip().endswith(";"):
                break
    return out

bad = []
for root in sys.argv[1:]:
    for d, _, files in os.walk(root):
        for f in sorted(files):
            if not f.endswith(".rs") or f == "tests.rs":
                continue
            p = os.path.join(d, f)
            text = open(p).read()
            lines = text.split("\n")
            cut = re.search(r"^#\[cfg\(test\)\]\s*\n\s*mod tests", text, flags=re.M)
            if cut:
                lines = text[: cut.start()].split("\n")
            if len(lines) > MAX_FILE and "rooms:" not in "\n".join(lines[:30]):
                bad.append(f"{p}: {len(lines)} lines")
            for name, first, n in functions(lines):
                said = "\n".join(lines[max(0, first - 6) : first - 1 + n])
                if n > MAX_FN and "rooms:" not in said:
                    bad.append(f"{p}:{first}: fn {name} is {n} lines")
print("\n".join(bad) if bad else "rooms: every file and function within bounds")
sys.exit(1 if bad else 0)
