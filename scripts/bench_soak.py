"""Soak: a simulated shift of at least --picks picks through `run-cell serve`, driven over OPC UA.

Starts `run-cell serve --dry-run --config <shift>` in a subprocess (the built-in simulated
cell, its camera `--camera` pixels, the feeder at 6 parts per simulated minute with time
running 60x: 360 parts a minute, more than the cell picks, so it never idles), calls
StartContinuous, and samples the server process (RSS, threads, open fds, child processes)
from /proc while the counters rise. At the end: Stop, SIGTERM, and the audit log and the history
store (a dry run's own, data/rehearsal/history.sqlite: picked rows, unique ids, PRAGMA integrity_check) checked against
the counters.

At 1920 x 1080 (the built-in camera) the cell runs as shipped: the drift watch on, over the
simulated table's reference marks. Smaller cameras do not resolve the 1.5 mm marks (run-cell
neither), so there the shift config turns them off.

    .venv/bin/python scripts/bench_soak.py [--picks 2000] [--camera 1920x1080] [--speed-factor 60] [--timeout-s 3600]
        [--count-objects [EVERY_S] [--trace]]

With --count-objects the server counts its Python objects by type (every 2 minutes by default)
(scripts/serve_counting_objects.py) and the bench prints the types that grew most, and RSS
against the object count at each count: a growth no type follows is the C allocator's.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import select
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from asyncua import Client

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from cell.audit import read_events  # noqa: E402
from cell.history.config import REHEARSAL_DIR  # noqa: E402
from tests.ports import free_port  # noqa: E402

SHIFT_TOML = """\
[camera]
width_px = {width}
height_px = {height}
[service]
capture_interval_s = {speed}   # simulated: 1 s of wall time
[sim]
speed_factor = {speed}
{marks}
[sim.feeder]
parts_per_minute = 6.0
max_on_table = 25
"""
PICK_2000 = 2000  # a long soak's reference point
FULL_HD = (1920, 1080)  # the built-in simulated camera, the default config's


def shift_toml(width: int, height: int, speed: float = 60.0) -> str:
    """The soak's config: the shipped simulated shift at this camera size, faster."""
    marks = "" if (width, height) == FULL_HD else "reference_marks_mm = []  # too small to find at this size"
    return SHIFT_TOML.format(width=width, height=height, marks=marks, speed=speed)


def camera_size(text: str) -> tuple[int, int]:
    """`--camera WIDTHxHEIGHT`, e.g. 1920x1080."""
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: give the camera size as WIDTHxHEIGHT, e.g. 1920x1080") from None
    if not (16 <= width <= 20000 and 16 <= height <= 20000):
        raise argparse.ArgumentTypeError(f"{text!r}: each side 16-20000 px (camera.width_px, camera.height_px)")
    return width, height


def proc_figures(pid: int) -> dict:
    status = Path(f"/proc/{pid}/status").read_text()
    rss_kb = int(next(line for line in status.splitlines() if line.startswith("VmRSS:")).split()[1])
    threads = len(os.listdir(f"/proc/{pid}/task"))
    fds = len(os.listdir(f"/proc/{pid}/fd"))
    children = sum(
        len(Path(f"/proc/{pid}/task/{t}/children").read_text().split()) for t in os.listdir(f"/proc/{pid}/task")
    )
    stat = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    cpu_s = (int(stat[11]) + int(stat[12])) / os.sysconf("SC_CLK_TCK")  # utime + stime
    return {"rss_mb": rss_kb / 1024, "threads": threads, "fds": fds, "children": children, "cpu_s": cpu_s}


def memory_kinds(pid: int) -> str:
    """RSS by kind (/proc/PID/smaps_rollup): anonymous memory (the heap, arrays) and file-backed
    (code, shared libraries)."""
    rows = dict(line.split(":", 1) for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines()[1:])
    mb = {k: int(rows[k].split()[0]) / 1024 for k in ("Rss", "Anonymous")}
    return f"anonymous {mb['Anonymous']:.1f} MB, file-backed and shared {mb['Rss'] - mb['Anonymous']:.1f} MB"


