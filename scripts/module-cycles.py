#!/usr/bin/env python3
"""Fails when a module of a workspace crate depends on itself through other modules.

For every crate root (src/lib.rs, src/main.rs) it follows the `mod name;` declarations to
the module files, reads each file's paths into the crate (`crate::a::b`, `super::a`,
`self::a`, and a child module named directly, e.g. `cams::Cams`, also inside `use` groups),
resolves each to the module that defines the item (through `pub use` re-exports, which are
a facade and make no edge themselves), and looks for strongly connected components in that
graph. A child that uses its parent's own items (`super::Type`) while the parent uses the
child is a cycle too. A path in a `macro_rules!` body that names a macro variable
(`super::$name::Args`, `$name::Args`) is read once for each identifier the macro's
invocations in the same file pass (`outputs!(mqtt, line)`: `super::mqtt::Args`,
`super::line::Args`); `$crate::a` is `crate::a`. A macro whose body declares `mod $name;`
declares a module of each identifier its invocations in the same file pass
(`backends!(realsense, recording)`). Inline modules (`mod tests { ... }`) are left out: nothing imports
them, so they close no cycle. The same graph, between the modules of one folder, is held
against ARCHITECTURE.md's fenced `layers` blocks (a module uses only those in the lines
below its own) and `apart` blocks (a module of one line never uses one of another), each
named by the folder's file. Usage: scripts/module-cycles.py [CRATE_DIR ...] (default:
crates/*).
"""

import bisect
import glob
import os
import re
import sys

MOD_DECL = re.compile(r"^\s*(?:pub(?:\([^)]*\))?\s+)?mod\s+(\w+)\s*;", re.M)
INLINE_MOD = re.compile(r"^\s*(?:pub(?:\([^)]*\))?\s+)?mod\s+\w+\s*\{")
REEXPORT = re.compile(r"^\s*pub(?:\([^)]*\))?\s+use\s+([^;]+);", re.M)
RAW_STRING = re.compile(r'r(#*)"')
PATH = re.compile(r"(?<![\w:])(crate|super|self|\w+)((?:::\w+)*)(::\{)?")
MACRO_DEF = re.compile(r"macro_rules!\s*(\w+)\s*\{")
MACRO_PATH = re.compile(r"(?<![\w:$])\$?\w+(?:::\$?\w+)+")
MACRO_VAR = re.compile(r"\$(?!crate\b)\w+")
MACRO_MOD = re.compile(r"\bmod\s+\$\w+\s*;")
CLOSE = {"{": "}", "(": ")", "[": "]"}


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
        text = strip_comments(open(file).read())
        for name in MOD_DECL.findall(text) + macro_mods(text):
            for candidate in (os.path.join(folder, name + ".rs"), os.path.join(folder, name, "mod.rs")):
                if os.path.exists(candidate):
                    modules[path + (name,)] = candidate
                    todo.append(path + (name,))
    return modules


def raw_prefix_starts(text, i):
    """Whether the `r` at `i` starts a token (`r"`, or `br"`), not ends a name (`for_r"`)."""

    def ident(at):
        return at >= 0 and (text[at].isalnum() or text[at] == "_")

    return not ident(i - 1) or (text[i - 1] == "b" and not ident(i - 2))


