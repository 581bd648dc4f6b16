#!/usr/bin/env python3
"""Issue 33's first-request figure: the wall time of many `coapcam measure --all --clouds`
processes against the demo scene through a lossy link, with and without the round trips
remembered between processes (coapcam::client::rtt_cache; COAPCAM_RTT_CACHE=off).

Each CLI process starts a new endpoint. Without a remembered round trip, a lost first
CON waits ACK_TIMEOUT (2-3 s); with one, about 120-180 ms at 20 ms. The script starts
`coapcam serve --scene scenes/demo.toml` (state in a scratch directory), prepares its
cameras once (`measure --prepare`), then runs PROCESSES measure processes one after the
other through the emulator (`coapcam netem`, or scripts/relay.py with --emulator
relay.py), in each mode given by --cache (on, off, or both alternating), every process
through a fresh relay with its own seed. The cache lives in a scratch XDG_CACHE_HOME.

    python3 scripts/bench-first-request.py --coapcam target/release/coapcam --processes 50

prints per mode the median, p95 (nearest rank) and maximum wall time, how many processes
took over one second and how many failed, with the 1-minute load average.
"""

import argparse
import json
import os
import re
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
    k = max(1, -(-len(v) * p // 1))
    return v[int(k) - 1]


def start_relay(kind, coapcam, forward, delay_ms, loss, seed):
    if kind == "relay.py":
        p = subprocess.Popen([sys.executable, str(HERE / "relay.py"), "--forward", forward,
                              "--delay-ms", str(delay_ms), "--loss", str(loss),
                              "--seed", str(seed)],
                             stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        m = re.match(r"listening (\S+)", p.stdout.readline())
    else:
        p = subprocess.Popen([str(coapcam), "netem", "--listen", "127.0.0.1:0", "--forward",
                              forward, "--delay-ms", str(round(delay_ms)), "--loss", str(loss),
                              "--seed", str(seed)],
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        m = None
        for _ in range(50):
            line = p.stderr.readline()
            m = re.search(r"listening on (\S+),", line)
            if m or not line:
                break
    if not m:
        p.kill()
        raise RuntimeError(f"{kind} did not start")
    return p, m.group(1)


def stop(p):
    p.send_signal(signal.SIGINT)
    try:
        p.wait(timeout=10)
    except subprocess.TimeoutExpired:
        p.kill()
        p.wait()


def main():
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--coapcam", type=Path, default=ROOT / "target/release/coapcam")
    parser.add_argument("--scene", type=Path, default=ROOT / "scenes/demo.toml")
    parser.add_argument("--processes", type=int, default=50)
    parser.add_argument("--delay-ms", type=float, default=10.0, help="one-way delay")
    parser.add_argument("--loss", type=float, default=0.02, help="loss each way")
    parser.add_argument("--emulator", default="netem", choices=["netem", "relay.py"])
    parser.add_argument("--cache", default="both", choices=["on", "off", "both"])
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--json", type=Path, help="write every process's result here")
    args = parser.parse_args()
    coapcam = args.coapcam.resolve()
    if not coapcam.is_file():
        print(f"bench-first-request: {coapcam} not found", file=sys.stderr)
        return 1
    modes = ["on", "off"] if args.cache == "both" else [args.cache]

    with tempfile.TemporaryDirectory(prefix="bench-first-") as work:
        work = Path(work)
        port = free_udp_port()
        server = f"127.0.0.1:{port}"
        serve = subprocess.Popen(
            [str(coapcam), "serve", "--scene", str(args.scene), "--bind", server,
             "--state-dir", str(work / "state")],
            stdout=subprocess.DEVNULL, stderr=open(work / "serve.log", "w"))
        env = dict(os.environ, XDG_CACHE_HOME=str(work / "cache"))
        try:
            deadline = time.monotonic() + 60
            while True:
                prep = subprocess.run(
                    [str(coapcam), "measure", "--server", f"coap://{server}", "--prepare",
                     "--json"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                    env=dict(env, COAPCAM_RTT_CACHE="off"))
                if prep.returncode == 0:
                    break
                if time.monotonic() > deadline or serve.poll() is not None:
                    raise RuntimeError(f"the server did not measure: {prep.stderr[-500:]}")
                time.sleep(0.5)
            results = []
            for i in range(args.processes):
                for mode in modes:
                    seed = args.seed * 100_003 + i * 2 + (mode == "off")
                    relay, addr = start_relay(args.emulator, coapcam, server, args.delay_ms,
                                              args.loss, seed)
                    load = os.getloadavg()[0]
                    started = time.monotonic()
                    try:
                        done = subprocess.run(
                            [str(coapcam), "measure", "--server", f"coap://{addr}", "--all",
                             "--clouds", "--json"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=dict(env, COAPCAM_RTT_CACHE=mode), timeout=120)
                        took = time.monotonic() - started
                        ok = done.returncode == 0
                        err = done.stderr.strip()[-200:]
                    except subprocess.TimeoutExpired:
                        took, ok, err = 120.0, False, "over 120 s"
                    finally:
                        stop(relay)
                    results.append({"cache": mode, "process": i + 1, "seed": seed,
                                    "time_s": took, "ok": ok, "load1": load,
                                    "error": None if ok else err})
                    print(f"cache {mode} process {i + 1}/{args.processes}: {took:.3f} s "
                          f"{'ok' if ok else 'FAILED: ' + err} (load {load:.1f})",
                          file=sys.stderr, flush=True)
        finally:
            serve.terminate()
            serve.wait(timeout=20)

    print(f"`measure --all --clouds` of {args.scene.name} through {args.emulator}, "
          f"{args.delay_ms:g} ms each way, {args.loss * 100:g} % loss each way, "
          f"{args.processes} processes per mode; seconds of each whole process.")
    print()
    print("| remembered round trips | median | p95 | max | over 1 s | failed | load (median, max) |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for mode in modes:
        rs = [r for r in results if r["cache"] == mode]
        ok = [r["time_s"] for r in rs if r["ok"]]
        loads = [r["load1"] for r in rs]
        if ok:
            print(f"| {mode} | {statistics.median(ok):.3f} | {nearest_rank(ok, 0.95):.3f} | "
                  f"{max(ok):.3f} | {sum(t > 1.0 for t in ok)} | {len(rs) - len(ok)} | "
                  f"{statistics.median(loads):.1f}, {max(loads):.1f} |")
        else:
            print(f"| {mode} | - | - | - | - | {len(rs)} | - |")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