async def drive(url: str, pid: int, picks: int, timeout_s: float) -> dict[str, Any]:
    async with Client(url, timeout=10, watchdog_intervall=15) as client:
        ns = await client.get_namespace_index("urn:pick-cell")
        cell = await client.nodes.objects.get_child(f"{ns}:Cell")

        async def read(name):
            return await (await cell.get_child(f"{ns}:{name}")).read_value()

        earlier_shifts = 0  # the shift's counters start again at a shift change ([shifts], wall clock)
        last = 0

        async def total():
            nonlocal earlier_shifts, last
            now = await read("PickedBolts") + await read("PickedNuts")
            if now < last:
                earlier_shifts += last
            last = now
            return earlier_shifts + now

        out: dict[str, Any] = {"start": proc_figures(pid), "start_kinds": memory_kinds(pid)}
        t0 = time.monotonic()
        await cell.call_method(f"{ns}:StartContinuous")
        states, last_print, samples = set(), 0, []  # (picks, RSS MB) four times a second
        while (n := await total()) < picks:
            states.add(await read("VisionState"))
            if n >= 100 and "at_100" not in out:
                out["at_100"] = proc_figures(pid)
            if n >= 100:
                samples.append((n, proc_figures(pid)["rss_mb"]))
            if time.monotonic() - t0 > timeout_s:
                raise SystemExit(f"timed out after {timeout_s} s at {n} picks")
            if n - last_print >= 250:
                f = proc_figures(pid)
                print(
                    f"  {n:5d} picks  {time.monotonic() - t0:6.0f} s  RSS {f['rss_mb']:.1f} MB  threads {f['threads']}"
                    f"  fds {f['fds']}",
                    flush=True,
                )
                last_print = n
            await asyncio.sleep(0.25)
        await cell.call_method(f"{ns}:Stop")
        while await read("VisionState") != "Ready":
            await asyncio.sleep(0.2)
        out["wall_s"] = time.monotonic() - t0
        # RSS swings by a frame's worth of arrays from one sample to the next: compare the peaks
        # of the first and the last 250 picks after pick 100, each over the same kind of work.
        early = [r for k, r in samples if k < 350]
        late = [r for k, r in samples if k >= picks - 250]
        out["peak_early"], out["peak_late"] = max(early), max(late)
        out["median_early"], out["median_late"] = statistics.median(early), statistics.median(late)
        # the yardstick for a long shift: the end against pick 2,000 (once the results kept
        # for OPC 40100 and the other bounded records have filled), over the same kind of stretch
        at_2000 = [r for k, r in samples if PICK_2000 <= k < PICK_2000 + 250]
        out["peak_2000"] = max(at_2000) if picks >= PICK_2000 + 500 and at_2000 else None
        out["end"] = proc_figures(pid)
        out["end_kinds"] = memory_kinds(pid)
        out["states"] = states
        out["counters"] = {
            name: await read(name)
            for name in ("PickedBolts", "PickedNuts", "Misses", "Retries", "Failed", "Unreachable", "UnknownLeft")
        }
        out["alarm"] = await read("ActiveAlarm")
        out["picks"] = await total()  # over every shift the run crossed
        out["earlier_shifts"] = earlier_shifts
        return out


def history_figures(path: Path) -> dict:
    """The store's side of the soak: what it holds, and whether the file is sound."""
    import sqlite3

    db = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        return {
            "picked": db.execute("SELECT count(*) FROM picks WHERE outcome = 'picked'").fetchone()[0],
            "rows": db.execute("SELECT count(*) FROM picks").fetchone()[0],
            "unique": db.execute("SELECT count(DISTINCT id) FROM picks").fetchone()[0],
            "integrity": db.execute("PRAGMA integrity_check").fetchone()[0],
            "images": db.execute("SELECT count(*) FROM images").fetchone()[0],
        }
    finally:
        db.close()


