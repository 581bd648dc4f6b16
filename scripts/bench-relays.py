#!/usr/bin/env python3
"""Windowed CoAP against QUIC through two link emulators written apart: our own
(`coapcam netem`, with or without jitter) and scripts/relay.py (exact per-datagram delays
in Python, no jitter). Issue 33's benchmark: a figure that holds through both is not an
emulator's quirk.

For every emulator, loss rate and body size, RUNS runs of each mode, interleaved (run 1
of every mode, then run 2, ...), each through a fresh relay seeded alike for both modes:

  window   coapcam get URI -o FILE --json   against coapcam serve --no-cameras --static
  quic     quic-bench get ADDR CERT FILE    (quinn 0.11, BBR, one stream, handshake
                                            included) against quic-bench serve

Each run is the client's whole process, start to exit, and its output is compared with
the body byte for byte (a run that differs, fails or passes --cap is a failed run). The
window's `max_window` (most block requests in flight) comes from its --json line.
netem takes whole milliseconds of delay and jitter; relay.py takes fractions.

    python3 scripts/bench-relays.py --coapcam target/release/coapcam --runs 15

prints one Markdown table: per (emulator, loss, size) the median, 95th percentile
(nearest rank) and maximum of each mode in seconds, the ratio of the medians, the slowest
window run over QUIC's median, how many window runs took more than 3 times QUIC's median,
the smallest max_window of the window's runs, and the machine's 1-minute load average
(median and maximum over the row's runs). --demo-loop runs `coapcam demo` over and over
beside the benchmark (issue 33's "machine load" case). --json FILE writes every run;
--trace-dir DIR keeps each window run's congestion-controller trace, round by round.

Exit status: 0 when the benchmark ran (failed runs are results), 1 when it could not
(a program missing, a server that did not start).
"""

import argparse
import json
import os
import random
import re
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent


def free_udp_port():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def nearest_rank(values, p):
    v = sorted(values)
    if not v:
        return None
    k = max(1, -(-len(v) * p // 1))  # ceil(n p), at least 1
    return v[int(k) - 1]


def loadavg():
    return os.getloadavg()[0]


class Relay:
    """One emulator instance between a client and `forward`, until stopped."""

    def __init__(self, kind, coapcam, forward, delay_ms, loss, seed, jitter_ms):
        self.kind = kind
        if kind == "relay.py":
            cmd = [sys.executable, str(HERE / "relay.py"), "--forward", forward,
                   "--delay-ms", str(delay_ms), "--loss", str(loss), "--seed", str(seed)]
            self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                         text=True)
            line = self.proc.stdout.readline()
            m = re.match(r"listening (\S+)", line)
            if not m:
                raise RuntimeError(f"relay.py did not start: {line!r} {self.proc.stderr.read()}")
            self.addr = m.group(1)
        else:
            # netem takes whole milliseconds.
            cmd = [str(coapcam), "netem", "--listen", "127.0.0.1:0", "--forward", forward,
                   "--delay-ms", str(round(delay_ms)), "--loss", str(loss), "--seed", str(seed)]
            if jitter_ms:
                cmd += ["--jitter-ms", str(round(jitter_ms))]
            self.proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                         text=True)
            deadline = time.monotonic() + 20
            self.addr = None
            while time.monotonic() < deadline:
                line = self.proc.stderr.readline()
                m = re.search(r"listening on (\S+),", line)
                if m:
                    self.addr = m.group(1)
                    break
                if not line and self.proc.poll() is not None:
                    break
            if not self.addr:
                raise RuntimeError("coapcam netem did not start")

    def stop(self):
        self.proc.send_signal(signal.SIGINT)
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


