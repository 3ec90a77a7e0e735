"""The run plan (``--plan``) against real runs: predicted and measured peak memory and step times.

    python -m experiments.plan_check [--cases tiny-2dgs,tiny-patexgs,beer8-2dgs,...] [--beer DIR]
                                     [--json benchmarks/plan_check_cpu_<commit>.json]
    python -m experiments.plan_check --replan benchmarks/plan_check_cpu_1bbcb6d.json

Each case is a short real training run (``python -m patexgs_jax.train`` with fewer steps than its
preset, same caps and schedules otherwise) in a fresh process, and the plan of that same command
line (``--plan --json``) in another. The run's process reports its peak resident memory per stage
(the Linux high-water mark, ``VmHWM`` = ``ru_maxrss``, read and reset through /proc/self/clear_refs
at the end of the 2DGS stage and before evaluation: each stage's figure is its own peak, the first
one including loading and compiling) and the duration of each of its steps (wall time between
steps, host work included: what the plan's few steps measure), whose median per stage it keeps; the
plan's step figure is checked against the stage's mean over the steps that compiled nothing
(:func:`mean_step_seconds`). Processes are started through ``sh`` so they do not inherit this
process's high-water mark. The table gives the plan's figure, the run's and the error (plan / run
- 1). ``--replan FILE`` makes FILE's plans again with the current code, keeping its runs (which the
plan does not change), and names the commit of each (``plan_at``).

Cases: ``tiny-2dgs``, ``tiny-patexgs`` (the embedded scene, tiny preset, 300 + 100 steps);
``beer8-2dgs``, ``beer8-patexgs``, ``beer4-2dgs``, ``beer4-patexgs`` (the beer capture at
``--factor`` 8 and 4, cpu preset, 150 + 100 steps); for a GPU, ``beer1-patexgs``: beer at full size
(720 x 1280), the ``small`` preset's 7,000 steps of 2DGS and 7,000 texture steps, at most 200,000
Gaussians (about 8 minutes on one H200).

On a GPU the peaks are the device's (``peak_bytes_in_use``), which cannot be reset: each stage's
figure is the peak up to its end (the texture stage's is its own wherever it exceeds stage 1's).
Each plan and run compiles in an empty compilation cache of its own (``--cache cold``, the
default: the first run of a command line, whose peak holds its compiles) or in the user's
(``--cache shared``: the figures then depend on what ran before). ``--timeout S`` stops a run
after S seconds; its row then holds what the run measured until then (``incomplete``: the
stages' step times so far, the peaks of the stages it finished), written every 250 steps by the
run's process.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import signal
import statistics
import subprocess
import sys
import tempfile
import time

from experiments.bench_train import _high_water_bytes
from experiments.provenance import git_commit, write_benchmark_json, write_json

SCHEMA = 1
BEER = "/work/shared/data/beer"

#: case: (uses the beer capture, train's arguments)
CASES = {
    "tiny-2dgs": (False, ["--method", "2dgs", "--preset", "tiny", "--iters-2dgs", "300"]),
    "tiny-patexgs": (False, ["--method", "patexgs", "--preset", "tiny", "--iters-2dgs", "300", "--iters-tex", "100"]),
    "beer8-2dgs": (True, ["--factor", "8", "--method", "2dgs", "--preset", "cpu", "--iters-2dgs", "150"]),
    "beer8-patexgs": (True, ["--factor", "8", "--method", "patexgs", "--preset", "cpu", "--iters-2dgs", "150",
                             "--iters-tex", "100"]),
    "beer4-2dgs": (True, ["--factor", "4", "--method", "2dgs", "--preset", "cpu", "--iters-2dgs", "150"]),
    "beer4-patexgs": (True, ["--factor", "4", "--method", "patexgs", "--preset", "cpu", "--iters-2dgs", "150",
                             "--iters-tex", "100"]),
    "beer1-patexgs": (True, ["--factor", "1", "--method", "patexgs", "--preset", "small", "--iters-2dgs", "7000",
                             "--iters-tex", "7000", "--max-gaussians", "200000"]),
}


def _peak_bytes(reset: bool = False) -> int:
    """The peak memory so far: the device's on a GPU (never reset), else this process's resident
    high-water mark (``reset`` lowers it to the current resident memory)."""
    import jax

    stats = jax.local_devices()[0].memory_stats() if jax.default_backend() != "cpu" else None
    if stats and "peak_bytes_in_use" in stats:
        return int(stats["peak_bytes_in_use"])
    return _high_water_bytes(reset=reset)


def run_case(argv: list[str], partial: str | None = None) -> dict:
    """In its own process: trains ``python -m patexgs_jax.train argv`` and returns each stage's
    peak memory (bytes: :func:`_peak_bytes`), step durations (median seconds per stage) and the
    time it took; with ``partial``, also writes the figures so far to that file every 250 steps."""
    import statistics

    import jax
    import numpy as np

    import patexgs_jax.training.run as run_mod
    from patexgs_jax.training.cli import main
    from patexgs_jax.training.trainer import Trainer

    peaks: dict[str, int] = {}
    stamps: list[tuple[int, int, float]] = []  # (stage, step, time)
    active: dict[int, int] = {}  # step: active Gaussians (every 50 steps)
    before, after, evaluate = Trainer.before_step, Trainer.after_step, run_mod.evaluate
    t: dict[str, float | None] = {"start": None, "eval": None}

    def before_step(self, step):
        if t["start"] is None:
            t["start"] = time.perf_counter()
            stamps.append((0, step, t["start"]))
        if step == self.cfg.iters_2dgs and "stage1" not in peaks:
            peaks["stage1"] = _peak_bytes(reset=True)
        before(self, step)

    def after_step(self, step):
        after(self, step)
        jax.block_until_ready(self.scene.means)
        stamps.append((1 if step <= self.cfg.iters_2dgs else 2, step, time.perf_counter()))
        if step % 50 == 0:
            active[step] = int(np.asarray(self.scene.active).sum())
        if partial is not None and len(stamps) % 250 == 0:
            write_json(partial, dict(figures(time.perf_counter()), incomplete=True, peak_bytes_so_far=_peak_bytes()))

    def evaluate_(*a, **k):
        if t["eval"] is None:
            t["eval"] = time.perf_counter()
            peaks["stage1" if "stage1" not in peaks else "texture"] = _peak_bytes(reset=True)
        return evaluate(*a, **k)

    def figures(t_end):
        spans: dict[int, list[float]] = {1: [], 2: []}
        for (_, _, t0), (stage, _, t1) in zip(stamps, stamps[1:]):
            spans[stage].append(t1 - t0)
        return dict(peak_bytes=dict(stage1=peaks.get("stage1"), texture=peaks.get("texture"), eval=peaks.get("eval")),
                    step_seconds={("stage1" if k == 1 else "texture"): (statistics.median(v) if v else None)
                                  for k, v in spans.items()},
                    steps={("stage1" if k == 1 else "texture"): len(v) for k, v in spans.items()},
                    stage_seconds={("stage1" if k == 1 else "texture"): sum(v) for k, v in spans.items()},
                    train_seconds=sum(spans[1]) + sum(spans[2]), total_seconds=t_end - (t["start"] or t_end),
                    step_ms={("stage1" if k == 1 else "texture"): [round(x * 1e3, 1) for x in v]
                             for k, v in spans.items()},
                    active_gaussians=active)

    Trainer.before_step, Trainer.after_step, run_mod.evaluate = before_step, after_step, evaluate_
    code = main(argv)
    t_end = time.perf_counter()
    peaks["eval"] = _peak_bytes()
    return dict(figures(t_end), code=code, compiles=_run_compiles(argv))


def _run_compiles(argv: list[str]) -> dict | None:
    """The run's compile record from its ``summary.json`` (in its ``--out`` folder): the step
    programs it compiled (``step_programs``, the seconds those steps took), the steps at which they
    compiled, the Eq. 7 allocation's step and the growth events (with ``layout_changed``: a bucket
    overflowed, the step recompiled), and what it compiled ahead; None without a summary."""
    if "--out" not in argv:
        return None
    path = os.path.join(argv[argv.index("--out") + 1], "summary.json")
    if not os.path.exists(path):
        return None
    with open(path) as f:
        s = json.load(f)
    alloc = s.get("allocation") or {}
    return dict(step_programs=(s.get("compiles") or {}).get("step_programs"),
                step_compile_seconds=(s.get("compiles") or {}).get("step_seconds"),
                xla_programs=(s.get("compiles") or {}).get("xla_programs"),
                xla_seconds=(s.get("compiles") or {}).get("xla_seconds"),
                compiled_at_steps=s.get("compiled_at_steps"), allocation_step=alloc.get("step"),
                growth_events=[dict(step=e["step"], grown=e["grown"], layout_changed=e["layout_changed"])
                               for e in s.get("growth_events") or []],
                compile_ahead=s.get("compile_ahead"))


#: Whether each plan and run process gets an empty compilation cache of its own (``--cache cold``,
#: the default) or the user's (``--cache shared``). A CPU run's peak resident memory holds the
#: compiles it does itself (XLA's compiler in the process): a run whose programs come from the
#: cache peaked 40% lower on the embedded scene (docs/memory.md), so the figures of a shared cache
#: follow whatever ran before. Cold is the first run of a command line, the one a memory check guards.
CACHE_MODES = ("cold", "shared")
_cache_mode = {"mode": "cold"}


def _child(args: list[str], timeout: float | None = None, log: str | None = None) -> tuple[int | None, str, str]:
    """Runs ``python args`` through ``sh``; returns (exit status, None once ``timeout`` seconds
    passed; stdout; stderr). With ``log``, the child's output also goes to ``log``.{out,err} as it
    runs. Under ``--cache cold`` the child's compilation cache is an empty folder of its own."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [root, os.environ.get("PYTHONPATH")])))
    # `; exit $?` keeps sh from exec-ing the command in its own process (which keeps the high-water mark).
    cmd = ["sh", "-c", shlex.join([sys.executable, *args]) + "; exit $?"]
    with tempfile.TemporaryDirectory() as tmp:
        if _cache_mode["mode"] == "cold":
            env["PATEXGS_COMPILE_CACHE"] = os.path.join(tmp, "xla")
        out_path, err_path = (f"{log}.out", f"{log}.err") if log else (f"{tmp}/out", f"{tmp}/err")
        with open(out_path, "w") as out, open(err_path, "w") as err:
            proc = subprocess.Popen(cmd, stdout=out, stderr=err, text=True, env=env, start_new_session=True)
            try:
                code = proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
                code = None
        with open(out_path) as out, open(err_path) as err:
            return code, out.read(), err.read()