def strip_comments(text):
    """The text with comments removed and every string and char literal emptied (`""`,
    `' '`), newlines kept. A lexer, not patterns: `"coap://h"` holds no comment, `'"'` opens
    no string, `/* /* */ */` nests, `r#"..."#` ends at its own hashes."""
    out, i, n = [], 0, len(text)
    while i < n:
        c = text[i]
        nxt = text[i + 1] if i + 1 < n else ""
        if c == "/" and nxt == "/":
            while i < n and text[i] != "\n":
                i += 1
        elif c == "/" and nxt == "*":
            depth, i = 1, i + 2
            while i < n and depth:
                if text.startswith("/*", i):
                    depth, i = depth + 1, i + 2
                elif text.startswith("*/", i):
                    depth, i = depth - 1, i + 2
                else:
                    out.append("\n" if text[i] == "\n" else "")
                    i += 1
        elif c == '"':
            i += 1
            while i < n and text[i] != '"':
                out.append("\n" if text[i] == "\n" else "")
                i += 2 if text[i] == "\\" else 1
            out.append('""')
            i += 1
        elif c == "r" and RAW_STRING.match(text, i) and raw_prefix_starts(text, i):
            raw = RAW_STRING.match(text, i)
            end = '"' + raw.group(1)
            j = text.find(end, i + len(raw.group(0)))
            j = n if j < 0 else j
            out.append('""' + "\n" * text.count("\n", i, j))
            i = j + len(end)
        elif c == "'":
            if nxt == "\\":
                j = text.find("'", i + 3)
                i = n if j < 0 else j + 1
                out.append("' '")
            elif i + 2 < n and text[i + 2] == "'":
                out.append("' '")
                i += 3
            else:
                out.append(c)
                i += 1
        else:
            out.append(c)
            i += 1
    return "".join(out)


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


def closing(text, start):
    """The index of the bracket that closes the one at `start` (the text's end if none)."""
    depth = 0
    for i in range(start, len(text)):
        if text[i] in CLOSE:
            depth += 1
        elif text[i] in CLOSE.values():
            depth -= 1
            if depth == 0:
                return i
    return len(text)


def macros(text):
    """(start of its body, end of its body, identifiers passed) for each `macro_rules!` of
    `text`: the identifiers its invocations in `text` pass."""
    out = []
    for d in MACRO_DEF.finditer(text):
        end = closing(text, d.end() - 1)
        passed = set()
        for call in re.finditer(r"(?<![\w$])" + d.group(1) + r"!\s*([({\[])", text):
            if d.start() <= call.start() <= end:
                continue
            passed.update(re.findall(r"\w+", text[call.end() : closing(text, call.end() - 1)]))
        out.append((d.end(), end, passed))
    return out


def macro_mods(text):
    """The modules a `macro_rules!` of `text` declares (`$(pub mod $name;)+`): the
    identifiers its invocations in `text` pass."""
    return sorted(
        ident
        for start, end, passed in macros(text)
        if MACRO_MOD.search(text, start, end)
        for ident in passed
    )


def macro_paths(text):
    """(position, path) for each path in a `macro_rules!` body of `text` that names a macro
    variable, once with each identifier that the macro's invocations in `text` pass in
    place of the variables."""
    out = []
    for start, end, passed in macros(text):
        for p in MACRO_PATH.finditer(text, start, end):
            if MACRO_VAR.search(p.group(0)):
                out.extend((p.start(), MACRO_VAR.sub(ident, p.group(0))) for ident in sorted(passed))
    return out


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
    found = [(m.start(), text, m) for m in PATH.finditer(text)]
    for at, path in macro_paths(text):
        found.extend((at, path, m) for m in PATH.finditer(path))
    for at, within, m in found:
        head, rest, group = m.group(1), m.group(2), m.group(3)
        if not rest and not group:
            continue
        line = bisect.bisect_right(inline_at, (at, float("inf"))) - 1
        if line >= 0 and inline_at[line][1]:
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
            tails = [prefix + h for h in group_heads(within, m.end() - 1)]
        else:
            tails = [prefix]
        out.extend((at, base, tail) for tail in tails)
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


def folders(graph, within=()):
    """The graph between the modules directly in module `within` (a folder and all below
    it is one) and `within` itself; the crate's top-level modules by default. Edges that
    leave `within` are left out."""
    depth = len(within)

    def child(module):
        return module[: depth + 1] if module[:depth] == within else None

    out = {}
    for source, targets in graph.items():
        s = child(source)
        if s is None:
            continue
        out.setdefault(s, set())
        out[s].update(t for t in map(child, targets) if t is not None and t != s)
    return out


