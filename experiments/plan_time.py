"""How long ``--plan`` itself takes on a capture of Mip-NeRF 360's size, cold and warm.

    python -m experiments.plan_time [--data /tmp/plan360] [--json benchmarks/plan_time_<commit>.json]

Makes the capture when ``--data`` has none (``python -m patexgs_jax.data.synthetic DATA --num-views
300 --width 800 --height 533 --supersample 1 --num-points 20000``: 262 training and 38 test views of
800x533), then runs ``python -m patexgs_jax.train --data DATA --factor 1 --preset paper --method
patexgs --plan --json FILE`` twice, each in a fresh process: first with an empty compile cache
(``PATEXGS_CACHE`` a new folder), then with the cache the first left. For each it records the
wall time, the process's CPU time (user + system, from ``wait4``), the load average before, after
and at its highest (sampled every second), every line the plan printed with the wall and CPU
seconds at which it came, and the plan's JSON (``plan``). On a shared machine the CPU time is the
closer figure for an idle one.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from experiments.provenance import write_benchmark_json

SCHEMA = 1
SYNTHETIC = ["--num-views", "300", "--width", "800", "--height", "533", "--supersample", "1", "--num-points", "20000"]


def _cpu_seconds(pid: int) -> float | None:
    """User + system CPU seconds of a running process (Linux ``/proc/PID/stat``), or None."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def time_plan(data: str, cache: str, method: str = "patexgs") -> dict:
    """Runs the plan command once with ``PATEXGS_CACHE=cache``; returns its timings and lines."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "plan.json"
        cmd = [sys.executable, "-m", "patexgs_jax.train", "--data", data, "--factor", "1", "--preset", "paper",
               "--method", method, "--plan", "--json", str(out)]
        env = dict(os.environ, PATEXGS_CACHE=cache, PYTHONUNBUFFERED="1")
        loads, lines, done = [os.getloadavg()[0]], [], threading.Event()
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)

        def sample():
            while not done.wait(1.0):
                loads.append(os.getloadavg()[0])

        threading.Thread(target=sample, daemon=True).start()
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.append(dict(wall_s=round(time.perf_counter() - t0, 1), cpu_s=_cpu_seconds(proc.pid),
                              text=line.rstrip("\n")))
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        done.set()
        code = os.waitstatus_to_exitcode(status)
        plan = json.loads(out.read_text()) if out.exists() else None
    if isinstance(plan, list):
        plan = plan[0]
    if plan is not None:
        plan.pop("views", None)
    return dict(command=" ".join(cmd[1:]), exit_code=code, wall_s=round(wall, 1),
                cpu_s=round(usage.ru_utime + usage.ru_stime, 1), load_start=loads[0], load_end=os.getloadavg()[0],
                load_max=max(loads), lines=lines, plan=plan)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m experiments.plan_time",
                                 description="How long --plan itself takes on a capture of Mip-NeRF 360's size, "
                                             "cold and warm.")
    ap.add_argument("--data", default="/tmp/plan360", help="the capture (made there when missing)")
    ap.add_argument("--method", default="patexgs", help="the method planned (default patexgs)")
    ap.add_argument("--json", default=None, help="write the timings there (experiments.provenance's header)")
    args = ap.parse_args(argv)
    if not (Path(args.data) / "synthetic.json").exists():
        subprocess.run([sys.executable, "-m", "patexgs_jax.data.synthetic", args.data, *SYNTHETIC], check=True)
    results = []
    with tempfile.TemporaryDirectory() as cache:
        for kind in ("cold", "warm"):
            r = dict(cache=kind, **time_plan(args.data, cache, args.method))
            results.append(r)
            print(f"{kind}: {r['wall_s']:.0f} s wall, {r['cpu_s']:.0f} s CPU, load {r['load_start']:.1f} to "
                  f"{r['load_end']:.1f} (at most {r['load_max']:.1f}), exit {r['exit_code']}", flush=True)
    if args.json:
        write_benchmark_json(args.json, results, SCHEMA, data=args.data,
                             conditions="python -m experiments.plan_time: the plan command in fresh processes, "
                                        "compile cache empty (cold) then the one it left (warm)")
    return 0 if all(r["exit_code"] == 0 for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