def check_case(name: str, beer: str, timeout: float | None = None, logs: str | None = None) -> dict:
    """One case: its plan, then its run (stopped after ``timeout`` seconds), each in a fresh
    process; the row of figures. With ``logs``, the children's output goes to files there."""
    uses_beer, argv = CASES[name]
    argv = (["--data", beer] if uses_beer else []) + argv
    log = (lambda part: os.path.join(logs, f"{name}.{part}")) if logs else (lambda part: None)
    with tempfile.TemporaryDirectory() as tmp:
        plan_json = os.path.join(tmp, "plan.json")
        t = time.perf_counter()
        code, out, err = _child(["-m", "patexgs_jax.train", *argv, "--plan", "--json", plan_json], log=log("plan"))
        plan_seconds = time.perf_counter() - t
        if code != 0:
            return dict(case=name, argv=argv, error=f"plan: exit {code}: {err.strip().splitlines()[-3:]}")
        with open(plan_json) as f:
            plan = json.load(f)
        partial = os.path.join(tmp, "partial.json")
        left = None if timeout is None else max(1.0, timeout - plan_seconds)
        t = time.perf_counter()
        code, out, err = _child(["-m", "experiments.plan_check", "--run-case",
                                 json.dumps([*argv, "--out", os.path.join(tmp, "run")]), "--partial", partial],
                                timeout=left, log=log("run"))
        if code is None and os.path.exists(partial):
            with open(partial) as f:
                run = dict(json.load(f), stopped_after_seconds=time.perf_counter() - t)
        elif code != 0:
            return dict(case=name, argv=argv, plan=plan, error=f"run: exit {code}: {err.strip().splitlines()[-3:]}")
        else:
            run = json.loads(out.strip().splitlines()[-1])
    row: dict = dict(case=name, argv=argv, plan_seconds=plan_seconds, gaussians=plan["gaussians"],
               texels_eq7=plan["texels_eq7"], measured_steps=plan["measured"]["steps"],
               timed_steps=plan["measured"].get("timed_steps"), plan_step_ms=plan["measured"].get("step_ms"),
               plan_measured=_plan_measured(plan),
               predicted=dict(peak_bytes=plan["peak_bytes"], step_seconds=plan["step_seconds"],
                              total_seconds=plan["total_seconds"],
                              time_terms_seconds=plan.get("time_terms_seconds"), ahead_steps=plan.get("ahead_steps")),
               measured=dict(peak_bytes=run["peak_bytes"], step_seconds=run["step_seconds"],
                             total_seconds=run["total_seconds"], steps=run["steps"],
                             stage_seconds=run.get("stage_seconds"), step_ms=run.get("step_ms"),
                             active_gaussians=run.get("active_gaussians"), compiles=run.get("compiles")))
    if run.get("incomplete"):
        row.update(incomplete=True, stopped_after_seconds=run["stopped_after_seconds"],
                   peak_bytes_so_far=run.get("peak_bytes_so_far"))
    row["relative_error"] = _errors(row)
    return row