def stated_groups(map_file, kind):
    """Module file -> the lines of the map's fenced blocks of `kind` (`layers`, `apart`)
    opened by ```` ```KIND crates/x/src/a/mod.rs ````, each line's words (a block may be
    indented, inside a list item)."""
    out = {}
    if not os.path.exists(map_file):
        return out
    pattern = r"^[ \t]*```" + kind + r"[ \t]+(\S+)[ \t]*\n(.*?)^[ \t]*```"
    for m in re.finditer(pattern, open(map_file).read(), re.M | re.S):
        out[m.group(1)] = [line.split() for line in m.group(2).splitlines() if line.split()]
    return out


def apart_problems(top, groups, within):
    """What breaks "a module of one group (a line) never uses one of another group" among
    the modules in `within`."""
    group = {}
    out = []
    for i, names in enumerate(groups):
        for name in names:
            group[within + (name,)] = i
    for module in sorted(m for m in group if m not in top):
        out.append(f"{'::'.join(module)} is in a group but not a module of the crate")
    for source in sorted(top):
        for target in sorted(top[source]):
            if source in group and target in group and group[source] != group[target]:
                out.append(f"{'::'.join(source)} uses {'::'.join(target)}, of another group")
    return out


def stated_layers(map_file):
    """Module file -> its child modules' layers, top first, from the map's fenced blocks
    opened by ```` ```layers crates/x/src/lib.rs ```` (a crate root: its top-level
    modules) or ```` ```layers crates/x/src/a/mod.rs ```` (module `a`: the modules in its
    folder): one layer a line. `self` in a layer is the module's own file; without it,
    that file is below every layer."""
    return stated_groups(map_file, "layers")


def layer_problems(top, layers, within=()):
    """What breaks "a module uses only the modules in the layers below its own" among the
    modules in `within` (by default the crate's top-level modules; `within`'s own file,
    unless a layer names it `self`, below them all, using none)."""
    rank = {}
    out = []
    for i, layer in enumerate(layers):
        for name in layer:
            rank[within if name == "self" else within + (name,)] = i
    rank.setdefault(within, len(layers))

    def name(module):
        return "::".join(module) or "(root)"

    for module in sorted(top):
        if module not in rank:
            out.append(f"{name(module)} is in no layer")
    for module in sorted(m for m in rank if m not in top and m != within):
        out.append(f"{name(module)} is in a layer but not a module of the crate")
    for source in sorted(top):
        for target in sorted(top[source]):
            if source in rank and target in rank and rank[target] <= rank[source]:
                where = "the same layer" if rank[target] == rank[source] else "a layer above"
                out.append(f"{name(source)} uses {name(target)}, in {where}")
    return out


def check(crates, map_file, base="."):
    """Every problem found, as lines of text."""
    layers = stated_layers(map_file)
    apart = stated_groups(map_file, "apart")
    out = []
    for crate in crates:
        for root in ("src/lib.rs", "src/main.rs"):
            root_file = os.path.join(crate, root)
            if not os.path.exists(root_file):
                continue
            modules = module_tree(root_file)
            graph = edges(modules)
            for scc in cycles(graph):
                names = sorted("::".join(m) or "(root)" for m in scc)
                out.append(f"{root_file}: import cycle among {', '.join(names)}")
                for m in sorted(scc):
                    deps = sorted("::".join(t) or "(root)" for t in graph[m] if t in scc)
                    out.append(f"    {'::'.join(m) or '(root)'} -> {', '.join(deps)}")
            top = folders(graph)
            for scc in cycles(top):
                names = sorted("::".join(m) or "(root)" for m in scc)
                out.append(f"{root_file}: top-level modules import each other: {', '.join(names)}")
                for m in sorted(scc):
                    for t in sorted(t for t in top[m] if t in scc):
                        via = sorted(
                            "::".join(s) + " -> " + "::".join(d)
                            for s, ds in graph.items()
                            if s[:1] == m
                            for d in ds
                            if d[:1] == t
                        )
                        out.append(f"    {'::'.join(m) or '(root)'} -> {'::'.join(t) or '(root)'} ({'; '.join(via)})")
            for module, file in sorted(modules.items()):
                key = os.path.relpath(file, base)
                top = folders(graph, module)
                for problem in layer_problems(top, layers[key], module) if key in layers else []:
                    out.append(f"{file}: not as {os.path.basename(map_file)} layers it: {problem}")
                for problem in apart_problems(top, apart[key], module) if key in apart else []:
                    out.append(f"{file}: not as {os.path.basename(map_file)} keeps it apart: {problem}")
    return out


