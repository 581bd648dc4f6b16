#!/usr/bin/env python3
"""Fails when a module of a workspace crate depends on itself through other modules.

For every crate root (src/lib.rs, src/main.rs) it follows the `mod name;` declarations to
the module files, reads each file's paths into the crate (`crate::a::b`, `super::a`,
`self::a`, and a child module named directly, e.g. `cams::Cams`, also inside `use` groups),
resolves each to the module that defines the item (through `pub use` re-exports, which are
a facade and make no edge themselves), and looks for strongly connected components in that
graph. A child that uses its parent's own items (`super::Type`) while the parent uses the
child is a cycle too. Inline modules (`mod tests { ... }`) are left out: nothing imports
them, so they close no cycle. Usage: scripts/module-cycles.py [CRATE_DIR ...] (default: crates/*).
"""

import glob
import os
import re
import sys

MOD_DECL = re.compile(r"^\s*(?:pub(?:\([^)]*\))?\s+)?mod\s+(\w+)\s*;", re.M)
INLINE_MOD = re.compile(r"^\s*(?:pub(?:\([^)]*\))?\s+)?mod\s+\w+\s*\{")
REEXPORT = re.compile(r"^\s*pub(?:\([^)]*\))?\s+use\s+([^;]+);", re.M)
PATH = re.compile(r"(?<![\w:])(crate|super|self|\w+)((?:::\w+)*)(::\{)?")


def module_tree(root_file):
    """Module path (tuple) -> file, following `mod x;` from the crate root."""
    modules = {(): root_file}
    todo = [()]
    while todo:
        path = todo.pop()
        file = modules[path]
        base = os.path.basename(file)
        folder = os.path.dirname(file)
        if base not in ("lib.rs", "main.rs", "mod.rs"):
            folder = os.path.join(folder, base[:-3])
        for name in MOD_DECL.findall(strip_comments(open(file).read())):
            for candidate in (os.path.join(folder, name + ".rs"), os.path.join(folder, name, "mod.rs")):
                if os.path.exists(candidate):
                    modules[path + (name,)] = candidate
                    todo.append(path + (name,))
    return modules


def strip_comments(text):
    text = re.sub(r"//[^\n]*", "", text)
    return re.sub(r'"(?:\\.|[^"\\])*"', '""', text)


def group_heads(text, start):
    """The first segments of the paths of a `{a, b::c, d::{e}}` group starting at `start`."""
    depth, item, heads = 0, "", []
    for ch in text[start:]:
        if ch == "{":
            depth += 1
            if depth == 1:
                continue
        elif ch == "}":
            depth -= 1
            if depth == 0:
                break
        if depth == 1 and ch == ",":
            heads.append(item)
            item = ""
        elif depth >= 1:
            item += ch
    heads.append(item)
    return [h.strip().split("::") for h in heads if h.strip()]


def references(modules, source, text):
    """(base module, path segments) of every path into the crate in a module's text."""
    inline_at = []
    stack, depth, pos = [], 0, 0
    for line in text.splitlines(keepends=True):
        if INLINE_MOD.match(line):
            stack.append(depth)
        inline_at.append((pos, len(stack)))
        depth += line.count("{") - line.count("}")
        while stack and depth <= stack[-1]:
            stack.pop()
        pos += len(line)
    out = []
    for m in PATH.finditer(text):
        head, rest, group = m.group(1), m.group(2), m.group(3)
        if not rest and not group:
            continue
        if max((n for p, n in inline_at if p <= m.start()), default=0):
            # Inside an inline module (`mod tests { ... }`): a module of its own, which
            # nothing imports, so it closes no cycle.
            continue
        if head == "crate":
            base = ()
        elif head == "super":
            base = source[:-1]
        elif head == "self":
            base = source
        elif source + (head,) in modules:
            base = source + (head,)
        else:
            continue
        prefix = [seg for seg in rest.split("::") if seg]
        if group:
            tails = [prefix + h for h in group_heads(text, m.end() - 1)]
        else:
            tails = [prefix]
        out.extend((m.start(), base, tail) for tail in tails)
    return out


def resolve(modules, aliases, base, tail, seen=()):
    """The module that defines what `base::tail` names, through `pub use` re-exports."""
    target = base
    for seg in tail:
        if seg == "super":
            target = target[:-1]
        elif target + (seg,) in modules:
            target = target + (seg,)
        elif (target, seg) in aliases and (target, seg) not in seen:
            alias_base, alias_tail = aliases[(target, seg)]
            return resolve(modules, aliases, alias_base, alias_tail, seen + ((target, seg),))
        else:
            break
    return target


def edges(modules):
    texts = {m: strip_comments(open(f).read()) for m, f in modules.items()}
    refs = {m: references(modules, m, t) for m, t in texts.items()}
    # `pub use a::b::{X, Y}` in module M: M::X is a::b's X.
    # A re-export is a facade, not a use: it makes no edge of its own.
    aliases, facade = {}, set()
    for m, text in texts.items():
        spans = [(r.start(), r.end()) for r in REEXPORT.finditer(text)]
        for at, base, tail in refs[m]:
            if any(a <= at < b for a, b in spans) and tail:
                name = tail[-1].split(" as ")[-1].strip()
                aliases[(m, name)] = (base, tail)
                facade.add((m, at, tuple(tail)))
    graph = {m: set() for m in modules}
    for source in modules:
        for at, base, tail in refs[source]:
            if (source, at, tuple(tail)) in facade:
                continue
            target = resolve(modules, aliases, base, tail)
            if target != source:
                graph[source].add(target)
    return graph


def cycles(graph):
    index, low, on, stack, out, counter = {}, {}, set(), [], [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            scc = []
            while True:
                w = stack.pop()
                on.discard(w)
                scc.append(w)
                if w == v:
                    break
            if len(scc) > 1:
                out.append(scc)

    sys.setrecursionlimit(10000)
    for v in graph:
        if v not in index:
            visit(v)
    return out


def main():
    crates = sys.argv[1:] or sorted(glob.glob("crates/*"))
    found = 0
    for crate in crates:
        for root in ("src/lib.rs", "src/main.rs"):
            root_file = os.path.join(crate, root)
            if not os.path.exists(root_file):
                continue
            graph = edges(module_tree(root_file))
            for scc in cycles(graph):
                found += 1
                names = sorted("::".join(m) or "(root)" for m in scc)
                print(f"{root_file}: import cycle among {', '.join(names)}")
                for m in sorted(scc):
                    deps = sorted("::".join(t) or "(root)" for t in graph[m] if t in scc)
                    print(f"    {'::'.join(m) or '(root)'} -> {', '.join(deps)}")
    if found:
        sys.exit(1)
    print(f"module-cycles: no import cycle in {len(crates)} crate(s)")


if __name__ == "__main__":
    main()