def _plan_measured(plan: dict) -> dict:
    """The plan's measured compile and evaluation seconds (what its time terms are made of) and its
    Gaussian counts timed."""
    m = plan["measured"]
    keys = ("compile_stage1", "compile_texture", "eval_view", "eval_compile", "gaussians", "stage1_gaussians",
            "scale", "padded_sizes", "seconds")
    return {k: m.get(k) for k in keys}


#: A run's step that took this many times its stage's median compiled something.
COMPILE_STEP_RATIO = 5.0


def mean_step_seconds(step_ms: dict) -> dict:
    """Each stage's mean step in seconds over its steps that compiled nothing (those above
    :data:`COMPILE_STEP_RATIO` times the stage's median left out): what the plan's step figure is,
    the mean of the stage's steps with the compiles counted apart (a median flips between the steps
    beside the compile ahead and the others, wherever those are about half the stage)."""
    out = {}
    for k, v in step_ms.items():
        if v:
            keep = [x for x in v if x <= COMPILE_STEP_RATIO * statistics.median(v)]
            out[k] = sum(keep) / len(keep) * 1e-3
    return out


def _measured(row, group: str) -> dict:
    """The run's figures the plan's ``group`` is checked against: its peaks, and its steps' means
    (:func:`mean_step_seconds`; a row without its steps' times, its medians)."""
    m = row["measured"]
    if group == "step_seconds" and m.get("step_ms"):
        return mean_step_seconds(m["step_ms"])
    return m[group]