def print_object_growth(path: Path) -> None:
    """RSS and the live object count at each count, and the types that grew most from the second count on."""
    lines = [json.loads(x) for x in path.read_text().splitlines()] if path.exists() else []
    if len(lines) < 3:
        print(f"object counts: {len(lines)} taken, too few to compare (a longer run takes more)")
        return
    print("object counts (RSS MB / live objects): " + ", ".join(f"{x['rss_mb']:.0f}/{x['objects']}" for x in lines))
    if lines[-1].get("malloc"):
        print(
            "C allocator at each count (MB in use / free but held / mapped big blocks): "
            + ", ".join(
                f"{m['in_use_mb']:.0f}/{m['free_held_mb']:.0f}/{m['mmapped_mb']:.0f}"
                for m in (x["malloc"] for x in lines)
            )
        )
    if "traced_mb" in lines[-1]:
        print("traced by Python at each count (MB): " + ", ".join(f"{x['traced_mb']:.1f}" for x in lines))
        print("source lines whose traced memory grew most, first count to last:")
        for row in lines[-1]["traced_growth_since_first"]:
            print(f"  {row}")
    first, last = lines[1]["types"], lines[-1]["types"]
    grew = sorted(((last.get(k, 0) - first.get(k, 0), k) for k in set(first) | set(last)), reverse=True)[:8]
    print("types that grew most from the second count to the last: " + ", ".join(f"{k} +{n}" for n, k in grew if n > 0))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--picks", type=int, default=2000)
    ap.add_argument(
        "--camera",
        type=camera_size,
        default=(960, 540),
        help="the simulated camera's size, WIDTHxHEIGHT (default 960x540; 1920x1080 is the shipped cell, drift watch on)",
    )
    ap.add_argument("--timeout-s", type=float, default=3600.0)
    ap.add_argument(
        "--speed-factor",
        type=float,
        default=60.0,
        help="simulated time's speed (default 60): higher makes a long soak shorter where the CPU keeps up",
    )
    ap.add_argument(
        "--trace",
        action="store_true",
        help="with --count-objects: also trace the Python allocations (tracemalloc; slower) and print what grew",
    )
    ap.add_argument(
        "--count-objects",
        type=float,
        nargs="?",
        const=120.0,
        metavar="EVERY_S",
        help="count the server's Python objects by type, every EVERY_S seconds (120 by default)",
    )
    args = ap.parse_args()
    load_start = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="soak-") as tmp_name:
        tmp = Path(tmp_name)
        (tmp / "shift.toml").write_text(shift_toml(args.camera[0], args.camera[1], args.speed_factor))
        print(f"camera {args.camera[0]} x {args.camera[1]}; drift watch {'on' if args.camera == FULL_HD else 'off'}")
        port = free_port()
        counts = tmp / "object-counts.jsonl"
        runner = (
            [
                str(REPO / "scripts" / "serve_counting_objects.py"),
                "--out",
                str(counts),
                "--every-s",
                str(args.count_objects),
                *(["--trace"] if args.trace else []),
                "--",
            ]
            if args.count_objects
            else ["-m", "cell.cli"]
        )
        cmd = [
            sys.executable,
            *runner,
            "serve",
            "--dry-run",
            "--config",
            str(tmp / "shift.toml"),
            "--log-dir",
            str(tmp / "logs"),
            "--opcua-port",
            str(port),
            "--http-port",
            str(free_port()),
        ]
        proc = subprocess.Popen(
            cmd,
            cwd=tmp,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env={**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))},
        )
        out = proc.stdout
        assert out is not None  # stdout=PIPE
        try:
            line = ""
            while not line.startswith("ready:"):
                if not select.select([out], [], [], 120)[0] or proc.poll() is not None:
                    raise SystemExit(f"serve did not start: {line}")
                line = out.readline()
            print(line.strip())
            print(f"RSS at ready {proc_figures(proc.pid)['rss_mb']:.1f} MB ({memory_kinds(proc.pid)})", flush=True)
            r = asyncio.run(drive(f"opc.tcp://127.0.0.1:{port}/cell", proc.pid, args.picks, args.timeout_s))
        finally:
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
            rc = proc.wait(60)
        events = [e for f in sorted((tmp / "logs").glob("cell-*.jsonl")) for e in read_events(f)]
        files = len(list((tmp / "logs").glob("cell-*.jsonl")))
        store = history_figures(tmp / "data" / REHEARSAL_DIR / "history.sqlite")  # a dry run's own store
        if args.count_objects:
            print_object_growth(counts)
    c = r["counters"]
    picks = r["picks"]
    if r["earlier_shifts"]:
        print(f"a shift change during the run: {r['earlier_shifts']} picks counted by the earlier shift(s)")
    picked_lines = sum(1 for e in events if e["kind"] == "verify" and e["result"] == "picked")
    faults = sum(1 for e in events if e["kind"] == "fault")
    s, a, e = r["start"], r["at_100"], r["end"]
    print(
        f"picks {picks} (this shift's: {c['PickedBolts']} bolts, {c['PickedNuts']} nuts) in {r['wall_s']:.0f} s wall "
        f"({60 * picks / r['wall_s']:.0f} per minute); misses {c['Misses']}, retries {c['Retries']}, "
        f"failed {c['Failed']}, unreachable {c['Unreachable']}, unknown left {c['UnknownLeft']}"
    )
    print(
        f"server CPU {e['cpu_s'] - s['cpu_s']:.0f} s for {picks} picks: {1000 * (e['cpu_s'] - s['cpu_s']) / max(picks, 1):.0f} ms a pick"
    )
    print(f"faults {faults}; vision states seen: {', '.join(sorted(r['states']))}; alarm: {r['alarm'] or 'none'}")
    print(
        f"RSS start {s['rss_mb']:.1f} MB, at pick 100 {a['rss_mb']:.1f} MB, end {e['rss_mb']:.1f} MB "
        f"(growth from pick 100: {100 * (e['rss_mb'] / a['rss_mb'] - 1):+.1f} %)"
    )
    print(
        f"RSS over picks 100-350 vs the last 250 picks: peak {r['peak_early']:.1f} -> {r['peak_late']:.1f} MB "
        f"({100 * (r['peak_late'] / r['peak_early'] - 1):+.1f} %), median {r['median_early']:.1f} -> "
        f"{r['median_late']:.1f} MB ({100 * (r['median_late'] / r['median_early'] - 1):+.1f} %)"
    )
    if r["peak_2000"] is not None:
        print(
            f"RSS over picks 2000-2250 vs the last 250 picks: peak {r['peak_2000']:.1f} -> {r['peak_late']:.1f} MB "
            f"({100 * (r['peak_late'] / r['peak_2000'] - 1):+.1f} %; flat: within 5 %)"
        )
    print(f"RSS by kind at start: {r['start_kinds']}; at the end: {r['end_kinds']}")
    print(
        f"threads start {s['threads']}, at pick 100 {a['threads']}, end {e['threads']}; "
        f"fds start {s['fds']}, at pick 100 {a['fds']}, end {e['fds']}; child processes at end {e['children']}"
    )
    print(
        f"audit: {len(events)} lines in {files} file(s); 'picked' lines {picked_lines} vs picks {picks}; "
        f"serve exit code {rc}"
    )
    print(
        f"history store: {store['picked']} picked rows of {store['rows']} picks, {store['unique']} unique ids; "
        f"integrity_check {store['integrity']}; {store['images']} images"
    )
    ok = (
        faults == 0
        and picked_lines == picks
        and store["picked"] == picks
        and store["unique"] == store["rows"]
        and store["integrity"] == "ok"
        and rc == 0
        and e["threads"] <= a["threads"]
        and e["fds"] <= a["fds"]
        and r["peak_late"] < 1.05 * (r["peak_2000"] or r["peak_early"])
    )
    load_end = os.getloadavg()
    print(
        f"load average (1, 5, 15 min): at start {load_start[0]:.2f} {load_start[1]:.2f} {load_start[2]:.2f}, "
        f"at end {load_end[0]:.2f} {load_end[1]:.2f} {load_end[2]:.2f}"
    )
    print("PASS" if ok else "FAIL")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