def start_servers(coapcam, quic_bench, files, bodies, work):
    procs = []
    port = free_udp_port()
    serve = subprocess.Popen(
        [str(coapcam), "serve", "--no-cameras", "--static", str(files), "--bind",
         f"127.0.0.1:{port}"],
        stdout=subprocess.DEVNULL, stderr=open(work / "serve.log", "w"))
    procs.append(serve)
    coap_addr = f"127.0.0.1:{port}"
    deadline = time.monotonic() + 30
    while True:
        probe = subprocess.run(
            [str(coapcam), "get", f"coap://{coap_addr}/.well-known/core", "--timeout", "2"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        if probe.returncode == 0:
            break
        if time.monotonic() > deadline or serve.poll() is not None:
            raise RuntimeError(f"coapcam serve did not start: {(work / 'serve.log').read_text()}")
        time.sleep(0.2)
    quic = {}
    for size, path in bodies.items():
        cert = work / f"quic-{size}.der"
        p = subprocess.Popen([str(quic_bench), "serve", "127.0.0.1:0", str(path), str(cert)],
                             stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        procs.append(p)
        line = p.stdout.readline()
        m = re.match(r"ready (\S+)", line)
        if not m:
            raise RuntimeError(f"quic-bench serve did not start: {line!r}")
        quic[size] = (m.group(1), cert)
    return procs, coap_addr, quic


def run_client(mode, coapcam, quic_bench, addr, size, quic_cert, out, cap, trace=None):
    if out.exists():
        out.unlink()
    if mode == "window":
        cmd = [str(coapcam), "get", f"coap://{addr}/files/body-{size}.bin", "-o", str(out),
               "--json", "--transfer", "window"]
    else:
        cmd = [str(quic_bench), "get", addr, str(quic_cert), str(out)]
    env = None
    if trace and mode == "window":
        env = dict(os.environ, RUST_LOG="coap_net::congestion=trace")
    start = time.monotonic()
    try:
        done = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                              timeout=cap, env=env)
        if env:
            trace.write_text(done.stderr)
        took = time.monotonic() - start
        status = done.returncode
        stdout = done.stdout
        err = done.stderr.strip()[-300:]
    except subprocess.TimeoutExpired:
        return {"time_s": cap, "ok": False, "error": f"over the cap of {cap} s"}
    result = {"time_s": took, "exit": status}
    if mode == "window":
        for line in stdout.splitlines():
            try:
                path = json.loads(line).get("transfer") or {}
            except json.JSONDecodeError:
                continue
            result["max_window"] = path.get("max_window")
            result["blocks_lost"] = path.get("blocks_lost")
            result["retransmissions"] = path.get("retransmissions")
    if status != 0:
        result.update(ok=False, error=f"exit {status}: {err}")
    return result


def main():
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--coapcam", type=Path, default=ROOT / "target/release/coapcam")
    parser.add_argument("--quic-bench", type=Path,
                        help="default: next to --coapcam, or $COAPCAM_QUIC_BENCH")
    parser.add_argument("--sizes", default="921610,2764810")
    parser.add_argument("--losses", default="0,0.02", help="loss each way, comma-separated")
    parser.add_argument("--delay-ms", type=float, default=10.0, help="one-way delay")
    parser.add_argument("--emulators", default="netem,relay.py",
                        help="netem, netem-jitter (netem with ±JITTER ms) and relay.py")
    parser.add_argument("--jitter-ms", type=float, default=1.0,
                        help="netem-jitter's jitter each way")
    parser.add_argument("--modes", default="window,quic")
    parser.add_argument("--runs", type=int, default=15)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--cap", type=float, default=60.0, help="seconds a run may take")
    parser.add_argument("--demo-loop", action="store_true",
                        help="run `coapcam demo` in a loop beside the benchmark")
    parser.add_argument("--json", type=Path, help="write every run here")
    parser.add_argument("--trace-dir", type=Path,
                        help="write each window run's controller trace (RUST_LOG="
                             "coap_net::congestion=trace) into this directory")
    args = parser.parse_args()

    coapcam = args.coapcam.resolve()
    if args.quic_bench:
        quic_bench = args.quic_bench.resolve()
    elif os.environ.get("COAPCAM_QUIC_BENCH"):
        quic_bench = Path(os.environ["COAPCAM_QUIC_BENCH"])
    else:
        quic_bench = coapcam.parent / "quic-bench"
    modes = args.modes.split(",")
    for prog, needed in [(coapcam, True), (quic_bench, "quic" in modes)]:
        if needed and not Path(prog).is_file():
            print(f"bench-relays: {prog} not found (cargo build --release -p coapcam -p quic-bench)",
                  file=sys.stderr)
            return 1
    sizes = [int(s) for s in args.sizes.split(",")]
    losses = [float(x) for x in args.losses.split(",")]
    emulators = args.emulators.split(",")
    for e in emulators:
        if e not in ("netem", "netem-jitter", "relay.py"):
            print(f"bench-relays: unknown emulator {e}", file=sys.stderr)
            return 2

    work = Path(tempfile.mkdtemp(prefix="bench-relays-"))
    files = work / "files"
    files.mkdir()
    bodies = {}
    for size in sizes:
        rng = random.Random(f"{args.seed}/{size}")
        path = files / f"body-{size}.bin"
        path.write_bytes(rng.randbytes(size))
        bodies[size] = path
    procs = []
    demo = None
    results = []
    try:
        procs, coap_addr, quic = start_servers(coapcam, quic_bench, files, bodies, work)
        if args.demo_loop:
            demo_dir = work / "demo"
            demo = subprocess.Popen(
                ["sh", "-c", f'while true; do "{coapcam}" demo --dir "{demo_dir}" '
                             '>/dev/null 2>&1; done'],
                start_new_session=True)
        out = work / "out.bin"
        for emulator in emulators:
            for loss in losses:
                for size in sizes:
                    body = bodies[size].read_bytes()
                    for run in range(args.runs):
                        seed = args.seed * 1_000_003 + run * 7919 + size + int(loss * 1000)
                        for mode in modes:
                            forward = coap_addr if mode == "window" else quic[size][0]
                            relay = Relay(emulator.split("-")[0] if emulator != "relay.py"
                                          else emulator, coapcam, forward, args.delay_ms, loss,
                                          seed, args.jitter_ms if emulator == "netem-jitter" else 0)
                            load = loadavg()
                            try:
                                trace = None
                                if args.trace_dir:
                                    args.trace_dir.mkdir(parents=True, exist_ok=True)
                                    trace = args.trace_dir / (
                                        f"{emulator}-{loss:g}-{size}-{run + 1}.log")
                                r = run_client(mode, coapcam, quic_bench, relay.addr, size,
                                               quic[size][1], out, args.cap, trace)
                            finally:
                                relay.stop()
                            if "ok" not in r:
                                same = out.exists() and out.read_bytes() == body
                                r["ok"] = same
                                if not same:
                                    r["error"] = "the output differs from the body"
                            r.update(emulator=emulator, loss=loss, size=size, mode=mode,
                                     run=run + 1, seed=seed, load1=load)
                            results.append(r)
                            extra = f" max_window {r.get('max_window')}" if mode == "window" else ""
                            print(f"{emulator} {loss:g} {size} {mode} run {run + 1}/{args.runs}: "
                                  f"{r['time_s']:.3f} s {'ok' if r['ok'] else 'FAILED: ' + r.get('error', '')}"
                                  f"{extra} (load {load:.1f})", file=sys.stderr, flush=True)
    finally:
        if demo:
            os.killpg(demo.pid, signal.SIGTERM)
            demo.wait()
        for p in procs:
            p.terminate()
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
        shutil.rmtree(work, ignore_errors=True)

    print(table(results, emulators, losses, sizes, modes, args))
    if args.json:
        args.json.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()},
                                         "runs": results}, indent=1) + "\n")
    return 0