def _errors(row) -> dict:
    err = {}
    for group in ("peak_bytes", "step_seconds"):
        for k, p in row["predicted"][group].items():
            m = _measured(row, group).get(k)
            if p and m:
                err[f"{group}.{k}"] = p / m - 1
    if not row.get("incomplete"):
        err["total_seconds"] = row["predicted"]["total_seconds"] / row["measured"]["total_seconds"] - 1
    return err


def replan(row: dict) -> dict:
    """``row`` with its plan made again by the current code (``--plan``, timed), its run kept."""
    if "error" in row:
        return row
    with tempfile.TemporaryDirectory() as tmp:
        plan_json = os.path.join(tmp, "plan.json")
        t = time.perf_counter()
        code, _, err = _child(["-m", "patexgs_jax.train", *row["argv"], "--plan", "--json", plan_json])
        if code != 0:
            raise RuntimeError(f"plan of {row['case']}: exit {code}: {err.strip().splitlines()[-3:]}")
        with open(plan_json) as f:
            plan = json.load(f)
    row = dict(row, plan_seconds=time.perf_counter() - t, plan_at=git_commit(),
               measured_steps=plan["measured"]["steps"], timed_steps=plan["measured"].get("timed_steps"),
               plan_step_ms=plan["measured"].get("step_ms"), plan_gaussians=plan["gaussians"],
               plan_measured=_plan_measured(plan),
               predicted=dict(peak_bytes=plan["peak_bytes"], step_seconds=plan["step_seconds"],
                              total_seconds=plan["total_seconds"], time_terms_seconds=plan.get("time_terms_seconds"),
                              ahead_steps=plan.get("ahead_steps")))
    row["relative_error"] = _errors(row)
    return row


