#!/usr/bin/env python3
"""Lists import cycles between the modules of each crate of the workspace; exits 1 if any.

Two modules are in a cycle when each reaches the other through `crate::` paths (a `use` or a
path in code). Modules are compared at each level of the tree: the top-level modules of a
crate, then the children of each module among themselves, so a child naming its parent
(`super::`) is not a cycle but two siblings naming each other are. Test modules (`tests`,
`#[cfg(test)]` files under `tests/`) are left out: they may reach anywhere.

Usage: scripts/module_cycles.py [CRATE_SRC_DIR ...]   (default: the src/ of every member of
the workspace, as Cargo.toml lists them)
"""

import os
import re
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def workspace_crates():
    """The src/ folder of every workspace member (a new crate is checked without a change here)."""
    with open(ROOT / "Cargo.toml", "rb") as f:
        members = tomllib.load(f)["workspace"]["members"]
    return [f"{m}/src" for m in members]


PATH = re.compile(r"\b(crate|super|self)((?:::[A-Za-z_][A-Za-z0-9_]*)+)")
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


def closing_brace(text: str, open_at: int) -> int:
    """Index of the `}` closing the `{` at `open_at`, skipping strings, chars and comments."""
    depth = 0
    i = open_at
    n = len(text)
    while i < n:
        ch = text[i]
        if text.startswith("//", i):
            i = text.find("\n", i)
            if i < 0:
                return n
            continue
        if text.startswith("/*", i):
            j = text.find("*/", i + 2)
            i = n if j < 0 else j + 2
            continue
        raw = re.match(r'b?r(#*)"', text[i : i + 40])
        if raw and (i == 0 or not (text[i - 1].isalnum() or text[i - 1] == "_")):
            end = '"' + raw.group(1)
            j = text.find(end, i + raw.end())
            i = n if j < 0 else j + len(end)
            continue
        if ch == '"':
            i += 1
            while i < n and text[i] != '"':
                i += 2 if text[i] == "\\" else 1
            i += 1
            continue
        if ch == "'":
            lit = re.match(r"'(\\.|[^\\'])'", text[i : i + 12])
            if lit:
                i += lit.end()
                continue
        if ch == "{":
            depth += 1
        elif ch == "}":
            depth -= 1
            if depth == 0:
                return i
        i += 1
    return n


def strip_tests(text: str) -> str:
    """The text without `#[cfg(test)] mod x { ... }` blocks."""
    out = []
    i = 0
    for m in TEST_MOD.finditer(text):
        if m.start() < i:
            continue
        out.append(text[i : m.start()])
        i = closing_brace(text, m.end() - 1) + 1
    out.append(text[i:])
    return "".join(out)


def split_top(text: str, sep: str = ","):
    """`text` split on `sep` outside braces."""
    parts, depth, cur = [], 0, []
    for ch in text:
        if ch == "{":
            depth += 1
        elif ch == "}":
            depth -= 1
        if ch == sep and depth == 0:
            parts.append("".join(cur))
            cur = []
        else:
            cur.append(ch)
    parts.append("".join(cur))
    return [p.strip() for p in parts if p.strip()]


def expand_use(tree: str):
    """Every path a use tree names, as lists of segments (`a::{b, c::{d as e}}`: a::b, a::c::d)."""
    tree = " ".join(tree.split())
    brace = tree.find("{")
    if brace < 0:
        path = re.split(r"\s+as\s+", tree)[0].strip()
        segs = [p for p in path.split("::") if p]
        if segs and segs[-1] in ("self", "*"):
            segs = segs[:-1]
        return [segs] if segs else [[]]
    prefix = [p for p in tree[:brace].split("::") if p.strip()]
    inner = tree[brace + 1 : tree.rfind("}")]
    out = []
    for item in split_top(inner):
        for sub in expand_use(item):
            out.append(prefix + sub)
    return out


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


USE = re.compile(r"\buse\s+([^;]+);")


def references(text: str, here: tuple) -> set:
    """Module paths (as far as named) this file's code names."""
    found = set()
    code = LINE_COMMENT.sub("", text)
    for m in USE.finditer(code):
        for segs in expand_use(m.group(1)):
            if segs and segs[0] in ("crate", "super", "self"):
                found.add(resolve(here, segs[0], segs[1:]))
    for m in PATH.finditer(code):
        parts = [p for p in m.group(2).split("::") if p]
        found.add(resolve(here, m.group(1), parts))
    return found


def crate_graph(src: Path):
    files = [
        p
        for p in src.rglob("*.rs")
        if "tests" not in p.relative_to(src).parts
        and p.stem != "tests"
        # A program under src/bin is a crate of its own (checked on its own).
        and not (src.name == "src" and p.relative_to(src).parts[0] == "bin")
    ]
    modules = {module_path(src, f) for f in files}
    edges = {}
    for f in files:
        here = module_path(src, f)
        text = strip_tests(f.read_text(encoding="utf-8"))
        for target in references(text, here):
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


def with_programs(crates):
    """Each crate's src/, then each program under its src/bin/ that has modules of its own."""
    out = []
    for c in crates:
        out.append(c)
        bins = ROOT / c / "bin"
        if bins.is_dir():
            out += [str(d.relative_to(ROOT)) for d in sorted(bins.iterdir()) if d.is_dir()]
    return out


def main(argv):
    crates = argv[1:] or with_programs(workspace_crates())
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
