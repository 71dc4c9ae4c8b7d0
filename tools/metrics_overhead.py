"""What ``fr track --metrics`` costs a running fleet: frames searched per second with and without the
metrics server (scraped every ``--scrape-every`` seconds), in runs alternating off, on, on, off, ...

N synthetic cameras (320 x 240, 25 frames/s, :mod:`fr_eval.datasets.live_stream`) are served by
threads of this process; each run is one ``fr track URL1 ... URLN --fast`` process.  Once every
camera has its first record, the records written in the next ``--seconds`` are counted, and the
CPU time the fleet's processes (its session: the fleet and its search workers) used meanwhile, read
from ``/proc``: on a machine that other work keeps busy, CPU seconds per frame say what the
metrics cost where frames per second mostly say what the other work took::

    python tools/metrics_overhead.py --cameras 16 --seconds 40 --repeats 2
"""
from __future__ import annotations

import argparse
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

from fr_eval.datasets.live_stream import MJPEGServer, SyntheticCamera
from fr_eval.machine import session_cpu_s


def _records(out: Path) -> int:
    return sum(max(0, len(path.read_bytes().splitlines()) - 1) for path in out.glob("*/frames.csv"))


def run(urls: list[str], seconds: float, metrics_port: int | None, scrape_every: float) -> tuple[float, float, int]:
    """Frames searched per second by one fleet run, its CPU seconds per frame, and the metrics pages
    read meanwhile."""
    with tempfile.TemporaryDirectory(prefix="fr-metrics-") as folder:
        out = Path(folder) / "out"
        command = [sys.executable, "-m", "fr_torch.cli", "track", *urls, "--out", str(out), "--fast", "--no-progress"]
        if metrics_port is not None:
            command += ["--metrics", f"127.0.0.1:{metrics_port}"]
        process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                   start_new_session=True)
        pages, stop = [], threading.Event()

        def scrape() -> None:
            while not stop.wait(scrape_every):
                try:
                    with urllib.request.urlopen(f"http://127.0.0.1:{metrics_port}/metrics", timeout=5) as response:
                        pages.append(len(response.read()))
                except OSError:
                    pass

        scraper = threading.Thread(target=scrape, daemon=True)
        if metrics_port is not None:
            scraper.start()
        try:
            deadline = time.monotonic() + 300
            while sum(1 for p in out.glob("*/frames.csv") if len(p.read_bytes().splitlines()) > 1) < len(urls):
                if process.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError("the fleet did not start")
                time.sleep(0.2)
            start, first, cpu = time.monotonic(), _records(out), session_cpu_s(process.pid)
            time.sleep(seconds)
            count, elapsed = _records(out) - first, time.monotonic() - start
            cpu = session_cpu_s(process.pid) - cpu
        finally:
            stop.set()
            os.killpg(process.pid, signal.SIGTERM)
            process.wait(60)
        return count / elapsed, cpu / max(count, 1), len(pages)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cameras", type=int, default=16)
    parser.add_argument("--seconds", type=float, default=40.0)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--scrape-every", type=float, default=1.0)
    parser.add_argument("--port", type=int, default=19464)
    args = parser.parse_args()
    servers = [MJPEGServer(SyntheticCamera(width=320, height=240, hfov_deg=50 + 3 * k, room_seed=k), fps=25).start()
               for k in range(args.cameras)]
    urls = [server.url for server in servers]
    rates: dict[str, list[float]] = {"off": [], "on": []}
    cpus: dict[str, list[float]] = {"off": [], "on": []}
    for repeat in range(args.repeats):
        for arm in (("off", "on") if repeat % 2 == 0 else ("on", "off")):
            rate, cpu, pages = run(urls, args.seconds, args.port if arm == "on" else None, args.scrape_every)
            rates[arm].append(rate)
            cpus[arm].append(cpu)
            print(f"run {repeat + 1} metrics {arm}: {rate:.2f} frames/s, {cpu:.3f} CPU s per frame, load average "
                  f"{os.getloadavg()[0]:.1f}" + (f", {pages} pages scraped" if arm == "on" else ""), flush=True)
    off, on = statistics.mean(rates["off"]), statistics.mean(rates["on"])
    cpu_off, cpu_on = statistics.mean(cpus["off"]), statistics.mean(cpus["on"])
    print(f"{args.cameras} cameras, {args.seconds:g} s x {args.repeats}: {off:.2f} frames/s without, {on:.2f} with "
          f"metrics scraped every {args.scrape_every:g} s ({100 * (on / off - 1):+.1f} %); CPU s per frame "
          f"{cpu_off:.3f} without, {cpu_on:.3f} with ({100 * (cpu_on / cpu_off - 1):+.1f} %)")
    for server in servers:
        server.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
