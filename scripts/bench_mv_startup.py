"""CPU time of what the OPC 40100-1 Machine Vision model adds to `run-cell serve`'s start-up,
each step in a fresh process (as a start is), against the imports the service needs anyway.

    .venv/bin/python scripts/bench_mv_startup.py [--repeat 3]

Prints, per step, the median CPU seconds (user + system of that process, time.process_time):
- imports: `import cv2, numpy, asyncua, starlette, uvicorn` (the start-up goal's yardstick)
- init: asyncua's `Server.init()` alone (the standard address space; what the old server did)
- xml: init with the DI and Machine Vision NodeSets imported from XML (no cache)
- cold: the same, writing the address space cache (the first start after an install)
- warm: init from that cache (every later start)
- warm+model: warm, then the VisionSystemType object built and its methods bound
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

STEP = r"""
import time, sys, json, asyncio, logging
logging.disable(logging.WARNING)
t0 = time.process_time()
import cv2, numpy, asyncua, starlette, uvicorn
t_imports = time.process_time() - t0
step, cache = sys.argv[1], sys.argv[2]
from pathlib import Path
from asyncua import Server

async def main():
    t = time.process_time()
    server = Server()
    if step == "init":
        await server.init()
    else:
        from cell.service.mv_addressspace import init_server_with_models
        await init_server_with_models(server, None if step == "xml" else Path(cache))
        if step == "warm+model":
            from cell.config import CellConfig
            from cell.recipes import RecipeBook
            from cell.service.machinevision import MachineVisionServer
            from tests.mv_fake_service import FakeLineService
            book = RecipeBook(Path(cache) / "recipes")
            service = FakeLineService(book)
            mv = MachineVisionServer(server, service, CellConfig(), recipes=book)
            await mv.start()
            await mv.stop()
            service.close()
    return time.process_time() - t

print(json.dumps({"imports": t_imports, "step": asyncio.run(main())}))
"""


def run(step: str, cache: Path) -> dict:
    out = subprocess.run(
        [sys.executable, "-c", STEP, step, str(cache)],
        capture_output=True,
        text=True,
        check=True,
        cwd=Path(__file__).parents[1],
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    times: dict[str, list[float]] = {k: [] for k in ("imports", "init", "xml", "cold", "warm", "warm+model")}
    for _ in range(args.repeat):
        with tempfile.TemporaryDirectory() as tmp:
            cache = Path(tmp)
            for step in ("init", "xml", "cold", "warm", "warm+model"):
                r = run(step, cache)
                times[step].append(r["step"])
                times["imports"].append(r["imports"])
    base = statistics.median(times["imports"])
    for step, values in times.items():
        m = statistics.median(values)
        print(
            f"{step:11s} {m:6.2f} s CPU  ({m / base:4.1f}x the imports; {len(values)} runs, {min(values):.2f}-{max(values):.2f})"
        )


if __name__ == "__main__":
    main()
