#!/usr/bin/env python3
"""Fails when two source files of one crate import each other, directly or around a longer circle.

An edge A -> B is a `use crate::...` or an inline `crate::...` path in file A that names module B (a file of
the same crate: `b.rs` or `b/mod.rs`, the longest match). Re-exports (`pub use`) and tests (`#[cfg(test)]`
modules) are not edges: a parent that re-exports its children, or a test that reaches anything, is no circle.
Usage: scripts/module-cycles.py CRATE_DIR...
"""
import re
import sys
from pathlib import Path

PATH = re.compile(r"\bcrate((?:::[A-Za-z_][A-Za-z0-9_]*)+)")


def module_files(src: Path) -> dict:
    mods = {}
    for f in src.rglob("*.rs"):
        rel = f.relative_to(src).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] in ("lib", "main", "mod"):
            parts = parts[:-1]
        if parts and parts[0] == "bin":
            continue
        mods[tuple(parts)] = f
    return mods


def code_without_tests_and_reexports(text: str) -> str:
    out, skip_depth, depth, pending = [], None, 0, False
    for line in text.splitlines():
        stripped = line.strip()
        if stripped.startswith("#[cfg(test)]"):
            pending = True
            continue
        if skip_depth is None and pending and stripped.startswith("mod "):
            skip_depth, pending = depth, False
        opens, closes = line.count("{"), line.count("}")
        if skip_depth is not None:
            depth += opens - closes
            if depth <= skip_depth:
                skip_depth = None
            continue
        depth += opens - closes
        if stripped.startswith("pub use ") or stripped.startswith("//"):
            continue
        out.append(line)
    return "\n".join(out)


def uses(text: str):
    # `use crate::{a::X, b::Y}` groups: every first segment after `crate::{`.
    for m in re.finditer(r"\bcrate::\{([^}]*)\}", text):
        for item in m.group(1).split(","):
            item = item.strip()
            if item:
                yield tuple(s for s in item.split("::") if s and s[0].islower() and s != "self")
    for m in PATH.finditer(text):
        yield tuple(s for s in m.group(1).split("::")[1:] if s and s[0].islower() and s != "self")


def cycles(crate: Path) -> list:
    mods = module_files(crate / "src")
    edges = {m: set() for m in mods}
    for m, f in mods.items():
        for path in uses(code_without_tests_and_reexports(f.read_text())):
            for n in range(len(path), 0, -1):
                target = path[:n]
                if target in mods:
                    if target != m and not (m[: len(target)] == target):
                        edges[m].add(target)
                    break
    # Tarjan's strongly connected components.
    index, low, stack, on, found, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(str(mods[c].relative_to(crate)) for c in comp))

    for v in mods:
        if v not in index:
            visit(v)
    return found


def main() -> int:
    bad = 0
    for d in sys.argv[1:]:
        for comp in cycles(Path(d)):
            print(f"{d}: files import each other: {' <-> '.join(comp)}", file=sys.stderr)
            bad += 1
    if not bad:
        print(f"no import circle between the files of {len(sys.argv) - 1} crates")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
