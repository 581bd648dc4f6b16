#!/usr/bin/env python3
"""Fails when a command of `coapcam` grows back into the library's work: a file of
crates/coapcam/src/cli/ over 600 lines, or a command's `run` (any `fn run` there) over 80
lines, from its `fn` to its closing brace. A command that needs more has work that belongs
in the library (ARCHITECTURE.md, "crates/coapcam"). Comments and strings are read as the
import check reads them (scripts/module-cycles.py), so a brace in either counts for
nothing. Usage: scripts/cli-size.py [--self-test] [CLI_DIR] (default:
crates/coapcam/src/cli).
"""

import glob
import importlib.util
import os
import re
import sys

MAX_FILE = 600
MAX_RUN = 80
RUN = re.compile(r"\bfn\s+run\s*[<(]")

_spec = importlib.util.spec_from_file_location(
    "module_cycles", os.path.join(os.path.dirname(os.path.abspath(__file__)), "module-cycles.py")
)
module_cycles = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(module_cycles)


def problems(cli_dir):
    """Every file and `run` over its limit, as lines of text."""
    files = sorted(glob.glob(os.path.join(cli_dir, "**", "*.rs"), recursive=True))
    if not files:
        return [f"{cli_dir}: no .rs file (is it the cli/ folder?)"]
    out = []
    for file in files:
        raw = open(file).read()
        lines = raw.count("\n") + (not raw.endswith("\n") and bool(raw))
        if lines > MAX_FILE:
            out.append(f"{file}: {lines} lines, over {MAX_FILE}")
        text = module_cycles.strip_comments(raw)
        for m in RUN.finditer(text):
            body = text.find("{", m.end())
            end = module_cycles.closing(text, body)
            length = text.count("\n", m.start(), end) + 1
            if length > MAX_RUN:
                line = text.count("\n", 0, m.start()) + 1
                out.append(f"{file}:{line}: run is {length} lines, over {MAX_RUN}")
    return out


def self_test():
    """The check on small folders written for it: what it must find, and not find."""
    import tempfile

    def run_of(n):
        return "pub async fn run(args: Args) -> anyhow::Result<()> {\n" + "    x();\n" * (n - 2) + "}\n"

    cases = [
        ({"a.rs": run_of(80)}, []),
        ({"a.rs": run_of(81)}, ["a.rs:1: run is 81 lines, over 80"]),
        # A brace in a string or a comment neither ends nor lengthens it.
        ({"a.rs": run_of(80).replace("x();", 'x("}"); // }', 1)}, []),
        ({"b/c.rs": "fn run() {\n}\n" + "\n" * 599}, ["c.rs: 601 lines, over 600"]),
        ({"b/c.rs": "fn run() {\n}\n" + "\n" * 598}, []),
    ]
    failed = 0
    for n, (files, expected) in enumerate(cases):
        with tempfile.TemporaryDirectory() as tmp:
            for name, text in files.items():
                path = os.path.join(tmp, name)
                os.makedirs(os.path.dirname(path), exist_ok=True)
                with open(path, "w") as f:
                    f.write(text)
            found = problems(tmp)
            missing = [e for e in expected if not any(e in line for line in found)]
            if missing or len(found) != len(expected):
                failed += 1
                print(f"self-test case {n}: expected {expected}, found {found}")
    if failed:
        sys.exit(1)
    print(f"cli-size: self-test passed ({len(cases)} cases)")


def main():
    if sys.argv[1:] == ["--self-test"]:
        self_test()
        return
    repo = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
    cli_dir = sys.argv[1] if sys.argv[1:] else os.path.join(repo, "crates/coapcam/src/cli")
    found = problems(cli_dir)
    for line in found:
        print(line)
    if found:
        sys.exit(1)
    print(f"cli-size: no cli/ file over {MAX_FILE} lines, no run over {MAX_RUN}")


if __name__ == "__main__":
    main()