def self_test():
    """The checker on small crates written for it: what it must find, and not find."""
    import tempfile

    cases = [
        # A folder cycle: no file imports one that imports it back.
        ({"lib.rs": "mod a;\nmod b;\n", "a/mod.rs": "mod x;", "a/x.rs": "use crate::b::Y;",
          "b.rs": "pub struct Y; fn f() { crate::a::x::g() }"}, None, ["top-level modules import each other: a, b"]),
        # A path after a URL in a string is a path; a char '"' opens no string.
        ({"lib.rs": "mod a;\nmod b;\n", "a.rs": 'const U: &str = "coap://h"; use crate::b::Y; const Q: char = \'"\';',
          "b.rs": "use crate::a::U;"}, None, ["import cycle among a, b"]),
        # An inline test module before a real use leaves it a use.
        ({"lib.rs": "mod a;\nmod b;\n", "a.rs": "mod tests {\n}\nuse crate::b::Y;\n", "b.rs": "use crate::a::Z;"}, None,
         ["import cycle among a, b"]),
        # Layers: upward and sideways uses, an unlisted module.
        ({"lib.rs": "mod a;\nmod b;\nmod c;\nmod d;\n", "a.rs": "", "b.rs": "use crate::a::X;", "c.rs": "use crate::d::X;",
          "d.rs": ""}, "a\nb\nc d\n", ["b uses a, in a layer above", "c uses d, in the same layer"]),
        ({"lib.rs": "mod a;\nmod b;\n", "a.rs": "use crate::b::X;", "b.rs": ""}, "a\n", ["b is in no layer"]),
        # A macro's paths through its variables, with the identifiers its invocation passes.
        ({"lib.rs": "mod s;\n", "s/mod.rs": "mod a;\nmod b;\n",
          "s/a.rs": "macro_rules! all { ($($n:ident),+) => { $(use super::$n::Args;)+ }; }\nall!(b);\n",
          "s/b.rs": "use super::a::X;"}, None, ["import cycle among s::a, s::b"]),
        ({"lib.rs": "mod a;\n", "a/mod.rs": "mod b;\nmacro_rules! m { ($n:ident) => { $n::Y }; }\nfn f() { m!(b) }\n",
          "a/b.rs": "use super::X;"}, None, ["import cycle among a, a::b"]),
        # Modules a macro declares, with the identifiers its invocation passes.
        ({"lib.rs": "mod s;\n", "s/mod.rs": "macro_rules! all { ($($n:ident),+) => { $(pub mod $n;)+ }; }\nall!(a, b);\n",
          "s/a.rs": "use super::b::X;", "s/b.rs": "use super::a::Y;"}, None, ["import cycle among s::a, s::b"]),
        ({"lib.rs": "mod a;\nmod b;\n", "a.rs": "macro_rules! m { () => { $crate::b::Y }; }\n",
          "b.rs": "use crate::a::X;"}, None, ["import cycle among a, b"]),
        # Clean: downward only.
        ({"lib.rs": "mod a;\nmod b;\n", "a.rs": "use crate::b::X;", "b.rs": ""}, "a\nb\n", []),
        # Layers of the modules in a folder (a/mod.rs), its own file placed by `self`: a
        # child that imports its sibling, the folder's file that uses a child above it.
        ({"lib.rs": "mod a;\n", "a/mod.rs": "mod x;\nmod y;\nmod v;\nuse v::W;\n",
          "a/x.rs": "use super::y::Y; use super::Z;", "a/y.rs": "", "a/v.rs": ""},
         {"a/mod.rs": "x y\nself\nv\n"}, ["a::x uses a::y, in the same layer"]),
        ({"lib.rs": "mod a;\n", "a/mod.rs": "mod x;\nmod v;\nuse v::W;\n", "a/x.rs": "use super::Z;",
          "a/v.rs": ""}, {"a/mod.rs": "x\nv\n"}, ["a uses a::v, in a layer above"]),
        ({"lib.rs": "mod a;\n", "a/mod.rs": "mod x;\nmod v;\nuse v::W;\n", "a/x.rs": "use super::Z;",
          "a/v.rs": "use crate::b::Q;"}, {"a/mod.rs": "x\nself\nv\n"}, []),
        # Groups kept apart: a module of one never uses one of another, at any depth
        # below them; within a group, and to a module in none, uses are free.
        ({"lib.rs": "mod e;\n", "e/mod.rs": "mod c;\nmod cs;\nmod s;\nmod ss;\nmod t;\n",
          "e/c.rs": "use super::cs::A; use super::t::T;", "e/cs.rs": "use super::ss::B;",
          "e/s.rs": "use super::ss::B;", "e/ss.rs": "", "e/t.rs": ""},
         {"apart e/mod.rs": "c cs\ns ss\n"}, ["e::cs uses e::ss, of another group"]),
        ({"lib.rs": "mod e;\n", "e/mod.rs": "mod c;\nmod s;\n", "e/c.rs": "use super::s::X;", "e/s.rs": ""},
         {"apart e/mod.rs": "c\ns\n"}, ["e::c uses e::s, of another group"]),
        ({"lib.rs": "mod e;\n", "e/mod.rs": "mod c;\nmod s;\nmod t;\n", "e/c.rs": "use super::t::X;",
          "e/s.rs": "use super::t::X;", "e/t.rs": ""}, {"apart e/mod.rs": "c\ns\n"}, []),
    ]
    failed = 0
    for n, (files, layers, expected) in enumerate(cases):
        with tempfile.TemporaryDirectory() as tmp:
            crate = os.path.join(tmp, "crates", "t")
            for name, text in files.items():
                path = os.path.join(crate, "src", name)
                os.makedirs(os.path.dirname(path), exist_ok=True)
                with open(path, "w") as f:
                    f.write(text)
            map_file = os.path.join(tmp, "MAP.md")
            if isinstance(layers, str):
                layers = {"lib.rs": layers}
            with open(map_file, "w") as f:
                for key, block in (layers or {}).items():
                    kind, file = key.split() if " " in key else ("layers", key)
                    f.write(f"```{kind} crates/t/src/{file}\n{block}```\n")
            found = check([crate], map_file, tmp)
            missing = [e for e in expected if not any(e in line for line in found)]
            if missing or (not expected and found):
                failed += 1
                print(f"self-test case {n}: expected {expected}, found {found}")
    # A block indented inside a list item is read as one at the margin.
    with tempfile.TemporaryDirectory() as tmp:
        map_file = os.path.join(tmp, "MAP.md")
        with open(map_file, "w") as f:
            f.write("- `x/`:\n\n  ```layers crates/t/src/x/mod.rs\n  self\n  a b\n  ```\n")
        found = stated_layers(map_file)
        if found != {"crates/t/src/x/mod.rs": [["self"], ["a", "b"]]}:
            failed += 1
            print(f"self-test: an indented block read as {found}")
    if failed:
        sys.exit(1)
    print(f"module-cycles: self-test passed ({len(cases) + 1} cases)")


def main():
    if sys.argv[1:] == ["--self-test"]:
        self_test()
        return
    crates = sys.argv[1:] or sorted(glob.glob("crates/*"))
    repo = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
    problems = check(crates, os.path.join(repo, "ARCHITECTURE.md"), repo)
    for line in problems:
        print(line)
    if problems:
        sys.exit(1)
    print(f"module-cycles: no import cycle, folders in one direction, in {len(crates)} crate(s)")


if __name__ == "__main__":
    main()
