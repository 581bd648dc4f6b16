#!/usr/bin/env python3
"""Fails when the map names what the code does not have: in ARCHITECTURE.md and
docs/design.md, a file or folder in backticks (`station/reads.rs`, `kinds/`) that no
tracked path ends with, a Rust path in backticks (`follow::run`, `coap::Limits`) whose
last name no source file's code (comments and strings left out) has, or a crate in design.md's layout table said
to depend on a crate its Cargo.toml does not list. It checks names, not sentences: what
a module does is read by people (ARCHITECTURE.md says so). Usage: scripts/map-names.py
[--self-test].
"""

import importlib.util
import os
import re
import subprocess
import sys
import tomllib

_spec = importlib.util.spec_from_file_location(
    "module_cycles", os.path.join(os.path.dirname(os.path.abspath(__file__)), "module-cycles.py")
)
module_cycles = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(module_cycles)

DOCS = ("ARCHITECTURE.md", "docs/design.md")
TICKED = re.compile(r"`([^`\n]+)`")
RUST_PATH = re.compile(r"^(?:[A-Za-z_]\w*::)+([A-Za-z_]\w*)(?:!|\(\))?$")
TABLE_ROW = re.compile(r"^\| `crates/([\w-]+)` \|.*\| ([^|]+) \|\s*$", re.M)


def file_names(text):
    """The files and folders a text names in backticks (not templates, globs or URIs)."""
    out = set()
    for ticked in TICKED.findall(text):
        for word in re.split(r"[\s,()]+", ticked):
            word = word.rstrip(".:;")
            if not word or any(c in word for c in "<*$") or "://" in word or word.startswith(("/", "~", "-")):
                continue
            if word.endswith(".rs") or (word.endswith("/") and len(word) > 1):
                out.add(word)
    return out


def rust_names(text):
    """The last names of the Rust paths (`a::b`) a text names in backticks."""
    return {m.group(1) for t in TICKED.findall(text) if (m := RUST_PATH.match(t.strip()))}


def said_dependencies(design):
    """Crate -> the crates design.md's layout table says it depends on."""
    out = {}
    for m in TABLE_ROW.finditer(design):
        words = [w.strip("` ") for w in m.group(2).split(",")]
        out[m.group(1)] = [w for w in words if re.fullmatch(r"[\w-]+", w)]
    return out


def problems(root):
    """Every name the map gives that the code lacks, as lines of text."""
    tracked = subprocess.run(["git", "ls-files"], cwd=root, capture_output=True, text=True, check=True)
    paths = ["/" + p for p in tracked.stdout.split()]
    folders = {p[: i + 1] for p in paths for i in range(len(p)) if p[i] == "/"}
    sources = "\n".join(
        module_cycles.strip_comments(open(os.path.join(root, p[1:]), errors="replace").read())
        for p in paths
        if p.endswith(".rs")
    )
    identifiers = set(re.findall(r"[A-Za-z_]\w*", sources))
    out = []
    for doc in DOCS:
        text = open(os.path.join(root, doc)).read()
        for name in sorted(file_names(text)):
            tail = "/" + name
            if not (any(p.endswith(tail) for p in paths) or any(f.endswith(tail) for f in folders)):
                out.append(f"{doc}: `{name}`: no such file or folder")
        for name in sorted(rust_names(text)):
            if name not in identifiers:
                out.append(f"{doc}: `...::{name}`: named nowhere in the sources")
    design = open(os.path.join(root, "docs/design.md")).read()
    for crate, said in sorted(said_dependencies(design).items()):
        manifest = os.path.join(root, "crates", crate, "Cargo.toml")
        if not os.path.exists(manifest):
            out.append(f"docs/design.md: crates/{crate} is no crate")
            continue
        toml = tomllib.load(open(manifest, "rb"))
        deps = set(toml.get("dependencies", {}))
        for target in toml.get("target", {}).values():
            deps |= set(target.get("dependencies", {}))
        for dep in said:
            if dep not in deps and dep not in ("all", "above"):
                out.append(f"docs/design.md: crates/{crate} is said to depend on {dep}, which its Cargo.toml does not list")
    return out


def self_test():
    """The readers on small texts: what they must find, and not find."""
    failed = []
    found = file_names("`station/reads.rs`, `kinds/` (`<output>.rs`, `*_state.rs`, `coap://h/`, `/cams/`)")
    if found != {"station/reads.rs", "kinds/"}:
        failed.append(f"file names: {found}")
    found = rust_names("`follow::run`, `coap::Limits`, `outputs!`, `Sink`, `a::b()`, `x :: y`")
    if found != {"run", "Limits", "b"}:
        failed.append(f"rust names: {found}")
    table = "| crate | what | depends on |\n|---|---|---|\n| `crates/netem` | a relay | tokio, rand |\n"
    found = said_dependencies(table)
    if found != {"netem": ["tokio", "rand"]}:
        failed.append(f"dependencies: {found}")
    for line in failed:
        print(f"self-test: {line}")
    if failed:
        sys.exit(1)
    print("map-names: self-test passed (3 cases)")


def main():
    if sys.argv[1:] == ["--self-test"]:
        self_test()
        return
    root = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
    found = problems(root)
    for line in found:
        print(line)
    if found:
        sys.exit(1)
    print(f"map-names: every file, Rust path and dependency {' and '.join(DOCS)} name is in the code")


if __name__ == "__main__":
    main()
