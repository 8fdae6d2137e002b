#!/usr/bin/env python3
"""Lists import cycles between the modules of each crate of the workspace; exits 1 if any.

Two modules are in a cycle when each reaches the other through `crate::` paths (a `use` or a
path in code). Modules are compared at each level of the tree: the top-level modules of a
crate, then the children of each module among themselves, so a child naming its parent
(`super::`) is not a cycle but two siblings naming each other are. Test modules (`tests`,
`#[cfg(test)]` files under `tests/`) are left out: they may reach anywhere.

Usage: scripts/module_cycles.py [CRATE_SRC_DIR ...]   (default: every crate's src/)
"""

import os
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_CRATES = [
    "common/src",
    "common/ipc/src",
    "agent-frontend/src",
    "agent-dds-worker/src",
    "deploy/src",
    "benches/src",
    "tests/src",
]

PATH = re.compile(r"\b(crate|super|self)((?:::[A-Za-z_][A-Za-z0-9_]*)+)")
USE_GROUP = re.compile(r"\buse\s+(crate|super|self)((?:::[A-Za-z_][A-Za-z0-9_]*)*)::\{([^;]*)\};", re.S)
LINE_COMMENT = re.compile(r"//.*")
TEST_MOD = re.compile(r"#\[cfg\(test\)\]\s*(?:pub(?:\([a-z]+\))?\s+)?mod\s+\w+\s*\{", re.S)


def module_path(src: Path, file: Path) -> tuple:
    rel = file.relative_to(src).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] in ("mod", "lib", "main"):
        parts.pop()
    if parts and parts[0] == "bin":
        return ("<bin>",) + tuple(parts[1:])
    return tuple(parts)


def strip_tests(text: str) -> str:
    """The text without `#[cfg(test)] mod x { ... }` blocks."""
    out = []
    i = 0
    for m in TEST_MOD.finditer(text):
        if m.start() < i:
            continue
        out.append(text[i : m.start()])
        depth = 0
        j = m.end() - 1
        while j < len(text):
            if text[j] == "{":
                depth += 1
            elif text[j] == "}":
                depth -= 1
                if depth == 0:
                    break
            j += 1
        i = j + 1
    out.append(text[i:])
    return "".join(out)


def resolve(base: tuple, anchor: str, rest: list) -> tuple:
    if anchor == "crate":
        return tuple(rest)
    if anchor == "self":
        return base + tuple(rest)
    # super (possibly repeated)
    here = list(base)
    while rest and rest[0] == "super":
        rest = rest[1:]
        here = here[:-1]
    return tuple(here[:-1]) + tuple(rest)


def references(text: str, here: tuple, is_mod_file: bool) -> set:
    """Module paths (as far as named) this file's code names."""
    base = here if is_mod_file else here
    # `self::` in a file is the file's own module; `super::` its parent.
    found = set()
    code = LINE_COMMENT.sub("", text)
    for m in USE_GROUP.finditer(code):
        prefix = [p for p in m.group(2).split("::") if p]
        for item in re.split(r"[,{}\s]+", m.group(3)):
            item = item.split(" as ")[0].strip()
            if item and item not in ("self", "*"):
                found.add(resolve(base, m.group(1), prefix + [item]))
            elif item == "self":
                found.add(resolve(base, m.group(1), prefix))
    for m in PATH.finditer(code):
        parts = [p for p in m.group(2).split("::") if p]
        found.add(resolve(base, m.group(1), parts))
    return found


def crate_graph(src: Path):
    files = [
        p
        for p in src.rglob("*.rs")
        if "tests" not in p.relative_to(src).parts and p.stem != "tests"
    ]
    modules = {module_path(src, f) for f in files}
    edges = {}
    for f in files:
        here = module_path(src, f)
        if here[:1] == ("<bin>",):
            continue
        text = strip_tests(f.read_text(encoding="utf-8"))
        for target in references(text, here, f.stem in ("mod", "lib", "main")):
            # The longest known module the path names.
            t = target
            while t and t not in modules:
                t = t[:-1]
            if not t or t == here:
                continue
            # Compare at the level where the two part: the children of their common parent.
            common = 0
            while common < min(len(here), len(t)) and here[common] == t[common]:
                common += 1
            if common == len(here) or common == len(t):
                continue  # one contains the other: parent and descendant
            a, b = here[: common + 1], t[: common + 1]
            edges.setdefault(a, {}).setdefault(b, set()).add((str(f.relative_to(ROOT)), "::".join(target)))
    return edges


def cycles(edges):
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []
    counter = [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges.get(v, {}):
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
                out.append(sorted(comp))

    sys.setrecursionlimit(10000)
    for v in list(edges):
        if v not in index:
            visit(v)
    return out


def main(argv):
    crates = argv[1:] or DEFAULT_CRATES
    found = 0
    for c in crates:
        src = ROOT / c
        if not src.is_dir():
            continue
        edges = crate_graph(src)
        for comp in cycles(edges):
            found += 1
            names = ["::".join(m) or "crate" for m in comp]
            print(f"{c}: cycle between {', '.join(names)}")
            members = set(comp)
            for a in comp:
                for b, why in sorted(edges.get(a, {}).items()):
                    if b in members:
                        f, path = sorted(why)[0]
                        more = f" (+{len(why) - 1} more)" if len(why) > 1 else ""
                        print(f"    {'::'.join(a)} -> {'::'.join(b)}: {f} names {path}{more}")
    if found:
        print(f"{found} module cycle(s)")
        return 1
    print("no module cycles")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