def _fmt(x, unit):
    if x is None:
        return "-"
    return f"{x / 2**20:.0f} MiB" if unit == "B" else f"{x * 1e3:.0f} ms" if unit == "s" else f"{x:.0f} s"


def table(rows) -> str:
    lines = ["| case | figure | plan | run | error |", "|---|---|---:|---:|---:|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['case']} | failed: {r['error']} | | | |")
            continue
        for group, unit in (("peak_bytes", "B"), ("step_seconds", "s")):
            for k, p in r["predicted"][group].items():
                m = _measured(r, group).get(k)
                if not p:  # (an untextured method has no texture stage: it continues stage 1)
                    continue
                e = r["relative_error"].get(f"{group}.{k}")
                lines.append(f"| {r['case']} | {group}.{k} | {_fmt(p, unit)} | {_fmt(m, unit)} | "
                             f"{'-' if e is None else f'{e:+.0%}'} |")
        e = r["relative_error"].get("total_seconds")
        measured = _fmt(r["measured"]["total_seconds"], "T") + (" (stopped)" if r.get("incomplete") else "")
        lines.append(f"| {r['case']} | total_seconds | {_fmt(r['predicted']['total_seconds'], 'T')} | "
                     f"{measured} | {'-' if e is None else f'{e:+.0%}'} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m experiments.plan_check", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", default=",".join(CASES), help=f"comma-separated, of {', '.join(CASES)}")
    ap.add_argument("--beer", default=BEER, help=f"the beer capture (default {BEER})")
    ap.add_argument("--json", default=None, help="write the rows there (experiments.provenance's header)")
    ap.add_argument("--timeout", type=float, default=None, metavar="S",
                    help="stop a case's plan + run after S seconds and keep what the run measured until then")
    ap.add_argument("--logs", default=None, metavar="DIR",
                    help="keep each plan's and run's output in DIR/<case>.{plan,run}.{out,err}")
    ap.add_argument("--cache", choices=CACHE_MODES, default="cold",
                    help="cold (default): each plan and run compiles everything, in an empty compilation cache of "
                    "its own; shared: the user's cache (figures then depend on what ran before)")
    ap.add_argument("--run-case", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--partial", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--replan", default=None, metavar="FILE",
                    help="make FILE's plans again with the current code (each in a fresh process), keep its runs, "
                    "and write the rows to --json (default: FILE); with --cases, those cases' rows only")
    args = ap.parse_args(argv)
    _cache_mode["mode"] = args.cache
    if args.replan is not None:
        with open(args.replan) as f:
            doc = json.load(f)
        only = None if args.cases == ",".join(CASES) else {c.strip() for c in args.cases.split(",")}
        rows = []
        for r in doc["results"]:
            if only is not None and r.get("case") not in only:
                continue
            rows.append(replan(r))
            print(table([rows[-1]]).split("\n", 2)[-1], flush=True)
        doc = dict(doc, results=rows, replanned=f"plans made again at {git_commit()}; runs from {doc.get('git')}",
                   replan_compile_cache=args.cache)
        write_json(args.json or args.replan, doc)
        print(table(rows))
        return 0
    if args.run_case is not None:
        print(json.dumps(run_case(json.loads(args.run_case), partial=args.partial)))
        return 0
    if args.logs:
        os.makedirs(args.logs, exist_ok=True)
    names = [c.strip() for c in args.cases.split(",") if c.strip()]
    unknown = [c for c in names if c not in CASES]
    if unknown:
        ap.error(f"unknown case(s) {', '.join(unknown)}; choose from {', '.join(CASES)}")
    if any(CASES[c][0] for c in names) and not os.path.isdir(args.beer):
        ap.error(f"--beer {args.beer}: no such folder (the beer capture, COLMAP layout)")
    rows = []
    for name in names:
        row = check_case(name, args.beer, timeout=args.timeout, logs=args.logs)
        rows.append(row)
        print(table([row]).split("\n", 2)[-1], flush=True)
        if args.json:  # after every case: a stopped check keeps what it measured
            write_benchmark_json(args.json, rows, SCHEMA, mode="plan_check", compile_cache=args.cache)
    print()
    print(table(rows))
    return 1 if any("error" in r for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