def table(results, emulators, losses, sizes, modes, args):
    lines = [
        f"{args.runs} runs per cell, {args.delay_ms:g} ms each way"
        f"{' , coapcam demo looping beside' if args.demo_loop else ''}; seconds of the "
        "client's whole process, median / p95 (nearest rank) / max of the successful runs, "
        "successful/runs; load: the 1-minute load average over the row's runs (median, max).",
        "",
        "| emulator | loss | bytes | " + " | ".join(f"{m} median / p95 / max" for m in modes)
        + " | window / QUIC | slowest window / QUIC median | window runs > 3x | "
          "smallest max_window | load |",
        "|---|---:|---:|" + "---:|" * len(modes) + "---:|---:|---:|---:|---:|",
    ]
    for e in emulators:
        for loss in losses:
            for size in sizes:
                row = [r for r in results if r["emulator"] == e and r["loss"] == loss
                       and r["size"] == size]
                if not row:
                    continue
                cells, med = [], {}
                for m in modes:
                    rs = [r for r in row if r["mode"] == m]
                    ok = [r["time_s"] for r in rs if r["ok"]]
                    if ok:
                        med[m] = statistics.median(ok)
                        cells.append(f"{med[m]:.3f} / {nearest_rank(ok, 0.95):.3f} / "
                                     f"{max(ok):.3f} {len(ok)}/{len(rs)}")
                    else:
                        cells.append(f"failed 0/{len(rs)}")
                win = [r for r in row if r["mode"] == "window"]
                win_ok = [r["time_s"] for r in win if r["ok"]]
                ratio = slowest = over = "-"
                if "window" in med and "quic" in med and med["quic"] > 0:
                    ratio = f"{med['window'] / med['quic']:.2f}x"
                    slowest = f"{max(win_ok) / med['quic']:.2f}x"
                    over = str(sum(1 for t in win_ok if t > 3 * med["quic"])
                               + sum(1 for r in win if not r["ok"]))
                windows = [r.get("max_window") for r in win if r.get("max_window") is not None]
                loads = [r["load1"] for r in row]
                lines.append(
                    f"| {e} | {loss * 100:g} % | {size} | " + " | ".join(cells)
                    + f" | {ratio} | {slowest} | {over} | {min(windows) if windows else '-'} | "
                      f"{statistics.median(loads):.1f}, {max(loads):.1f} |")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
